"""Shared fixtures: a small real surface (ellipsoid with a bump) and its sphere map.

Building the surface and its map takes a second or two, so both are computed once per session.
"""

import os
import shutil
import signal
import tempfile

import numpy as np
import pytest

# A test run started in the background by a shell without job control inherits SIGINT ignored;
# the Ctrl-C tests need Python's own handler, which a run from a terminal has.
signal.signal(signal.SIGINT, signal.default_int_handler)

# Every test session gets its own, empty preprocessing cache (also inherited by CLI subprocesses):
# results never leak in from a user's cache or from an earlier run.
_MADE_HERE = [tempfile.mkdtemp(prefix="mdlshapemodel-test-cache-")]
os.environ["MDLSHAPEMODEL_CACHE"] = _MADE_HERE[0]
# hypothesis (Testing/test_fuzz_readers.py) keeps what it learns in a folder of its own, not in
# the checkout (.hypothesis/)
if "HYPOTHESIS_STORAGE_DIRECTORY" not in os.environ:
    _MADE_HERE.append(tempfile.mkdtemp(prefix="mdlshapemodel-test-hypothesis-"))
    os.environ["HYPOTHESIS_STORAGE_DIRECTORY"] = _MADE_HERE[-1]


def pytest_sessionfinish(session, exitstatus):
    """The session's own folders go with it (each run made new ones in the system's temp)."""
    for folder in _MADE_HERE:
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def rng():
    """A fresh, seeded random generator for each test."""
    return np.random.default_rng(20100401)


@pytest.fixture(scope="session")
def bump_surface():
    """Closed genus-0 surface of an ellipsoid with a bump: (vertices, faces), about 1,000 vertices."""
    from mdlshapemodel.demo import bump_ellipsoid_mask
    from mdlshapemodel.prepare.surface import mask_to_surface

    mask = bump_ellipsoid_mask(shape=(22, 26, 36), semi_axes=(12.0, 7.0, 5.5), bump_radius=4.0,
                               bump_position=0.3)
    vertices, faces, _ = mask_to_surface(mask)
    return vertices, faces


@pytest.fixture(scope="session")
def bump_map(bump_surface):
    """The :class:`SphereMap` of :func:`bump_surface`."""
    from mdlshapemodel.prepare.sphere import sphere_map

    vertices, faces = bump_surface
    return sphere_map(vertices, faces)
