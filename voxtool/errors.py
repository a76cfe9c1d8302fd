"""One exception root for everything voxtool reports to a user.

Every message names the file (or parameter) and what is wrong with it, so the CLI can print it
as a single line and exit non-zero.
"""

from __future__ import annotations


class VoxtoolError(Exception):
    """Root of all errors voxtool raises on bad input or bad parameters."""

    exit_code = 1


class ParameterError(VoxtoolError):
    """A parameter (CLI option, config value) is out of its valid range."""

    exit_code = 2


class SourceError(VoxtoolError):
    """A scan source (PCD, PLY, MCAP, graph, pose file) is missing or malformed."""

    exit_code = 3


class KeyRangeError(VoxtoolError):
    """A point or sensor origin lies outside the octree's addressable key range."""

    exit_code = 4


class FormatError(VoxtoolError):
    """A file voxtool reads back (snapshot, packet log, .bt) is malformed."""

    exit_code = 5


class RegressionError(VoxtoolError):
    """`stats --compare` found figures that drifted beyond tolerance."""

    exit_code = 6
