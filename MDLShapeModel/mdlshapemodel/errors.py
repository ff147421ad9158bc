"""Exceptions with messages meant for users: one line naming the problem."""


class MDLShapeModelError(Exception):
    """Base class of every error this package raises on purpose."""


class InputError(MDLShapeModelError):
    """An input file cannot be read or does not hold what it should."""


class SurfaceError(MDLShapeModelError):
    """A surface is not one closed, manifold, genus-0 component."""


class SphereMapError(MDLShapeModelError):
    """A surface could not be mapped bijectively onto the sphere."""


class ConfigError(MDLShapeModelError):
    """A configuration value is out of range; the message names the field."""
