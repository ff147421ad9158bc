"""The Python packages the library needs beyond those Slicer ships, installed into Slicer after
asking (never vtk or SimpleITK: Slicer's own)."""

from __future__ import annotations

import slicer

from .resources import resourcePath

# Python packages the library needs that Slicer ships itself and that must never be installed
# into Slicer by pip (another vtk breaks Slicer).
SHIPPED_BY_SLICER = ("vtk", "SimpleITK")


def requirements() -> list:
    """The pip requirements the library needs beyond what Slicer ships
    (``Resources/requirements.txt``)."""
    lines = resourcePath("requirements.txt").read_text().splitlines()
    return [line.strip() for line in lines if line.strip() and not line.startswith("#")]


def missingRequirements(wanted=None) -> list:
    """The requirements (``wanted``; by default :func:`requirements`) whose distribution is not
    installed (or too old)."""
    from importlib.metadata import PackageNotFoundError, version

    from packaging.requirements import Requirement

    missing = []
    for text in requirements() if wanted is None else wanted:
        requirement = Requirement(text)
        try:
            if not requirement.specifier.contains(version(requirement.name), prereleases=True):
                missing.append(text)
        except PackageNotFoundError:
            missing.append(text)
    return missing


def ensureDependencies(ask: bool = True) -> bool:
    """Install the missing requirements into Slicer's Python after asking the user; never vtk or
    SimpleITK (Slicer's own). True when everything is there."""
    missing = missingRequirements()
    if not missing:
        return True
    if ask and not slicer.util.confirmOkCancelDisplay(
            "MDLShapeModel needs these Python packages, which will be installed now:\n"
            + "\n".join(missing)):
        return False
    if hasattr(slicer, "packaging") and hasattr(slicer.packaging, "pip_ensure"):
        slicer.packaging.pip_ensure(missing)        # Slicer 5.11 and later
    else:
        slicer.util.pip_install(" ".join(f'"{r}"' for r in missing))
    return not missingRequirements()


# -- helpers: files and nodes ------------------------------------------------------------------
