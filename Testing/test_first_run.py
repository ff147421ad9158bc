"""What a new user meets first: --version, build's examples, the hint for labels written apart,
inputs checked before anything is written, a build folder refused as input, the rerun after a
failed start, the main guard of a script, mode weights in standard deviations, the line of the
first run's compilation."""

import os
import textwrap
from pathlib import Path

import numpy as np
import pytest

from mdlshapemodel import ShapeModel
from mdlshapemodel.kernels import COMPILING
from mdlshapemodel.prepare import io
from mdlshapemodel.version import __version__

from common import run_cli, run_python
from synthetic import write_population


def test_version():
    result = run_cli("--version")
    assert result.returncode == 0 and result.stdout.strip() == f"mdlshapemodel {__version__}"


def test_build_help_ends_with_examples():
    text = run_cli("build", "--help").stdout
    examples = text[text.index("examples:"):]
    assert "mdlshapemodel build labels/ -o both --label 1,2" in examples
    assert text.rstrip().endswith("(after an interruption)")


def test_labels_written_apart_get_the_comma_hint(tmp_path):
    result = run_cli("build", tmp_path, "--label", "1", "2", "-o", tmp_path / "out")
    assert result.returncode == 2
    assert "write --label 1,2" in result.stderr
    assert not (tmp_path / "out").exists()
    other = run_cli("build", tmp_path, "-o", tmp_path / "out", "--bogus", "3")
    assert other.returncode == 2 and "unrecognized arguments: --bogus 3" in other.stderr



@pytest.mark.parametrize("count", [0, 1, 2])
def test_too_few_inputs_or_a_missing_path_leave_nothing_behind(tmp_path, count):
    inputs = write_population(tmp_path / "in", count) if count else []
    folder = tmp_path / "in" if count else tmp_path / "missing"
    result = run_cli("build", folder, "-o", tmp_path / "out", "--workers", 1)
    assert result.returncode == 2
    assert ("no such file or folder" if not count else
            f"{len(inputs)} input file(s) found; a model needs at least 3") in result.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_failed_start_does_not_block_the_rerun_and_a_build_folder_is_not_an_input(tmp_path):
    write_population(tmp_path / "in", 3)
    quick = ["--points", 42, "--workers", 1, "--baselines", "", "--no-cache",
             "--evaluation-modes", 1, "--specificity-samples", 50, "--surface-samples", 0]
    failed = run_cli("build", tmp_path / "in", "-o", tmp_path / "out", "--label", "9", *quick)
    assert failed.returncode == 2 and "usable case" in failed.stderr
    assert (tmp_path / "out" / "build.log").exists()           # what the failed start left
    rerun = run_cli("build", tmp_path / "in", "-o", tmp_path / "out", *quick)
    assert rerun.returncode == 0, rerun.stderr                 # not "holds an earlier build"
    again = run_cli("build", tmp_path / "in", "-o", tmp_path / "out", *quick)
    assert again.returncode == 2 and "holds an earlier build (model.h5" in again.stderr
    as_input = run_cli("build", tmp_path / "out", "-o", tmp_path / "other", *quick)
    assert as_input.returncode == 2
    assert "a build's output folder (it holds model.h5), not a folder of inputs" in as_input.stderr
    assert not (tmp_path / "other").exists()


UNGUARDED = textwrap.dedent("""
    import sys
    from mdlshapemodel import BuildConfig, build_model

    build_model([sys.argv[1]], sys.argv[2], BuildConfig(points=42, workers=2, baselines=[]))
""")


def test_a_script_without_the_main_guard_is_told_to_add_it(tmp_path):
    write_population(tmp_path / "in", 3)
    script = tmp_path / "unguarded.py"
    script.write_text(UNGUARDED)
    result = run_python(f"import runpy, sys; sys.argv = [{str(script)!r}, {str(tmp_path / 'in')!r}, "
                        f"{str(tmp_path / 'out')!r}]; runpy.run_path({str(script)!r}, "
                        "run_name='__main__')")
    assert result.returncode != 0
    assert "put the call under 'if __name__ == \"__main__\":'" in result.stderr
    assert "worker process died" not in result.stderr
    assert not (tmp_path / "out").exists()


def test_model_instances_in_standard_deviations_and_shapes_written_as_vtp(tmp_path, rng):
    shapes = rng.normal(size=(6, 12, 3))
    triangles = np.array([[0, 1, 2], [2, 3, 4]])
    model = ShapeModel.from_shapes(shapes, np.full(12, 1 / 12), triangles=triangles)
    sd = model.instance(standard_deviations=[2.0, -1.0])
    raw = model.instance([2.0 * np.sqrt(model.variances[0]), -np.sqrt(model.variances[1])])
    np.testing.assert_allclose(sd, raw)
    with pytest.raises(ValueError, match="either scores or standard_deviations"):
        model.instance([1.0], standard_deviations=[1.0])
    with pytest.raises(ValueError, match="standard deviations for a model of"):
        model.instance(standard_deviations=np.ones(model.n_modes + 1))
    model.save_shape(tmp_path / "plus.vtp", sd)
    vertices, faces = io.read_mesh(tmp_path / "plus.vtp")
    np.testing.assert_allclose(vertices, sd, rtol=1e-12)
    assert np.array_equal(faces, triangles)


@pytest.mark.slow
def test_a_label_that_no_case_holds_is_reported(tmp_path):
    write_population(tmp_path / "in", 3)
    result = run_cli("build", tmp_path / "in", "-o", tmp_path / "out", "--label", "1,3",
                     "--points", 42, "--workers", 1, "--baselines", "", "--no-cache",
                     "--evaluation-modes", 1, "--specificity-samples", 50,
                     "--surface-samples", 0)
    assert result.returncode == 0, result.stderr
    message = "label 3 is in none of the 3 label maps (labels found: 1)"
    assert f"warning: {message}" in result.stdout                      # the summary
    assert message in (tmp_path / "out" / "build.log").read_text()
    metrics = __import__("json").loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["warnings"] == [message]
    assert message in (tmp_path / "out" / "report.html").read_text()


def numba_index_files(folder: Path) -> dict:
    """numba's cache index files under ``folder`` and their modification times."""
    return {path: path.stat().st_mtime_ns for path in folder.rglob("*.nbi")}


@pytest.mark.slow
def test_a_cold_kernel_cache_is_announced_and_compiled_once_before_the_workers(tmp_path):
    write_population(tmp_path / "in", 3)
    cache = tmp_path / "numba"       # numba's cache, empty: as on a fresh install
    environment = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    quick = ["--points", 42, "--workers", 2, "--no-cache", "--evaluation-modes", 1,
             "--specificity-samples", 50, "--surface-samples", 10, "--max-time", 20]
    cold = run_cli("build", tmp_path / "in", "-o", tmp_path / "cold", *quick, env=environment)
    assert cold.returncode == 0, cold.stderr
    assert cold.stderr.count(COMPILING) == 1
    assert cold.stderr.index(COMPILING) < cold.stderr.index("preprocessing 3 cases")
    compiled = numba_index_files(cache)
    assert compiled
    # the second process of the compilation also compiled analyze --tfce's kernel, which no
    # build calls
    assert any(path.name.startswith("tfce._enhance_rows") for path in compiled)
    # and the kernel that replays field warps on another sampling, which the tiny build of the
    # compilation does not reach and a larger build does (the model's points when written)
    assert any(path.name.startswith("hotloops.field_map") for path in compiled)
    warm = run_cli("build", tmp_path / "in", "-o", tmp_path / "warm", *quick, env=environment)
    assert warm.returncode == 0, warm.stderr
    assert COMPILING not in warm.stderr
    # the first build compiled everything a build needs (in its workers, its optimisation and
    # its evaluation) before its workers started: the second compiled nothing
    assert numba_index_files(cache) == compiled
