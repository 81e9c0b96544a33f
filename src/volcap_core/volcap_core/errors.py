"""What went wrong, and whose fault it is.

Every problem a user can act on is a ``VolcapError``: a bad input (a file, a message, an
argument or a setting), a bad bag, a calibration too weak to trust, a device that is not there,
a graph that did not come up. The `volcap` command prints such an error on one line and exits
with its ``exit_code`` (2; 3 for a weak calibration); nodes log it and report it on
``/volcap/diagnostics``. Anything else is a bug in volcap: a traceback and exit 1.

The kinds also derive from the builtin exception a caller would have caught before (a
``BadInput`` is a ``ValueError``, a ``BadBag`` a ``RuntimeError``), so code written against the
builtins keeps working.
"""
from __future__ import annotations


class VolcapError(Exception):
    """A problem the user can fix; ``exit_code`` is what the command line exits with."""
    exit_code = 2


class BadInput(VolcapError, ValueError):
    """An input file, message, argument or setting that volcap cannot use (the message says which
    and why)."""


class UnknownName(VolcapError, KeyError):
    """A camera (or other named thing) that the rig, calibration or bag does not have."""

    def __str__(self) -> str:      # KeyError quotes its argument; the message is a sentence
        return str(self.args[0]) if self.args else ''


class BadBag(VolcapError, RuntimeError):
    """A bag that is missing, unreadable, corrupt or truncated."""


class WeakCalibration(VolcapError):
    """A calibration whose predicted error is beyond the target: written, but not to be trusted."""
    exit_code = 3


class MissingDevice(VolcapError, RuntimeError):
    """A compute device (CUDA) or sensor that was asked for and is not there."""


class GraphError(VolcapError, RuntimeError):
    """A node graph that did not come up, or a node that stopped: the message names which."""
