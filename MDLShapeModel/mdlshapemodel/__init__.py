"""MDLShapeModel: statistical shape models with correspondence by minimum description length.

The library behind the ``mdlshapemodel`` command, the VTK filters and the 3D Slicer module
(Davies et al., IEEE TMI 29(4), 2010). Importing the package (or :mod:`mdlshapemodel.config`)
loads only the configuration and the exceptions; :func:`build_model` and :class:`ShapeModel` load
their rooms on first use, so a panel that only fills a :class:`BuildConfig` stays light.
"""

from .config import BuildConfig
from .errors import (BuildError, Cancelled, ConfigError, InputError, InternalError,
                     MDLShapeModelError, SphereMapError, SurfaceError)

from .version import __version__

__all__ = ["BuildConfig", "BuildError", "Cancelled", "ConfigError", "InputError",
           "InternalError", "MDLShapeModelError", "ShapeModel", "SphereMapError", "SurfaceError",
           "build_model", "__version__"]


def __getattr__(name):
    # the heavy public names, imported when first used (PEP 562)
    if name == "build_model":
        from .build import build_model

        return build_model
    if name == "ShapeModel":
        from .model.shape_model import ShapeModel

        return ShapeModel
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
