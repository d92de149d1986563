"""Exception types raised by psprm_core for bad input.

Every error that comes from user input (YAML files, URDFs, poses) is a :class:`PsprmError` whose message names the
file and the field, so command-line tools and ROS nodes can report it in one line instead of a traceback.
"""

from __future__ import annotations


class PsprmError(Exception):
    """Base class of all errors psprm raises for bad input or impossible requests."""


class InputError(PsprmError, ValueError):
    """A value passed to the library is unusable (wrong shape, out of range, unknown name); also a ``ValueError``,
    so callers that catch that keep working."""


class UnknownNameError(PsprmError, KeyError):
    """A name that is not there: a scene's target, obstacle, goal region or problem, a robot's joint, a surrogate's
    class. Also a ``KeyError``; its message is printed as written (not quoted as a key)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class OutOfRangeError(PsprmError, IndexError):
    """An index outside what exists (a target's placement, a class index). Also an ``IndexError``."""


class ConfigError(PsprmError):
    """A configuration file (robot, scene, planner settings) is malformed or names something unknown.

    Parameters
    ----------
    source : str
        File (or other origin) the configuration came from.
    field : str
        Dotted path of the offending field inside the file (``"obstacles[2].size"``); empty for the whole file.
    message : str
        What is wrong.
    """

    def __init__(self, source: str, field: str, message: str):
        self.source = str(source)
        self.field = field
        self.message = message
        where = f"{self.source}" + (f": field '{field}'" if field else "")
        super().__init__(f"{where}: {message}")


class RobotModelError(PsprmError):
    """A robot description cannot be used (missing link or joint, URDF not found, ...)."""
