"""What every benchmark ends with: its rows as a table on stdout, and as JSON."""

from __future__ import annotations

import json
from pathlib import Path


def write_report(rows: list[dict], cols: list[str], out: str | Path, **meta) -> Path:
    """Print `rows` as a ' | '-separated table of `cols`, write {**meta, "rows": rows} to `out`."""
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(str(r[c]) for c in cols))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({**meta, "rows": rows}, indent=2))
    return out
