"""`python -m voxtool.cli`."""

from voxtool.cli import run

run()
