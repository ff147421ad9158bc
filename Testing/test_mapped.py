"""Tests of mdlshapemodel.prepare.mapped: prepared cases whose surfaces lie in a mapped file give
the same arrays, the pages read go back at a release, and a pool's process reads them from the
file instead of receiving them."""

import gc
import logging
import pickle
import sys
import weakref

import numpy as np
import pytest

from mdlshapemodel.memory import release_freed_memory
from mdlshapemodel.prepare.case import PreparedCase, PreparedPart
from mdlshapemodel.prepare.mapped import MappedCases, CasesInFile, mapped_cases
from mdlshapemodel.prepare.sphere import SphereMap


def made_cases(sizes, seed=0, parts=1):
    """Cases of random arrays shaped as sphere maps (``sizes``: vertices per case), with
    ``parts`` parts each."""
    rng = np.random.default_rng(seed)
    cases = []
    for k, n in enumerate(sizes):
        mapped = []
        for j in range(parts):
            sphere = rng.normal(size=(n, 3))
            sphere /= np.linalg.norm(sphere, axis=1)[:, None]
            faces = rng.integers(0, n, size=(2 * n - 4, 3))
            mapped.append(PreparedPart(f"p{j}" if parts > 1 else "", f"/in/c{k}.vtk",
                                       SphereMap(rng.normal(size=(n, 3)) * 10, faces, sphere,
                                                 {"flipped_triangles": 0}), "filled", 1.5))
        cases.append(PreparedCase(f"c{k}", mapped, 0.5 + k, mirrored=bool(k % 2)))
    return cases


@pytest.mark.parametrize("parts", [1, 2])
def test_mapped_cases_are_the_same_cases_with_read_only_views_of_the_file(tmp_path, parts):
    cases = made_cases([7, 50, 3, 1000], parts=parts)
    mapped = mapped_cases(cases, tmp_path / "surfaces.tmp")
    assert isinstance(mapped, MappedCases) and len(mapped) == len(cases)
    assert (tmp_path / "surfaces.tmp").is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["surfaces.tmp"]     # no temporary left
    for i, (case, other) in enumerate(zip(cases, mapped)):
        assert (other.name, other.voxel_size, other.mirrored) == (case.name, case.voxel_size,
                                                                  case.mirrored)
        assert other.part_names == case.part_names and other.repair == case.repair
        for part, mine in zip(case.parts, other.parts):
            for name in ("vertices", "faces", "sphere"):
                given, viewed = getattr(part.map, name), getattr(mine.map, name)
                assert viewed.dtype == given.dtype and viewed.shape == given.shape
                assert np.array_equal(viewed, given)
                assert not viewed.flags.writeable
                assert viewed.ctypes.data % 64 == 0
            assert mine.map.quality == part.map.quality
        # what another process reads from the file, case by case
        read = mapped.file.meshes(i)
        assert len(read) == parts
        for (vertices, faces), part in zip(read, case.parts):
            assert np.array_equal(vertices, part.map.vertices)
            assert np.array_equal(faces, part.map.faces) and faces.dtype == part.map.faces.dtype
    assert np.array_equal(mapped[1].surface()[0], cases[1].surface()[0])


def test_a_case_file_that_cannot_be_written_leaves_the_cases_in_memory(tmp_path, caplog):
    cases = made_cases([5, 6, 7])
    with caplog.at_level(logging.WARNING, logger="mdlshapemodel"):
        kept = mapped_cases(cases, tmp_path / "no such folder" / "surfaces.tmp")
    assert kept is cases
    assert "could not write" in caplog.text and "no such folder" in caplog.text


def test_curves_and_no_cases_are_not_mapped(tmp_path):
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare.case import prepare_case

    from test_curves import ellipse, write_table
    curve = prepare_case(str(write_table(tmp_path / "a.csv", ellipse())), BuildConfig())
    assert curve.is_curve
    assert mapped_cases([curve], tmp_path / "s.tmp") == [curve]
    assert mapped_cases([], tmp_path / "s.tmp") == []
    assert not (tmp_path / "s.tmp").exists()


def test_the_file_goes_at_the_end_of_the_block_also_after_an_error(tmp_path):
    path = tmp_path / "surfaces.tmp"
    with CasesInFile(made_cases([5, 6, 7]), path) as mapped:
        assert path.is_file()
        kept = mapped[0].map.vertices.copy()
    assert not path.exists()
    assert np.array_equal(mapped[0].map.vertices, kept)     # the mapping outlives the file
    with pytest.raises(KeyError):
        with CasesInFile(made_cases([5, 6, 7]), path):
            raise KeyError("stop")
    assert not path.exists()


def test_the_list_given_for_the_block_is_not_kept(tmp_path):
    cases = made_cases([5, 6, 7])
    given = weakref.ref(cases[0].parts[0].map.vertices)
    with CasesInFile(cases, tmp_path / "surfaces.tmp") as cases:     # the name now the mapped
        gc.collect()
        assert given() is None
        assert cases[0].map.vertices.shape == (5, 3)


def mapped_resident_mb() -> float:
    """This process's resident MB of mapped files (``RssFile``)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("RssFile:"):
                return int(line.split()[1]) / 1024
    raise AssertionError("no RssFile in /proc/self/status")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc is Linux's")
def test_the_pages_read_of_a_mapped_case_go_back_at_a_release(tmp_path):
    # 80 MB of arrays: untouched, they are not resident; read, they are; released, not again
    mapped = mapped_cases(made_cases([1_000_000] * 2), tmp_path / "surfaces.tmp")
    untouched = mapped_resident_mb()
    total = sum(float(part.map.vertices.sum() + part.map.sphere.sum() + part.map.faces.sum())
                for case in mapped for part in case.parts)
    read = mapped_resident_mb()
    assert read - untouched > 70
    assert release_freed_memory()
    released = mapped_resident_mb()
    assert read - released > 70
    again = sum(float(part.map.vertices.sum() + part.map.sphere.sum() + part.map.faces.sum())
                for case in mapped for part in case.parts)
    assert again == total                     # read again from the file: the same bytes


def test_a_pool_process_reads_the_true_surfaces_from_the_file(tmp_path):
    """The surfaces that an evaluation sends a :class:`~mdlshapemodel.parallel.ProcessPool`
    name the file instead of holding every mesh, and measure the same."""
    from mdlshapemodel.model.evaluation import ModelFrameSurfaces, evaluate_state
    from mdlshapemodel.parallel import process_pool

    from test_evaluation_subsample import surfaces_case

    prepared, state, config = surfaces_case(tmp_path)
    mapped = mapped_cases(prepared, tmp_path / "surfaces.tmp")
    held = ModelFrameSurfaces(state, mapped)
    named = ModelFrameSurfaces(state, mapped, from_file=True)
    sent = pickle.loads(pickle.dumps(named))
    assert len(sent) == len(held) == len(prepared)
    for (v, f), (nv, nf) in zip(held, sent):
        assert np.array_equal(v, nv) and np.array_equal(f, nf)
    meshes = sum(case.map.vertices.nbytes + case.map.faces.nbytes for case in prepared)
    assert len(pickle.dumps(held)) > meshes
    assert len(pickle.dumps(named)) < meshes / 4
    # a plain list of cases has no file to name: its meshes go with it
    assert len(pickle.dumps(ModelFrameSurfaces(state, list(mapped), from_file=True))) > meshes
    here = evaluate_state(state, config, prepared)
    with process_pool(2) as pool:
        assert evaluate_state(state, config, mapped, pool=pool).result() == here
        assert evaluate_state(state, config, mapped, pool=pool, background=False) == here
