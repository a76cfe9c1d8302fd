"""The README's two set-up commands are the ones CI runs."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ci_runs_the_readme_commands():
    readme = (ROOT / "README.md").read_text()
    block = re.search(r"```bash\n(.*?)```", readme, re.S).group(1).strip().splitlines()
    assert len(block) == 2
    assert "voxtool build --sample" in block[0] and "pytest" in block[1]
    ci = (ROOT / ".ci" / "run").read_text()
    for command in block:
        core = command.replace("pip install -e", "pip install -q -e").replace("python -m pytest", "python -m pytest -q")
        core = core.replace("apt-get update && apt-get install -y", "apt-get update -qq && apt-get install -y -qq")
        assert core in ci, command


def test_every_install_hint_names_the_distribution():
    """"voxtool" on the package index is another project: `pip install 'voxtool[odometry]'` would
    install it. The distribution is named in pyproject.toml, voxtool.DISTRIBUTION and every hint
    (code, README, docs), and it is the one installed here that provides the voxtool package."""
    from importlib.metadata import packages_distributions

    import tomllib

    import voxtool

    name = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["name"]
    assert voxtool.DISTRIBUTION == name != "voxtool"
    hints = []
    for path in [ROOT / "README.md", *(ROOT / "docs").rglob("*.md"), *(ROOT / "voxtool").rglob("*.py")]:
        hints += re.findall(r"pip install '([\w.-]+)\[", path.read_text())
    assert hints and {h for h in hints if h != "{DISTRIBUTION}"} == {name}, hints
    assert name in packages_distributions()["voxtool"]
