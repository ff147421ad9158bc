"""From a model to findings: where groups differ, what changes with a covariate, which cases
are unusual.

The stage after :mod:`mdlshapemodel.model`: functions over arrays and
:class:`~mdlshapemodel.model.shape_model.ShapeModel`\\ s that return named results.

- :func:`~.table.subjects`: a subjects table (CSV with a ``case`` column) matched to a build's
  cases, and the design of one test;
- :func:`~.shapes.read_build`, :func:`~.shapes.align`, :func:`~.shapes.vertex_normals`: the
  corresponded shapes, aligned, and the mean surface's normals;
- :func:`~.superimposition.resistant_procrustes`: the alignment that a local change moves
  little (``align(..., superimposition="resistant")``);
- :func:`~.glm.permutation_test`: per-point linear models, Freedman-Lane permutations,
  family-wise (maximum statistic) and FDR (:func:`~.glm.benjamini_hochberg`) correction;
- :func:`~.effects.interval`, :func:`~.effects.cohens_d`,
  :func:`~.effects.partial_eta_squared`: how large and how certain an effect is at each point
  (:func:`~.study.effects_of`), and the shapes it describes (:func:`~.study.effect_shapes`);
- :func:`~.discriminant.discriminant`: the discriminant shape change of two groups;
- :func:`~.classification.classify`: how well the shapes tell two or more groups apart on
  held-out cases (repeated cross-validation, the nuisance regressed out in each training fold,
  AUC and balanced accuracy with corrected intervals, the AUC's permutation p-value);
- :func:`~.study.point_test`, :func:`~.study.signed_maps`: the per-point test of a design
  (independent cases, each subject's change, time within subjects, whole subjects) and the
  signed map of each effect column and contrast;
- :func:`~.study.analyze_shapes`: all of them for one build and table (an
  :class:`~.study.Analysis`).
"""

from .classification import classify
from .discriminant import discriminant
from .glm import benjamini_hochberg, permutation_test
from .shapes import align, read_build, vertex_normals
from .study import Analysis, analyze_shapes, point_test, signed_maps, unusual_cases
from .table import Subjects, subjects

__all__ = ["Analysis", "Subjects", "align", "analyze_shapes", "benjamini_hochberg", "classify",
           "discriminant", "permutation_test", "point_test", "read_build", "signed_maps",
           "subjects", "unusual_cases", "vertex_normals"]
