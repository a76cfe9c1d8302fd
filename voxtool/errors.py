"""One exception root for everything voxtool reports to a user.

Every message names the file (or parameter) and what is wrong with it, so the CLI can print it
as a single line and exit non-zero.
"""

from __future__ import annotations


class VoxtoolWarning(UserWarning):
    """Something a user should know that does not stop the work (a file beside the input that
    could not be used); the command line prints it as one `voxtool: warning:` line."""


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


class ChangeLimitError(VoxtoolError):
    """`diff --max-changed` found more voxels that changed state than allowed."""

    exit_code = 7


def first_line(err: Exception) -> str:
    """An exception's first line of text (a C++ library's errors run over several), or its type."""
    return (str(err).strip().splitlines() or [type(err).__name__])[0]


def mcap_problem(err: Exception) -> str:
    """What is wrong with an MCAP file, from the mcap library's exception, in plain words."""
    import struct

    from mcap.exceptions import EndOfFile, InvalidMagic, RecordLengthLimitExceeded

    if isinstance(err, RecordLengthLimitExceeded):
        return "a record declares more bytes than any record may hold: the file is truncated or corrupt"
    if isinstance(err, EndOfFile | EOFError | struct.error):
        return "it ends inside a record: the file is truncated"
    if isinstance(err, InvalidMagic):
        return "it does not start (or end) with the MCAP magic: not an MCAP file, or a truncated one"
    text = str(err)
    if "crc" in text.lower():
        return f"a CRC does not match: the file is corrupt ({text})"
    return f"it is corrupt ({type(err).__name__}: {text})"
