"""MDLShapeModel: statistical shape models with correspondence by minimum description length.

The library behind the ``mdlshapemodel`` command, the VTK filters and the 3D Slicer module
(Davies et al., IEEE TMI 29(4), 2010).
"""

from .config import BuildConfig
from .errors import (ConfigError, InputError, MDLShapeModelError, SphereMapError,
                     SurfaceError)
from .model import ShapeModel

__version__ = "0.1.0"

__all__ = ["BuildConfig", "ConfigError", "InputError", "MDLShapeModelError", "ShapeModel",
           "SphereMapError", "SurfaceError", "build_model", "__version__"]


def build_model(*args, **kwargs):
    """See :func:`mdlshapemodel.pipeline.build_model`."""
    from .pipeline import build_model as build

    return build(*args, **kwargs)
