"""The errors pipe_nav_core raises about what it is given (a bag, a CSV, a setting, a path):
every exception class of the package, in this one module.

Every one derives from :class:`PipeNavError`, so a caller catches them all in one clause and
tells them from a bug; the command line prints each as one line naming the input and exits 2,
and prints anything else as an internal error (``pipe-nav --debug`` shows its traceback).
:class:`InputError` is also a ValueError: the content of a file or a value is wrong.
"""

from __future__ import annotations


class PipeNavError(Exception):
    """Something pipe_nav_core was given cannot be used; the message is one line for people,
    naming the input (``bags/x.mcap: not an MCAP file (bad magic)``)."""


class InputError(PipeNavError, ValueError):
    """The content of a file, or a value, the user gave is wrong."""


class ConfigError(InputError):
    """An invalid estimator or node setting; the message names the setting (as the user gave
    it: ``--set KEY``, a YAML key, a ROS parameter) and what is allowed."""


class BagFormatError(PipeNavError):
    """A bag file is not of the form it should be (a one-line reason, without the path: the
    bag reader adds it when it turns this into a :class:`BagError`)."""


class McapFormatError(BagFormatError):
    """The file is not MCAP at all (a one-line reason, without the path)."""


class BagError(PipeNavError):
    """A bag cannot be read or written. The message is one human-readable line, starting with
    the path, e.g. ``bags/x.mcap: not an MCAP file (bad magic)``."""


class CentrelineCsvError(InputError):
    """A centreline CSV file is malformed; the message names the file and the line."""


class MarkerCsvError(InputError):
    """A marker CSV file is malformed; the message names the file and the line."""


class OutputIsInputError(InputError):
    """The requested output path would overwrite an input."""


class CliError(PipeNavError):
    """A user error with a one-line message."""
