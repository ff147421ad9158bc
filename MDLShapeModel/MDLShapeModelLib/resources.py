"""The module's files in its ``Resources/`` folder (the .ui, the icon, the requirements)."""

from __future__ import annotations

import pathlib

MODULE_DIRECTORY = pathlib.Path(__file__).resolve().parents[1]


def resourcePath(relativePath: str) -> pathlib.Path:
    """A file of the module's ``Resources/`` folder (beside the module's file, in a checkout as in
    a built or installed extension)."""
    path = MODULE_DIRECTORY / "Resources" / relativePath
    if not path.exists():
        raise FileNotFoundError(f"MDLShapeModel resource {relativePath!r} not found in "
                                f"{MODULE_DIRECTORY / 'Resources'}")
    return path
