"""The errors mistool raises for bad input.

Library code raises these and never prints or exits; the command line catches
:class:`MistoolError`, prints ``mistool: error: <message>`` on one line and returns a
non-zero exit code. Anything else escaping is a bug and keeps its traceback.

Messages say where (file, frame, key), what was expected, what was found, and the fix
when it is obvious.
"""

from __future__ import annotations


class MistoolError(Exception):
    """Base class of every error caused by the user's input."""


class InputPathError(MistoolError):
    """A path is missing, empty, unreadable, or not what a command expects."""


class MaskFormatError(MistoolError):
    """A mask image or video is corrupt, has the wrong shape/dtype, or changes size."""


class ConfigError(MistoolError):
    """``mistool.toml`` or a command-line option is invalid."""


class TableError(MistoolError):
    """A motion table (CSV) is malformed or lacks required columns."""


class InputWarning(UserWarning):
    """Something odd about the input that does not stop the command (a mask video that
    ends early, a ``source`` video that disagrees with the masks); the command line
    prints it as one ``mistool: warning: ...`` line."""


class MistoolWarning(UserWarning):
    """Something in the input is unusual but not an error (e.g. unknown label values, or
    camera intrinsics scaled to the masks' size)."""
