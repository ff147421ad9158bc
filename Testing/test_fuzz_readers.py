"""Fuzzing every reader that ``prepare_case`` uses: damaged files are rejections, never exceptions.

Small valid files of each input format are cut short, bit-flipped, overwritten with random bytes,
and given absurd numbers in their headers (0, -1, NaN, 10^12...); gzip files also have their
*decompressed* bytes damaged and are compressed again, so that the header's meaning is fuzzed
behind a valid CRC. For every such file ``prepare_case`` must return a prepared case or a
rejection with a one-line reason, and print nothing; any exception is a bug in the package. A
crash of a native reader would end the test run (VTK's PLY reader did, on one damaged file in
two: the package has its own PLY reader now).

The budget is bounded for CI: a fixed number of examples per format, the same ones on every run
(derandomized; no example database is written). ``MDLSHAPEMODEL_FUZZ_EXAMPLES=2000`` runs a
longer search.
"""

import faulthandler
import gzip
import os
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import HealthCheck, given, settings, strategies as st

from mdlshapemodel.config import BuildConfig
from mdlshapemodel.correspondence.sampling import icosphere
from mdlshapemodel.prepare import PreparedCase, Rejection, io, prepare_case

from synthetic import small_mask

CONFIG = BuildConfig(cache_dir="")
EXAMPLES = int(os.environ.get("MDLSHAPEMODEL_FUZZ_EXAMPLES", 60))   # per format
HANG = 120   # seconds: one damaged file is prepared in well under 1 s
ABSURD = [b"0", b"-1", b"nan", b"inf", b"1e308", b"65535", b"4294967296", b"1000000000000",
          b"-2147483648"]


def _seed_files() -> dict:
    """The bytes of one small valid file of every format the fuzzing damages."""
    with tempfile.TemporaryDirectory(prefix="mdlshapemodel-fuzz-seeds-") as folder:
        return _write_seeds(Path(folder))


def _write_seeds(folder: Path) -> dict:
    image = sitk.GetImageFromArray(small_mask(0.0).astype(np.uint8))
    for suffix in (".nii.gz", ".nrrd", ".mha"):
        sitk.WriteImage(image, str(folder / f"seed{suffix}"), True)   # compressed
    vertices, faces = icosphere(2)
    vertices = vertices * np.array([10.0, 7.0, 5.0])
    for suffix in (".vtk", ".vtp", ".stl", ".ply"):
        io.write_polydata(folder / f"seed{suffix}", vertices, faces)
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    (folder / "seed.obj").write_text("# SPACE=LPS\n" + "\n".join(lines) + "\n")
    return {p.name.removeprefix("seed"): p.read_bytes() for p in folder.iterdir()}


SEEDS = _seed_files()
SUFFIXES = sorted(SEEDS)


@st.composite
def damaged(draw, original: bytes) -> bytes:
    """``original`` with one to three kinds of damage."""
    compressed = original[:2] == b"\x1f\x8b" and draw(st.booleans())
    data = bytearray(gzip.decompress(original) if compressed else original)
    for _ in range(draw(st.integers(1, 3))):
        if not data:
            break
        kind = draw(st.sampled_from(["cut", "flip", "overwrite", "number"]))
        at = draw(st.integers(0, len(data) - 1))
        if kind == "cut":
            del data[at:]
        elif kind == "flip":
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif kind == "overwrite":
            chunk = draw(st.binary(min_size=1, max_size=16))
            data[at:at + len(chunk)] = chunk
        else:                                  # a number of the header (its first 1,000 bytes)
            numbers = list(re.finditer(rb"\d+(\.\d+)?", bytes(data[:1000])))
            if numbers:
                number = draw(st.sampled_from(numbers))
                data[number.start():number.end()] = draw(st.sampled_from(ABSURD))
    return gzip.compress(bytes(data)) if compressed else bytes(data)


def _check(suffix: str, data: bytes, capfd):
    with tempfile.TemporaryDirectory(prefix="mdlshapemodel-fuzz-") as folder:
        path = Path(folder) / f"damaged{suffix}"
        path.write_bytes(data)
        capfd.readouterr()
        # a reader that hangs (SimpleITK did, on a direction holding 1e308) ends the run with
        # its traceback instead of holding CI until its time limit
        faulthandler.dump_traceback_later(HANG, exit=True)
        try:
            result = prepare_case(path, CONFIG)
        finally:
            faulthandler.cancel_dump_traceback_later()
        printed = capfd.readouterr()
        assert isinstance(result, (PreparedCase, Rejection))
        if isinstance(result, Rejection):
            assert result.reason and len(result.reason) < 400
            assert result.reason.isprintable(), result.reason          # one line
            assert printed.err == "" and printed.out == "", printed   # nothing but the reason
        assert sorted(p.name for p in Path(folder).iterdir()) == [path.name]   # wrote nothing


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_damaged_files_are_rejected_with_one_line_never_an_exception(suffix, capfd):
    @settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                     HealthCheck.function_scoped_fixture])
    @given(data=damaged(SEEDS[suffix]))
    def fuzz(data):
        _check(suffix, data, capfd)

    fuzz()


def test_the_seeds_are_prepared():
    """The undamaged files are good cases: the damage is what the fuzzing tests."""
    with tempfile.TemporaryDirectory() as folder:
        for suffix, data in SEEDS.items():
            path = Path(folder) / f"seed{suffix}"
            path.write_bytes(data)
            assert isinstance(prepare_case(path, CONFIG), PreparedCase), suffix
