"""Progress bars on stderr (tqdm), shown when stderr is a terminal unless asked otherwise."""

from __future__ import annotations

import sys


def bar(total: int | None, desc: str, progress: bool | None = None, unit: str = "it"):
    """A tqdm bar for `total` steps; `progress` None: only when stderr is a terminal."""
    from tqdm import tqdm

    shown = sys.stderr.isatty() if progress is None else progress
    return tqdm(total=total, desc=desc, unit=unit, disable=not shown, file=sys.stderr, leave=False)


def track(items, total: int | None, desc: str, progress: bool | None = None, unit: str = "it"):
    """The items, advancing a bar (see bar()) by one per item; the bar closes at the end."""
    with bar(total, desc, progress, unit) as steps:
        for item in items:
            yield item
            steps.update(1)
