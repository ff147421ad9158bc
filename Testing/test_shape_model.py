"""Tests of the area-weighted point distribution model (docs/method.md section 1) and its file.

The model file follows the Statismo file format (groups /version, /representer, /model,
/modelinfo) as Statismo and Scalismo write and read it; the readers and writers below are
written from that format, with plain h5py, independently of mdlshapemodel.model.shape_model.
"""

import h5py
import numpy as np
import pytest

from mdlshapemodel.errors import InputError
from mdlshapemodel.model.shape_model import ShapeModel


def random_population(rng, n_s=8, n_p=30):
    shapes = rng.normal(size=(1, n_p, 3)) * 5 + rng.normal(size=(n_s, n_p, 3))
    weights = rng.uniform(0.2, 2.0, size=n_p)
    return shapes, weights / weights.sum()


def weighted_inner(a, b, weights):
    """sum_k w_k a_k . b_k of two (n_p, 3) arrays."""
    return float(np.sum(weights[:, None] * a * b))


def test_mean_and_mode_count(rng):
    shapes, weights = random_population(rng)
    model = ShapeModel.from_shapes(shapes, weights)
    np.testing.assert_allclose(model.mean, shapes.mean(axis=0))
    assert model.n_modes == len(shapes) - 1
    assert model.modes.shape == (len(shapes) - 1,) + shapes.shape[1:]
    assert model.scores.shape == (len(shapes), len(shapes) - 1)
    assert model.part_sizes == [shapes.shape[1]]
    assert model.names == [f"case_{i}" for i in range(len(shapes))]


def test_modes_are_orthonormal_in_the_weighted_inner_product(rng):
    shapes, weights = random_population(rng)
    model = ShapeModel.from_shapes(shapes, weights)
    gram = np.array([[weighted_inner(a, b, weights) for b in model.modes] for a in model.modes])
    np.testing.assert_allclose(gram, np.eye(model.n_modes), atol=1e-10)
    # ... and not in the plain Euclidean one (the weights matter)
    plain = np.einsum("mkd,nkd->mn", model.modes, model.modes)
    assert not np.allclose(plain, np.eye(model.n_modes), atol=1e-3)


def test_variances_are_eigenvalues_of_the_centred_weighted_gram(rng):
    shapes, weights = random_population(rng)
    n_s = len(shapes)
    model = ShapeModel.from_shapes(shapes, weights)
    centred = shapes - shapes.mean(axis=0)
    gram = np.array([[weighted_inner(a, b, weights) for b in centred] for a in centred])  # D'
    eigenvalues = np.sort(np.linalg.eigvalsh(gram))[::-1] / n_s
    np.testing.assert_allclose(model.variances, eigenvalues[:n_s - 1], rtol=1e-10)
    assert abs(eigenvalues[-1]) < 1e-12 * eigenvalues[0]           # centring removes one
    assert np.all(np.diff(model.variances) <= 0)
    # total variance = mean weighted squared distance to the mean
    total = np.mean([weighted_inner(c, c, weights) for c in centred])
    assert model.variances.sum() == pytest.approx(total, rel=1e-10)


def test_training_scores(rng):
    shapes, weights = random_population(rng)
    model = ShapeModel.from_shapes(shapes, weights)
    np.testing.assert_allclose(model.scores.mean(axis=0), 0.0, atol=1e-10)
    covariance = model.scores.T @ model.scores / len(shapes)          # divisor n_s
    np.testing.assert_allclose(covariance, np.diag(model.variances), atol=1e-10)
    for i, shape in enumerate(shapes):
        np.testing.assert_allclose(model.instance(model.scores[i]), shape, atol=1e-10)
        np.testing.assert_allclose(model.project(shape), model.scores[i], atol=1e-10)


def test_project_inverts_instance(rng):
    shapes, weights = random_population(rng)
    model = ShapeModel.from_shapes(shapes, weights)
    b = rng.normal(size=model.n_modes) * np.sqrt(model.variances)
    np.testing.assert_allclose(model.project(model.instance(b)), b, atol=1e-10)
    np.testing.assert_allclose(model.project(model.instance(b[:3]), n_modes=3), b[:3],
                               atol=1e-10)
    np.testing.assert_allclose(model.instance(np.zeros(0)), model.mean)
    # the instance is mean + sum_m b_m mode_m
    expected = model.mean + sum(bm * mode for bm, mode in zip(b, model.modes))
    np.testing.assert_allclose(model.instance(b), expected, atol=1e-12)
    # a batch of score vectors gives one shape each; the training scores give the training shapes
    batch = model.instance(np.stack([b, 0.5 * b]))
    np.testing.assert_allclose(batch[0], expected, atol=1e-12)
    np.testing.assert_allclose(batch[1], model.instance(0.5 * b), atol=1e-12)
    np.testing.assert_allclose(model.instance(model.scores), shapes, atol=1e-9)


def test_projection_is_the_weighted_least_squares_fit(rng):
    """For a shape outside the model, the projected instance minimises the weighted error."""
    shapes, weights = random_population(rng)
    model = ShapeModel.from_shapes(shapes, weights)
    outside = shapes[0] + rng.normal(size=shapes[0].shape)
    b = model.project(outside, n_modes=4)
    design = (model.modes[:4] * np.sqrt(weights)[None, :, None]).reshape(4, -1).T
    rhs = ((outside - model.mean) * np.sqrt(weights)[:, None]).ravel()
    expected, *_ = np.linalg.lstsq(design, rhs, rcond=None)
    np.testing.assert_allclose(b, expected, atol=1e-10)


def test_population_with_two_true_modes(rng):
    n_p = 40
    weights = rng.uniform(0.5, 1.5, size=n_p)
    weights /= weights.sum()
    mean = rng.normal(size=(n_p, 3))
    directions = rng.normal(size=(2, n_p, 3))
    coefficients = rng.normal(size=(12, 2)) * [3.0, 1.0]
    shapes = mean + np.einsum("im,mkd->ikd", coefficients, directions)
    model = ShapeModel.from_shapes(shapes, weights)
    assert model.n_modes == 2
    # the model's modes span the true directions
    for d in directions:
        residual = d - sum(weighted_inner(d, m, weights) * m for m in model.modes)
        assert weighted_inner(residual, residual, weights) < 1e-20 * weighted_inner(d, d, weights)


# ---------------------------------------------------------------------------------------------
# The model file: Statismo layout + our exact copy
# ---------------------------------------------------------------------------------------------

def saved_model(rng, tmp_path, triangles=True, parameters=False, n_s=6, n_p=15):
    shapes, weights = random_population(rng, n_s=n_s, n_p=n_p)
    names = ["left/ünïcode case"] + [f"case {chr(98 + i)}" for i in range(n_s - 1)]
    model = ShapeModel.from_shapes(
        shapes, weights, names=names,
        triangles=rng.integers(0, n_p, size=(20, 3)) if triangles else None,
        part_sizes=[n_p - 5, 5], delta=0.1, strategy="one-at-a-time", sweeps=7, converged=True,
        nothing=None, config='{"points": 642}',
        parameters=_unit_vectors(rng, n_p) if parameters else None)
    path = tmp_path / "model.h5"
    model.save(path)
    return model, shapes, path


def _unit_vectors(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def covariance(basis, variances):
    """basis diag(variances) basis^T of a (3n, m) basis."""
    return (basis * variances) @ basis.T


def model_covariance(model):
    """V diag(lambda) V^T with V the flattened modes (x1, y1, z1, x2, ...)."""
    flat = model.modes.reshape(model.n_modes, -1).T
    return covariance(flat, model.variances)


def assert_same_covariance(a, b, rtol=1e-6):
    assert np.linalg.norm(a - b) <= rtol * np.linalg.norm(b)


def text(value):
    return value.decode() if isinstance(value, bytes) else str(value)


def read_statismo(path):
    """A reader written from the Statismo format: only /version, /representer, /model, /modelinfo.

    Returns mean (3n,), orthonormal basis U (3n, m), variances (m,), noise variance, the
    representer's points (3, n) and cells (3, t) or None, and the scores (m, n_s) or None.
    """
    with h5py.File(path, "r") as f:
        version = (int(f["version/majorVersion"][()]), int(f["version/minorVersion"][()]))
        assert version == (0, 9)
        mean = f["model/mean"][()].astype(np.float64)
        basis = f["model/pcaBasis"][()].astype(np.float64)         # 0.9: orthonormal U
        variances = f["model/pcaVariance"][()].astype(np.float64)
        noise = float(f["model/noiseVariance"][()])
        points = f["representer/points"][()].astype(np.float64)
        cells = f["representer/cells"][()] if "cells" in f["representer"] else None
        scores = f["modelinfo/scores"][()].astype(np.float64)
    return mean, basis, variances, noise, points, cells, scores


def is_fixed_length_string(type_id):
    return isinstance(type_id, h5py.h5t.TypeStringID) and not type_id.is_variable_str()


def test_save_writes_every_group_dataset_and_attribute_of_the_statismo_layout(rng, tmp_path):
    model, shapes, path = saved_model(rng, tmp_path)
    n_p, m, n_s = len(model.mean), model.n_modes, len(shapes)
    with h5py.File(path, "r") as f:
        for name, value in (("majorVersion", 0), ("minorVersion", 9)):
            dataset = f["version"][name]
            assert isinstance(dataset, h5py.Dataset)          # datasets, not attributes
            assert dataset.shape == () and dataset.dtype == np.int32 and dataset[()] == value

        representer = f["representer"]
        expected = {"name": b"itkStandardMeshRepresenter", "version": b"0.1",
                    "datasetType": b"POLYGON_MESH"}
        for name, value in expected.items():
            assert representer.attrs[name] == value
            assert is_fixed_length_string(representer.attrs.get_id(name).get_type())
        assert representer["points"].shape == (3, n_p) and representer["points"].dtype == np.float32
        assert representer["cells"].shape == (3, 20) and representer["cells"].dtype == np.int32

        group = f["model"]
        for name, shape in (("mean", (3 * n_p,)), ("pcaBasis", (3 * n_p, m)),
                            ("pcaVariance", (m,)), ("noiseVariance", ())):
            assert group[name].shape == shape and group[name].dtype == np.float32, name
        assert group["noiseVariance"][()] == 0

        info = f["modelinfo"]
        assert is_fixed_length_string(info["build-time"].id.get_type())
        assert info["scores"].shape == (m, n_s) and info["scores"].dtype == np.float32
        builder = info["modelBuilder-0"]
        for name in ("builderName", "buildTime"):
            assert builder[name].shape == () and is_fixed_length_string(builder[name].id.get_type())
        uris = builder["dataInfo"]
        assert [text(uris[f"URI_{i}"][()]) for i in range(n_s)] == model.names
        parameters = builder["parameters"]
        assert text(parameters["strategy"][()]) == "one-at-a-time"
        assert text(parameters["delta"][()]) == "0.1"
        for group in (uris, parameters):                       # Statismo reads them as strings
            assert all(is_fixed_length_string(d.id.get_type()) for d in group.values())
        assert sorted(info) == ["build-time", "modelBuilder-0", "scores"]
        assert sorted(f) == ["mdlshapemodel", "model", "modelinfo", "representer", "version"]


def test_statismo_groups_hold_the_same_gaussian(rng, tmp_path):
    model, shapes, path = saved_model(rng, tmp_path)
    mean, basis, variances, noise, points, cells, scores = read_statismo(path)
    # point-interleaved vectors: x1, y1, z1, x2, ...
    np.testing.assert_allclose(mean[:3], model.mean[0], rtol=1e-6)
    np.testing.assert_allclose(mean, model.mean.ravel(), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(basis.T @ basis, np.eye(model.n_modes), atol=1e-6)
    assert np.all(np.diff(variances) <= 0) and noise == 0
    assert_same_covariance(covariance(basis, variances), model_covariance(model))
    # the representer is the mean mesh
    np.testing.assert_array_equal(points, model.mean.T.astype(np.float32))
    np.testing.assert_array_equal(cells.T, model.triangles)
    # scores: Statismo's coefficients alpha = diag(var)^(-1/2) U^T (x - mean), column per case
    alpha = (basis.T @ (shapes.reshape(len(shapes), -1) - mean).T) / np.sqrt(variances)[:, None]
    np.testing.assert_allclose(scores, alpha, atol=1e-4)
    rebuilt = mean + (basis * np.sqrt(variances)) @ scores[:, 2]
    np.testing.assert_allclose(rebuilt, shapes[2].ravel(), atol=1e-4)


def test_the_euclidean_basis_is_exact_before_float32_storage(rng):
    shapes, weights = random_population(rng)
    model = ShapeModel.from_shapes(shapes, weights)
    basis, variances, to_statismo = model.euclidean_pca()
    np.testing.assert_allclose(basis.T @ basis, np.eye(model.n_modes), atol=1e-12)
    assert_same_covariance(covariance(basis, variances), model_covariance(model), rtol=1e-12)
    alpha = to_statismo @ model.scores.T
    centred = (shapes - model.mean).reshape(len(shapes), -1).T
    expected = basis.T @ centred / np.sqrt(variances)[:, None]
    np.testing.assert_allclose(alpha, expected, atol=1e-10)


def assert_identical(loaded, model):
    for key in ("mean", "modes", "variances", "weights", "scores", "triangles", "parameters"):
        expected, actual = getattr(model, key), getattr(loaded, key)
        if expected is None:
            assert actual is None, key
        else:
            np.testing.assert_array_equal(actual, expected)
            assert actual.dtype == np.asarray(expected).dtype and actual.shape == expected.shape
    for key in ("mean", "modes", "variances", "weights", "scores"):          # bit for bit
        assert getattr(loaded, key).tobytes() == getattr(model, key).tobytes()
    assert loaded.names == model.names
    assert loaded.part_sizes == model.part_sizes
    assert loaded.metadata == model.metadata
    assert [type(v) for v in loaded.metadata.values()] == [type(v) for v in model.metadata.values()]


@pytest.mark.parametrize("triangles", [True, False])
@pytest.mark.parametrize("parameters", [True, False])
def test_round_trip_is_exact(rng, tmp_path, triangles, parameters):
    model, _, path = saved_model(rng, tmp_path, triangles=triangles, parameters=parameters)
    loaded = ShapeModel.load(path)
    assert_identical(loaded, model)
    assert loaded.metadata["delta"] == 0.1 and loaded.metadata["nothing"] is None
    np.testing.assert_array_equal(loaded.instance(loaded.scores[2]),
                                  model.instance(model.scores[2]))
    if not triangles:
        with h5py.File(path, "r") as f:
            assert f["representer"].attrs["datasetType"] == b"POINT_SET"
            assert "cells" not in f["representer"]


def test_round_trip_without_cases_or_modes(rng, tmp_path):
    shapes, weights = random_population(rng, n_s=4, n_p=5)
    model = ShapeModel.from_shapes(shapes, weights)
    no_cases = ShapeModel(mean=model.mean, modes=model.modes, variances=model.variances,
                          weights=weights, scores=np.zeros((0, model.n_modes)))
    no_modes = ShapeModel(mean=model.mean, modes=np.zeros((0, 5, 3)), variances=np.zeros(0),
                          weights=weights, scores=np.zeros((0, 0)))
    for name, empty in (("no_cases.h5", no_cases), ("no_modes.h5", no_modes)):
        empty.save(tmp_path / name)
        assert_identical(ShapeModel.load(tmp_path / name), empty)
        with h5py.File(tmp_path / name, "r") as f:     # Statismo's marker for "no scores"
            np.testing.assert_array_equal(f["modelinfo/scores"][()], np.zeros((1, 1)))


def write_statismo(path, mean, basis, variances, cells=None, scores=None, version=(0, 9),
                   names=None, noise=0.0):
    """A Statismo shape-model file written from the format (as another tool would)."""
    with h5py.File(path, "w") as f:
        if version is not None:
            f["version/majorVersion"] = np.int32(version[0])
            f["version/minorVersion"] = np.int32(version[1])
        representer = f.create_group("representer")
        representer.attrs["name"] = np.bytes_("itkStandardMeshRepresenter")
        representer.attrs["datasetType"] = np.bytes_("POLYGON_MESH")
        representer["points"] = mean.reshape(-1, 3).T.astype(np.float32)
        if cells is not None:
            representer["cells"] = cells.T.astype(np.int32)
        # 0.8 (and unversioned files, which Statismo reads as 0.8) store U diag(sqrt(variances))
        stored = basis * np.sqrt(variances) if version in ((0, 8), None) else basis
        f["model/mean"] = mean.astype(np.float32)
        f["model/pcaBasis"] = stored.astype(np.float32)
        f["model/pcaVariance"] = variances.astype(np.float32)
        f["model/noiseVariance"] = np.float32(noise)
        f["modelinfo/build-time"] = "Mon Jan  1 00:00:00 2024"
        if scores is not None:
            f["modelinfo/scores"] = scores.astype(np.float32)
        builder = f.create_group("modelinfo/modelBuilder-0")
        builder["builderName"] = "PCAModelBuilder"
        builder.create_group("parameters")
        data_info = builder.create_group("dataInfo")
        for i, name in enumerate(names or []):
            data_info[f"URI_{i}"] = name


def random_statismo_model(rng, n_p=12, m=4):
    mean = rng.normal(size=3 * n_p) * 10
    basis, _ = np.linalg.qr(rng.normal(size=(3 * n_p, m)))
    variances = np.sort(rng.uniform(0.5, 9.0, size=m))[::-1]
    basis = basis.astype(np.float32).astype(np.float64)        # what the file can hold
    variances = variances.astype(np.float32).astype(np.float64)
    return mean.astype(np.float32).astype(np.float64), basis, variances


@pytest.mark.parametrize("version", [(0, 9), (0, 8), None])
def test_load_a_plain_statismo_file(rng, tmp_path, version):
    n_p, m = 12, 4
    mean, basis, variances = random_statismo_model(rng, n_p, m)
    cells = rng.integers(0, n_p, size=(9, 3))
    alpha = rng.normal(size=(m, 5))
    names = [f"subject-{i}.vtk" for i in range(5)]
    path = tmp_path / "statismo.h5"
    write_statismo(path, mean, basis, variances, cells, alpha, version, names)
    model = ShapeModel.load(path)

    np.testing.assert_array_equal(model.mean, mean.reshape(n_p, 3))
    np.testing.assert_array_equal(model.weights, np.full(n_p, 1 / n_p))
    assert model.part_sizes == [n_p] and model.parameters is None
    np.testing.assert_array_equal(model.triangles, cells)
    assert model.names == names
    gram = np.array([[weighted_inner(a, b, model.weights) for b in model.modes]
                     for a in model.modes])
    np.testing.assert_allclose(gram, np.eye(m), atol=1e-6)
    np.testing.assert_allclose(model.variances, variances / n_p, rtol=1e-6)
    assert_same_covariance(model_covariance(model), covariance(basis, variances))
    # the scores are the same shapes as Statismo's coefficients
    for i in range(5):
        statismo_shape = mean + (basis * np.sqrt(variances)) @ alpha[:, i]
        np.testing.assert_allclose(model.instance(model.scores[i]).ravel(), statismo_shape,
                                   atol=1e-4)
    b = rng.normal(size=m) * np.sqrt(model.variances)
    np.testing.assert_allclose(model.project(model.instance(b)), b, atol=1e-5)


def test_load_a_statismo_file_without_scores(rng, tmp_path):
    mean, basis, variances = random_statismo_model(rng)
    write_statismo(tmp_path / "a.h5", mean, basis, variances)
    model = ShapeModel.load(tmp_path / "a.h5")
    assert model.scores.shape == (0, 4) and model.names == [] and model.triangles is None
    write_statismo(tmp_path / "b.h5", mean, basis, variances, scores=np.zeros((1, 1)))
    assert ShapeModel.load(tmp_path / "b.h5").scores.shape == (0, 4)     # Statismo's marker


def test_our_file_read_only_through_its_statismo_groups(rng, tmp_path):
    """What Statismo/Scalismo see: the same Gaussian, scores and mesh (float32 precision)."""
    model, shapes, path = saved_model(rng, tmp_path)
    with h5py.File(path, "r+") as f:
        del f["mdlshapemodel"]
    foreign = ShapeModel.load(path)
    assert_same_covariance(model_covariance(foreign), model_covariance(model))
    np.testing.assert_allclose(foreign.mean, model.mean, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(foreign.triangles, model.triangles)
    assert foreign.names == model.names
    for i, shape in enumerate(shapes):
        np.testing.assert_allclose(foreign.instance(foreign.scores[i]), shape, atol=1e-4)


def test_load_the_first_layout(rng, tmp_path):
    """Files written before the Statismo layout (root datasets) still load."""
    shapes, weights = random_population(rng, n_s=4, n_p=6)
    model = ShapeModel.from_shapes(shapes, weights, strategy="fixed")
    with h5py.File(tmp_path / "old.h5", "w") as f:
        f.attrs["format"] = "mdlshapemodel"
        f.attrs["format_version"] = 1
        for key in ("mean", "modes", "variances", "weights", "scores"):
            f[key] = getattr(model, key)
        f["part_sizes"] = np.asarray(model.part_sizes)
        f.create_dataset("names", data=np.array(model.names, dtype=object),
                         dtype=h5py.string_dtype())
        f.attrs["strategy"] = "fixed"
    assert_identical(ShapeModel.load(tmp_path / "old.h5"), model)


def test_files_that_are_not_models_are_a_clear_error(tmp_path):
    empty = tmp_path / "empty.h5"
    h5py.File(empty, "w").close()
    with pytest.raises(InputError, match="empty.h5: neither"):
        ShapeModel.load(empty)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["model"] = np.zeros(3)                 # a dataset, not Statismo's group
    with pytest.raises(InputError, match="other.h5: neither"):
        ShapeModel.load(other)
    notes = tmp_path / "notes.txt"
    notes.write_text("not a model\n")
    with pytest.raises(InputError, match="notes.txt: not an HDF5 file"):
        ShapeModel.load(notes)
    with pytest.raises(InputError, match="missing.h5: no such model file"):
        ShapeModel.load(tmp_path / "missing.h5")


def test_inconsistent_statismo_files_are_a_clear_error(rng, tmp_path):
    mean, basis, variances = random_statismo_model(rng)
    path = tmp_path / "bad.h5"
    write_statismo(path, mean, basis[:-3], variances)
    with pytest.raises(InputError, match="bad.h5: not a 3-D shape model"):
        ShapeModel.load(path)
    write_statismo(path, mean, basis, variances, scores=np.ones((3, 2)))
    with pytest.raises(InputError, match="bad.h5: modelinfo/scores"):
        ShapeModel.load(path)
    write_statismo(path, mean, basis, variances, version=(2, 0))
    with pytest.raises(InputError, match="bad.h5: unsupported Statismo file version 2.0"):
        ShapeModel.load(path)
    with h5py.File(path, "r+") as f:
        del f["model/pcaVariance"]
        f["version/majorVersion"][()] = 0
        f["version/minorVersion"][()] = 9
    with pytest.raises(InputError, match="bad.h5: damaged or incomplete"):
        ShapeModel.load(path)


def test_metadata_keys_must_be_hdf5_names(rng, tmp_path):
    shapes, weights = random_population(rng, n_s=4, n_p=6)
    model = ShapeModel.from_shapes(shapes, weights, **{"a/b": 1})
    with pytest.raises(ValueError, match="a/b"):
        model.save(tmp_path / "model.h5")
    assert not (tmp_path / "model.h5").exists()
