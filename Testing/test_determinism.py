"""Reproducible preparation: identical input gives bit-identical surfaces and sphere maps in any
process, working directory, environment and number of workers."""

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mdlshapemodel
from mdlshapemodel import BuildConfig
from mdlshapemodel.prepare import prepare_case, preprocess

from files import write_label_map
from synthetic import small_mask

from common import HIPPOCAMPI

PREPARE = """
import hashlib, sys
from mdlshapemodel import BuildConfig
from mdlshapemodel.prepare import prepare_case
case = prepare_case(sys.argv[1], BuildConfig(labels=[1, 2]))
digest = hashlib.sha256()
for array in (case.map.vertices, case.map.faces, case.map.sphere):
    digest.update(array.tobytes())
print(len(case.map.vertices), digest.hexdigest())
"""


def digest_of(case) -> str:
    digest = hashlib.sha256()
    for array in (case.map.vertices, case.map.faces, case.map.sphere):
        digest.update(array.tobytes())
    return digest.hexdigest()


def write_mask(path, mask):
    return write_label_map(path, mask, spacing=(0.9, 1.0, 1.1))


def label_map(tmp_path) -> Path:
    if HIPPOCAMPI.is_dir():
        return HIPPOCAMPI / "hippocampus_003.nii.gz"
    return write_mask(tmp_path / "case.nii.gz", small_mask(0.3))


def test_a_case_prepares_bit_for_bit_alike_in_separate_processes(tmp_path):
    path = label_map(tmp_path)
    here = prepare_case(str(path), BuildConfig(labels=[1, 2]))
    outputs = set()
    for k, padding in enumerate((0, 20_000)):
        folder = tmp_path / ("w" * (k * 40 + 1))
        folder.mkdir()
        # the same package as this process's, from another working directory
        package_root = str(Path(mdlshapemodel.__file__).resolve().parents[1])
        environment = dict(os.environ, PADDING="x" * padding, PYTHONPATH=package_root,
                           OPENBLAS_NUM_THREADS=str(k + 1), OMP_NUM_THREADS=str(k + 1))
        result = subprocess.run([sys.executable, "-c", PREPARE, str(path)], cwd=folder,
                                env=environment, capture_output=True, text=True, check=True,
                                timeout=300)
        outputs.add(result.stdout.strip())
    assert outputs == {f"{len(here.map.vertices)} {digest_of(here)}"}


def test_one_and_two_workers_prepare_identical_cases(tmp_path):
    paths = [write_mask(tmp_path / f"case_{k}.nii.gz", small_mask(p))
             for k, p in enumerate((-0.4, 0.0, 0.4))]
    serial, _ = preprocess(paths, BuildConfig(workers=1, cache_dir=""))
    parallel, _ = preprocess(paths, BuildConfig(workers=2, cache_dir=""))
    assert [c.name for c in serial] == [c.name for c in parallel] == ["case_0", "case_1", "case_2"]
    assert [digest_of(c) for c in serial] == [digest_of(c) for c in parallel]


@pytest.mark.skipif(not HIPPOCAMPI.is_dir(), reason="the shared hippocampus data is not here")
def test_remeshed_hippocampus_surfaces_are_well_shaped():
    # the deterministic remesher keeps the triangles regular (quality 4 sqrt(3) A / sum l^2,
    # 1 for an equilateral triangle); the sphere map of such a surface has no flipped triangle
    case = prepare_case(str(HIPPOCAMPI / "hippocampus_001.nii.gz"), BuildConfig(labels=[1, 2]))
    vertices, faces = case.map.vertices, case.map.faces
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    lengths = np.stack([np.linalg.norm(b - c, axis=1), np.linalg.norm(c - a, axis=1),
                        np.linalg.norm(a - b, axis=1)], axis=1)
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    quality = 4 * np.sqrt(3) * area / np.sum(lengths ** 2, axis=1)
    assert quality.min() > 0.5 and np.median(quality) > 0.9
    assert case.map.quality["flipped_triangles"] == 0
