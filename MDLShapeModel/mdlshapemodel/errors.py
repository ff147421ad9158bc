"""Exceptions with messages meant for users: one line naming the problem."""

from __future__ import annotations


class MDLShapeModelError(Exception):
    """Base class of every error this package raises on purpose."""


class InputError(MDLShapeModelError):
    """An input file cannot be read or does not hold what it should."""


class SurfaceError(MDLShapeModelError):
    """A surface is not one closed, manifold, genus-0 component."""


class SphereMapError(MDLShapeModelError):
    """A surface could not be mapped bijectively onto the sphere."""


class ConfigError(MDLShapeModelError):
    """A configuration value is out of range; the message names the field.

    ``setting`` is the name of the setting at fault (a field of the config record; None where
    no one setting is), so that each face names it its own way (the command line by its flag,
    the Slicer panel by its field's label); ``problem`` is the message without that name.
    """

    def __init__(self, message: str, setting: str | None = None, problem: str | None = None):
        super().__init__(message)
        self.setting = setting
        self.problem = message if problem is None else problem


class BuildError(MDLShapeModelError):
    """No model can be built (e.g. fewer than 3 usable cases)."""


class ArgumentError(ValueError):
    """A function of the library was called with arguments it cannot work with (arrays of the
    wrong shape, counts or names out of range): the caller's mistake, named in the message, as
    numpy's own ``ValueError`` names it.

    Deliberately not an :class:`MDLShapeModelError`: the library's own calls are made with
    arguments it checked, so inside a build such an error is a bug, never a rejected input.
    """


class InternalError(Exception):
    """A bug in this package met while working on an input: not a problem of the input.

    The message names the input and says that it is a bug; the traceback goes to the build log.
    Deliberately not an :class:`MDLShapeModelError`: code that rejects bad inputs by catching
    those never takes a bug for a bad input.
    """


class Cancelled(Exception):
    """Raised by (or on behalf of) a progress callback to stop a long operation; the state reached
    so far is kept and, in a build, its model written."""
