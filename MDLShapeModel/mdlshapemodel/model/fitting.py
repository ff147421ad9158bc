"""Fitting a new case to an existing model: its correspondence, pose, scores and reconstruction.

The paper notes (III-D) that examples can be added to a model one at a time. ``fit_case`` does that
for one new case without changing the model: the training shapes are the model's own
(``mean + scores @ modes``: exact but for the modes of negligible variance that a model drops,
:data:`~.shape_model.NEGLIGIBLE_VARIANCE`) and stay
fixed; only the new case's reparameterization and pose are optimised (by the model's build strategy
unless told otherwise), to minimise the description length of the training set with the new case
added (eq. 14). The corresponded case is then aligned to the model mean, projected onto the modes,
and reconstructed.

The new case goes through the same preprocessing as the model's training cases (the build's
settings are stored in the model file), and its sphere map is aligned to the model's own
parameterization: the mean mesh with the sampling grid as its sphere map.

The command ``mdlshapemodel fit`` (fitting the cases of files and writing its folder) is
:mod:`mdlshapemodel.fit`.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..config import BuildConfig
from ..correspondence.circle import CurvePart
from ..correspondence.objective import objectives
from ..correspondence.smoothness import Smoothness
from ..correspondence.state import CorrespondenceState, Example, FixedExample, PartState
from ..correspondence.strategies import optimise
from ..correspondence.trace import Trace
from ..errors import InputError
from ..geometry import Pose, align
from ..prepare import PreparedCase
from ..prepare.parts import CaseInput, case_inputs, prepare_object
from ..prepare.curve import align_curve_origins, curve_map
from ..prepare.sphere import SphereMap, align_parameterizations, reference_frames
from ..prepare.surface import MIRROR, mirror_points
from .shape_model import ShapeModel
from .outliers import modes_explaining, new_case_distances


@dataclass
class FitResult:
    """A new case fitted to a model."""

    name: str
    path: str
    corresponded: np.ndarray        # (n_p, 3) the case's points, its own physical coordinates
    aligned: np.ndarray             # (n_p, 3) the same points in the model frame
    to_model: Pose                  # physical -> model frame (a reflection first if mirrored)
    scores: np.ndarray              # (n_modes,) b = projection onto the modes
    squared_error: np.ndarray       # (n_modes + 1,) sum_k w_k |x_k - x'_k(M)|^2, M = 0..n_modes
    distance_error: np.ndarray      # (n_modes + 1,) sum_k w_k |x_k - x'_k(M)|, mm
    objective: dict = field(default_factory=dict)
    notes: dict = field(default_factory=dict)   # the preparation facts (PreparedCase.record)

    def reconstruction(self, model: ShapeModel, n_modes: int | None = None,
                       physical: bool = True) -> np.ndarray:
        """The model's reconstruction with the first ``n_modes`` modes (default all), in the
        case's physical coordinates (default) or the model frame."""
        shape = model.instance(self.scores[:n_modes])
        if not physical:
            return shape
        return self.to_model.inverse().apply(shape)


def build_config_of(model: ShapeModel) -> BuildConfig:
    """The build settings stored with the model (defaults when it has none)."""
    text = model.metadata.get("config")
    if not text:
        return BuildConfig()
    data = json.loads(text)
    known = {key: value for key, value in data.items() if key in BuildConfig.__dataclass_fields__}
    return BuildConfig.from_dict(known)


def fit_case(model: ShapeModel, path, config: BuildConfig | None = None, max_time: float = 60.0,
             max_sweeps: int = 10_000, seed: int = 0, progress=None, prepared=None,
             strategy: str | None = None) -> FitResult:
    """Find the correspondence of a new case against ``model`` and project it onto the modes.

    Parameters
    ----------
    model : ShapeModel
        A model with its sampling grid (``model.parameters``); of one part or several.
    path : path or CaseInput
        Label map or mesh of the new case (a multi-part model's parts are split from a label map
        by the labels it was built with), or a :class:`~.prepare.parts.CaseInput` of one file per
        part (e.g. a row group of a manifest).
    config : BuildConfig, optional
        Preprocessing settings (default: the ones stored in the model).
    max_time, max_sweeps : budget of the optimisation of the new case.
    prepared : PreparedCase, optional
        The case already preprocessed (``path`` is then only used for its name).
    strategy : str, optional
        Optimisation strategy for the new case (default: the model's build strategy).
    """
    if model.parameters is None or model.triangles is None:
        raise InputError("the model has no sampling grid (model.parameters) or no triangles; "
                         "rebuild it with this version")
    config = config or build_config_of(model)
    if prepared is not None:
        case = prepared
    else:
        case = prepare_object(path if isinstance(path, CaseInput)
                              else case_inputs([path], config)[0], config)
    if not isinstance(case, PreparedCase):
        raise InputError(f"{case.path}: {case.reason}")
    meshes = model.part_meshes()
    if case.part_names != [mesh.name for mesh in meshes]:
        raise InputError(f"{case.path}: its parts {case.part_names} are not the model's "
                         f"{[mesh.name for mesh in meshes]}")
    started = time.perf_counter()

    training = model.instance(model.scores)
    examples = [FixedExample(name, shape) for name, shape in zip(model.names, training)]
    grids = [(model.parameters[m.rows], m.triangles) for m in meshes]
    if model.of_curves != case.is_curve:
        raise InputError(f"{case.path}: a {'2-D' if case.is_curve else '3-D'} input; the model "
                         f"is of {'2-D curves' if model.of_curves else 'surfaces'}")
    if case.is_curve:
        # the new outline's origin aligned to the model's mean outline, then sampled at the grid
        new_maps = [align_curve_origins([curve_map(model.mean[m.rows, :2]), part.map])[1]
                    for m, part in zip(meshes, case.parts)]
        examples.append(Example(case.name, [CurvePart(new, *grid)
                                            for new, grid in zip(new_maps, grids)]))
    else:
        # the model's parameterization: each part of the mean mesh, sampled at its grid points;
        # the new case's parts aligned to them in the frame of the whole object
        references = [SphereMap(model.mean[m.rows], m.triangles, model.parameters[m.rows])
                      for m in meshes]
        whole = [(model.mean, model.triangles), case.surface()]
        frames = reference_frames(whole) if len(meshes) > 1 else None
        new_maps = [align_parameterizations([reference, part.map], frames=frames)[1]
                    for reference, part in zip(references, case.parts)]
        examples.append(Example(case.name, [PartState(new.vertices, new.faces, new.sphere,
                                                      *grid)
                                            for new, grid in zip(new_maps, grids)]))
    voxel = float(model.metadata.get("voxel_size_mm", case.voxel_size))
    # the model's prior on smooth correspondence (if it was built with one) holds for the new
    # case too, so that its points do not slide where the training cases' could not
    weight = config.smoothness_for(curves=case.is_curve)
    smoothness = Smoothness(weight, voxel) if weight > 0 and not case.is_curve else None
    state = CorrespondenceState(examples, grids, scaling=config.scaling,
                                planar=case.is_curve, smoothness=smoothness)

    data_range = float(np.max(np.ptp(state.aligned_shapes().reshape(-1, 3), axis=0)))
    fixed, integrated = objectives(config, voxel, data_range)
    initial = state.description_length(integrated)
    settings = replace(config, strategy=strategy or config.strategy, max_time=max_time,
                       max_sweeps=max_sweeps).optimisation_settings()
    trace = Trace()
    optimise(state, (fixed, integrated), settings, np.random.default_rng(seed), trace, progress,
             active=[len(examples) - 1])
    final = state.description_length(integrated)     # eq. 14, as ``initial`` (without the prior)

    raw = examples[-1].raw_points()
    to_model = align(raw, model.mean, model.weights, scaling=config.scaling,
                     planar=case.is_curve)
    aligned = to_model.apply(raw)
    scores = model.project(aligned)
    squared, distance = reconstruction_errors(model, aligned, scores)
    physical = raw
    if case.mirrored:  # the pose acts on the mirrored copy: reflect points first
        physical = mirror_points(raw)
        to_model = to_model.compose(Pose(1.0, np.diag(MIRROR), np.zeros(3)))
    return FitResult(case.name, str(case.path), physical, aligned, to_model, scores, squared,
                     distance, {"initial": float(initial), "final": float(final),
                                "evaluations": state.evaluations,
                                "seconds": time.perf_counter() - started,
                                "strategy": settings.strategy},
                     case.record())


def reconstruction_errors(model: ShapeModel, aligned: np.ndarray, scores: np.ndarray):
    """Weighted squared (mm^2) and mean point-to-point (mm) error of the reconstruction of an
    aligned shape with M = 0..n_modes modes."""
    squared, distance = [], []
    for m in range(model.n_modes + 1):
        residual = aligned - model.instance(scores[:m])
        squared.append(float(model.weights @ np.sum(residual ** 2, axis=1)))
        distance.append(float(model.weights @ np.linalg.norm(residual, axis=1)))
    return np.array(squared), np.array(distance)


def unusual_fit(model: ShapeModel, result: FitResult) -> dict | None:
    """How unusual a fitted case is against the model's training cases: its Mahalanobis
    distance over the modes explaining 95% of the variance, its p-value against the training
    cases' empirical null (flagged below p = 0.01) and against the F distribution of a new
    case's distance under normality (:func:`~.outliers.new_case_distances`); and where it
    departs most from its reconstruction by those modes (mm, the point's index). None when the
    model keeps fewer than 3 training cases' scores."""
    n = len(model.scores)
    if n < 3 or model.n_modes == 0:
        return None
    k = modes_explaining(model.variances, n_cases=n)
    found = new_case_distances(result.scores[None], model.variances, model.scores, k)
    departure = np.linalg.norm(result.aligned - model.instance(result.scores[:k]), axis=1)
    return {"modes": k, "distance": float(found.distance[0]), "p": float(found.p[0]),
            "p_normal": float(found.p_normal[0]), "flagged": bool(found.outlier[0]),
            "threshold": float(found.threshold[0]), "null": found.null.to_json(),
            "max_departure_mm": float(departure.max()),
            "at_point": int(departure.argmax())}
