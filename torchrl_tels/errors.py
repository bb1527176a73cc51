"""The errors torchrl_tels raises about a user's input.

Every one derives from :class:`TelsError`: the recipe shows such an error as one
``error:`` line and exits with code 2, while anything else (a bug, an error deep
in torch) keeps its traceback. Each also derives from the builtin a caller
would expect (``ValueError``, ``RuntimeError``, ...).
"""
from __future__ import annotations

__all__ = [
    "CheckpointError", "ConfigError", "DatasetError", "MissingDependencyError", "MonitorError", "NonFiniteLossError", "OutKeysError", "TaskError",
    "TelsError",
]


class TelsError(Exception):
    """A deliberate report about the user's input; its message names the problem."""


class ConfigError(TelsError, ValueError):
    """A config value is out of range or of the wrong kind."""


class DatasetError(TelsError, ValueError):
    """A dataset could not be found, read or validated.

    The message names the source and the problem (missing key, mismatched
    lengths, non-finite values, ...), so it can be shown to a user as is.
    """


class TaskError(TelsError, ValueError):
    """An unknown task, or an evaluation environment that cannot be built."""


class MissingDependencyError(TelsError, ImportError):
    """An optional dependency a feature needs is not installed; the message gives the pip line."""


class CheckpointError(TelsError, RuntimeError):
    """A checkpoint file is missing, unreadable, not one of ours, or made for another setup."""


class NonFiniteLossError(TelsError, FloatingPointError):
    """A loss term, or a tensor about to be checkpointed, became NaN or inf: the run stops and
    the last good checkpoint stays as it was."""


class MonitorError(TelsError, ValueError):
    """The deployment monitor was misused or fed bad data: a flag asked of an uncalibrated
    monitor, detectors whose sizes differ from the env's, the data's or each other's, a non-finite
    input, too few trajectories to calibrate on."""


class OutKeysError(TelsError, ValueError, RuntimeError):
    """A loss was asked for an output key it does not write (``select_out_keys``, ``out_keys = ...``).

    Both builtins because tensordict's ``select_out_keys`` raises ``ValueError`` for one unknown key and
    ``RuntimeError`` for several: code written against torchrl's losses catches this one either way."""
