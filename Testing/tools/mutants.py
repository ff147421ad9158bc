"""A mutation check of the test suite: plant one-line bugs, one at a time, and see the tests
that should catch each fail.

Each mutant is a realistic one-line bug: a file of the package, the exact original text (which
must occur exactly once in that file, so that the list cannot silently rot as the code changes;
Testing/test_mutants_list.py checks it among the quick tests), its replacement, the quick tests
that must catch it and what it would break. The package is copied once into a temporary folder
(with its ``__pycache__``, so that numba's compiled kernels stay cached); each mutant is written
into the copy, its tests run there (``-m "not slow"``, except for a mutant marked ``slow``,
whose only tests start a Dask cluster; ``PYTHONPATH`` naming the copy, a time limit), and the
original is put back. Before the mutants, each distinct selection of tests is run
on the unchanged copy: a test that fails without a bug kills nothing.

Usage (from the checkout, with the project's virtualenv active)::

    python Testing/tools/mutants.py                 # every mutant; exit 1 if any survives
    python Testing/tools/mutants.py --list          # the list, checked against the code
    python Testing/tools/mutants.py --only NAME     # one mutant (repeatable)

Run it before resolving an issue that touches the analysis, the outlier distances, guides,
landmarks, the viewer or the evaluation; add every bug found to :data:`MUTANTS`.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "MDLShapeModel" / "mdlshapemodel"
TESTING = ROOT / "Testing"
TIMEOUT = 1200          # seconds for one mutant's tests


@dataclass(frozen=True)
class Mutant:
    """One planted bug: in ``file`` (relative to the package), ``original`` becomes
    ``replacement``; ``tests`` (pytest arguments relative to Testing/: files or node ids) with
    the optional ``-k`` expression ``k`` must fail (the quick ones only, unless ``slow``)."""

    name: str
    file: str
    original: str
    replacement: str
    tests: tuple
    description: str
    k: str = ""
    slow: bool = False      # its tests include slow ones (a Dask cluster's)


MUTANTS = [
    # --- the per-point test and the effects (analysis/) ---
    Mutant("freedman_lane_without_nuisance", "analysis/glm.py",
           "permuted_z = basis_z[:, 1:]", "permuted_z = basis_z[:, :1]",
           ("test_analysis_calibration.py",),
           "the nuisance left out of the permuted statistics (only the intercept, which drops "
           "out): too liberal with several nuisance columns correlated with the groups"),
    Mutant("effect_of_the_nuisance_reported", "analysis/study.py",
           "columns = [subjects.nuisance, subjects.interest]",
           "columns = [subjects.interest, subjects.nuisance]",
           ("test_outputs_recomputed.py",),
           "design columns in another order: the written difference is the nuisance's slope"),
    Mutant("normal_difference_reversed", "analysis/study.py",
           'normal_difference = np.einsum("rpd,pd->rp", difference, normals)',
           'normal_difference = -np.einsum("rpd,pd->rp", difference, normals)',
           ("test_outputs_recomputed.py",),
           "the effect's normal component with its sign reversed (inward written as outward)"),
    Mutant("size_removed_inverted", "analysis/shapes.py",
           "(sizes.mean() / sizes)", "(sizes / sizes.mean())",
           ("test_outputs_recomputed.py",),
           "--size removed scales each case by its size over the mean (doubles the differences)"),
    Mutant("mirrored_cases_not_reflected", "folders.py",
           "flips = [mirrored.get(name, False) for name in model.names]",
           "flips = [False for name in model.names]",
           ("test_outputs_recomputed.py",),
           "the analysis takes mirrored cases as they were written (the other side)"),
    Mutant("mirrored_outputs_not_reflected_back", "outputs.py",
           "physical = physical_shapes(raw, [case.mirrored for case in prepared])",
           "physical = physical_shapes(raw, [False for case in prepared])",
           ("test_outputs_recomputed.py",),
           "correspondence/ of a mirrored case left in the mirrored frame, off its input"),
    Mutant("reference_ignored", "analysis/table.py",
           "levels = [first] + [level for level in levels if level != first]",
           "levels = sorted(levels)",
           ("test_outputs_recomputed.py",),
           "--reference ignored: every difference's sign flips when the reference sorts last"),
    Mutant("two_d_aligned_in_3d", "analysis/study.py",
           "aligned = align(used, model.weights, config.size, planar, config.superimposition)",
           "aligned = align(used, model.weights, config.size, False, config.superimposition)",
           ("test_outputs_recomputed.py",),
           "2-D outlines aligned by 3-D rotations (a turn about an in-plane axis mirrors them)"),
    Mutant("parts_each_ignored", "analysis/study.py",
           'if config.parts == "each" and len(model.part_sizes) > 1:',
           'if config.parts == "each" and len(model.part_sizes) > 2:',
           ("test_outputs_recomputed.py",),
           "--parts each aligns a two-part object as one"),
    Mutant("displacement_vector_ignored", "analysis/study.py",
           'if config.displacement == "normal":', 'if config.displacement != "":',
           ("test_outputs_recomputed.py",),
           "--displacement vector tests the normal component"),
    Mutant("global_test_modes_ignore_the_nuisance", "analysis/study.py",
           "max_modes=len(subjects.interest) - z - r - 1)",
           "max_modes=len(subjects.interest) - r - 2)",
           ("test_outputs_recomputed.py",),
           "the global test takes more principal scores than its degrees of freedom allow"),
    Mutant("normals_turned_inward", "model/normals.py",
           "if inward[rows].sum() < 0:", "if inward[rows].sum() > 0:",
           ("test_outputs_recomputed.py",),
           "the mean's normals point inward: every normal displacement has its sign reversed",
           k="dent"),
    # --- discriminant and classification ---
    Mutant("ledoit_wolf_over_n", "analysis/classification.py",
           "b2 = (np.sum(np.sum(centred ** 2, axis=1) ** 2) / n - np.sum(sample ** 2)) / n",
           "b2 = (np.sum(np.sum(centred ** 2, axis=1) ** 2) / n - np.sum(sample ** 2))",
           ("test_analysis_calibration.py", "test_analysis_classify.py"),
           "Ledoit-Wolf's intensity with 1/n for 1/n^2 (always shrunk to the identity)"),
    Mutant("discriminant_reversed", "analysis/discriminant.py",
           "w = np.linalg.solve(covariance, means[1] - means[0])",
           "w = np.linalg.solve(covariance, means[0] - means[1])",
           ("test_analysis_calibration.py",),
           "the discriminant (and its pattern) point from the second group to the first"),
    Mutant("discriminant_pattern_reversed", "analysis/discriminant.py",
           'pattern = np.einsum("n,npd->pd", value, shapes - mean) / n',
           'pattern = np.einsum("n,npd->pd", value, mean - shapes) / n',
           ("test_analysis_calibration.py",),
           "the discriminant's shape pattern reversed"),
    Mutant("classifier_leakage", "analysis/classification.py",
           "train_scores, test_scores = folds.scores(train, test)",
           "train_scores, test_scores = folds.scores(np.union1d(train, test), test)",
           ("test_analysis_calibration.py", "test_analysis_classify.py"),
           "the classifier's PCA and LDA fitted on all cases, the held-out ones included"),
    Mutant("nuisance_fitted_on_all_cases", "analysis/classification.py",
           "design = self.design[train]",
           "design = self.design[np.union1d(train, test)][:len(train)]",
           ("test_analysis_classify.py",),
           "the nuisance regression's rows not the training cases'"),
    Mutant("lda_pooled_class_weights", "analysis/classification.py",
           "for g in range(groups)) / groups",
           "for g in range(groups)) / (groups + 1)",
           ("test_analysis_classify.py",),
           "the groups' covariances averaged with the wrong weight (not scikit-learn's LDA)"),
    Mutant("auc_ties_count_whole", "analysis/classification.py",
           "mean_rank = (first + last) / 2 + 1",
           "mean_rank = last + 1.0",
           ("test_analysis_calibration.py",),
           "tied held-out values count as wins in the AUC"),
    Mutant("interval_uncorrected", "analysis/classification.py",
           "spread = np.sqrt((1 / j + test_share) * np.var(values, ddof=1)) if j > 1 else np.inf",
           "spread = np.sqrt((1 / j) * np.var(values, ddof=1)) if j > 1 else np.inf",
           ("test_analysis_classify.py",),
           "the naive interval of the folds' mean (too narrow: the folds share their cases)"),
    Mutant("permutation_p_without_the_observed", "analysis/classification.py",
           "float((1 + np.sum(null >= auc - 1e-12)) / (len(null) + 1)))",
           "float(np.sum(null >= auc - 1e-12) / len(null)))",
           ("test_analysis_classify.py",),
           "the AUC's permutation p without the observed labeling (can be 0)"),
    # --- outliers (model/outliers.py) ---
    Mutant("training_beta_parameters", "model/outliers.py",
           "reference = beta(k / 2, (n - k - 1) / 2)", "reference = beta(k / 2, (n - k) / 2)",
           ("test_analysis_calibration.py",),
           "a training case's Beta with (n - k) / 2: false flags 3x the level at n = 8"),
    Mutant("new_case_f_scale", "model/outliers.py",
           "scale = (n - k) / (k * (n + 1))", "scale = (n - k) / (k * (n - 1))",
           ("test_analysis_calibration.py",),
           "a new case's F scale with n - 1 for n + 1: too many new cases flagged at small n"),
    Mutant("empirical_null_with_the_case_itself", "model/outliers.py",
           "empirical_null(np.delete(p_normal, int(np.flatnonzero(group == key)[0])))",
           "empirical_null(p_normal)",
           ("test_analysis_statistics.py",),
           "a training case in its own empirical null: a far case widens the null that judges it"),
    Mutant("empirical_null_spread_unbounded", "model/outliers.py",
           "body = EmpiricalNull(max(centre, 0.0), max(spread, 1.0))",
           "body = EmpiricalNull(max(centre, 0.0), spread)",
           ("test_analysis_calibration.py",),
           "the null's spread allowed below 1: more flags than the normal theory under normality"),
    Mutant("unusual_departure_one_mode_more", "analysis/study.py",
           "reconstructed = model.instance(model.scores[:, :k])",
           "reconstructed = model.instance(model.scores[:, :k + 1])",
           ("test_outputs_recomputed.py",),
           "a case's departure measured from its reconstruction by one mode more"),
    Mutant("training_p_over_n", "model/outliers.py",
           "p = reference.sf(np.clip(squared / (n - 1), 0.0, 1.0))",
           "p = reference.sf(np.clip(squared / n, 0.0, 1.0))",
           ("test_outputs_recomputed.py",),
           "a training case's p-value from d^2 / n: too few cases flagged"),
    # --- the viewer ---
    Mutant("viewer_modes_colour_reversed", "report/viewer.py",
           'along = np.einsum("kpd,pd->kp", scaled, normals)',
           'along = np.einsum("kpd,pd->kp", -scaled, normals)',
           ("test_viewer_colours.py",),
           "the viewer colours a mode's outward displacement as inward"),
    Mutant("viewer_colour_scale_reversed", "report/viewer.py",
           "colorscale: SCALES.normal.colorscale,",
           "colorscale: SCALES.normal.colorscale, reversescale: true,",
           ("test_viewer_colours.py",),
           "plotly's RdBu reversed: outward drawn blue"),
    Mutant("viewer_case_colour_reversed", "report/viewer.py",
           "c[i] += (p[3 * i + e] - mean[3 * i + e]) * normals[3 * i + e];",
           "c[i] += (mean[3 * i + e] - p[3 * i + e]) * normals[3 * i + e];",
           ("test_viewer_colours.py",),
           "a picked case coloured by its displacement reversed"),
    # --- landmarks and guides ---
    Mutant("markups_ras_read_as_lps", "prepare/landmarks.py",
           'rows.append((point.get("label", ""), position, system))',
           'rows.append((point.get("label", ""), position, "LPS"))',
           ("test_markups.py",),
           "a Slicer markups JSON in RAS read as LPS (x and y of the wrong sign)"),
    Mutant("markups_unplaced_kept", "prepare/landmarks.py",
           'if point.get("positionStatus") == "undefined":',
           'if point.get("positionStatus") == "missing":',
           ("test_markups.py",),
           "an unplaced control point of a markups JSON kept as a landmark"),
    Mutant("guides_at_the_farthest_vertex", "correspondence/guides.py",
           "order = np.argsort(-(grids[j][:candidates] @ np.nan_to_num(place)), kind=\"stable\")",
           "order = np.argsort(grids[j][:candidates] @ np.nan_to_num(place), kind=\"stable\")",
           ("test_guides.py",),
           "a landmark guided at the grid vertex farthest from it", k="nearest_its_place"),
    # --- the build's tables (outputs.py) ---
    Mutant("distance_in_voxels_times_the_voxel", "outputs.py",
           '"mean_distance_voxels": float(distances.mean() / case.voxel_size),',
           '"mean_distance_voxels": float(distances.mean() * case.voxel_size),',
           ("test_outputs_recomputed.py",),
           "cases.csv's distance in voxels multiplied by the voxel size (right at 1 mm only)"),
    Mutant("largest_surface_distance_averaged", "outputs.py",
           '"max": float(np.max([c["max_distance_mm"] for c in cases]))},',
           '"max": float(np.mean([c["max_distance_mm"] for c in cases]))},',
           ("test_outputs_recomputed.py",),
           "metrics.json's largest surface distance the mean of the cases' largest"),
    Mutant("landmark_distance_not_euclidean", "folders.py",
           "float(np.linalg.norm(self.point - self.given))",
           "float(np.abs(self.point - self.given).sum())",
           ("test_markups.py",),
           "landmarks.csv's distance the sum of the coordinate differences"),
    Mutant("landmark_worst_case_is_the_nearest", "outputs.py",
           "worst = max(mine)", "worst = min(mine)",
           ("test_markups.py",),
           "metrics.json names the case nearest its landmark as the farthest"),
    # --- fit.json (model/fitting.py) ---
    Mutant("fit_departure_from_all_modes", "model/fitting.py",
           "departure = np.linalg.norm(result.aligned - model.instance(result.scores[:k]), axis=1)",
           "departure = np.linalg.norm(result.aligned - model.instance(result.scores), axis=1)",
           ("test_outputs_recomputed.py",),
           "a fitted case's departure measured from its reconstruction by all modes, not k"),
    Mutant("fit_reconstruction_one_mode_ahead", "model/fitting.py",
           "residual = aligned - model.instance(scores[:m])",
           "residual = aligned - model.instance(scores[:m + 1])",
           ("test_outputs_recomputed.py",),
           "fit.json's reconstruction error for M modes is that of M + 1"),
    # --- compare.csv (report/compare.py, model/evaluation.py) ---
    Mutant("compare_value_written_as_its_se", "report/compare.py",
           'values[measure][k], values[measure + "_se"][k])',
           'values[measure][k], values[measure][k])',
           ("test_compare_csv.py",),
           "compare.csv's SE column holds the value"),
    Mutant("compare_cases_matched_by_position", "report/compare.py",
           "index = [position[n] for n in shared]",
           "index = list(range(len(shared)))",
           ("test_compare_csv.py",),
           "models compared case by position, not by name"),
    Mutant("difference_se_summed", "model/evaluation.py",
           "se = np.hypot(np.asarray(other[measure + \"_se\"]),",
           "se = np.add(np.asarray(other[measure + \"_se\"]),",
           ("test_compare_csv.py",),
           "the SE of an unpaired difference the sum of the SEs (too few differences called)"),
    # --- meshes: what test_remesh.py and test_sphere.py reached through private functions ---
    Mutant("half_edges_next_reversed", "prepare/remesh.py",
           "nxt[half] = corners[:, [1, 2, 0]].ravel()",
           "nxt[half] = corners[:, [2, 0, 1]].ravel()",
           ("test_remesh.py",),
           "the remesher's half-edges run each triangle backwards", k="oriented_genus_0"),
    Mutant("corner_lists_lose_the_first_corner", "prepare/multilevel.py",
           "head[corners[order[starts]]] = order[starts]",
           "head[corners[order[starts]]] = order[starts][::-1]",
           ("test_sphere.py",),
           "each vertex's corner list starts at another vertex's corner",
           k="vertex_numbering"),
    # --- the prior's weight where landmarks guide (config.py, initial.py, build.py) ---
    Mutant("guided_smoothness_not_applied", "config.py",
           "return GUIDED_SMOOTHNESS if guided else SMOOTHNESS", "return SMOOTHNESS",
           ("test_guides.py",),
           "the prior's default weight where landmarks guide never applied (the unguided one)",
           k="default_weight"),
    Mutant("guided_smoothness_for_every_surface", "correspondence/initial.py",
           "weight = config.smoothness_for(curves=False, guided=guides is not None)",
           "weight = config.smoothness_for(curves=False, guided=True)",
           ("test_guides.py",),
           "the guided default weight applied to unguided builds too", k="default_weight"),
    Mutant("guided_smoothness_not_recorded", "build.py",
           "guided=state.guides is not None))", "guided=False))",
           ("test_guides.py",),
           "the model records the unguided weight after a guided build: fit applies another "
           "prior than the build did", k="default_weight"),
    # --- the initial rigid alignment of the surfaces (prepare/sphere.py reference_frames) ---
    Mutant("frame_twists_dropped", "prepare/sphere.py",
           "return [twist @ flip for flip in flips for twist in twists]",
           "return [flip for flip in flips]",
           ("test_sphere.py",),
           "no turns about the first axis: two near-equal axes of a cross-section leave a "
           "long bone a quarter turn off", k="reference_frames"),
    Mutant("frame_ranked_farthest_first", "prepare/sphere.py",
           'for k in np.argsort(distances, kind="stable")[:FRAME_REFINED]]',
           'for k in np.argsort(distances, kind="stable")[::-1][:FRAME_REFINED]]',
           ("test_sphere.py",),
           "the candidates at the largest chamfer distance refined (the frame turned over)",
           k="reference_frames"),
    Mutant("frame_sign_choices_listed_twice", "prepare/sphere.py",
           "flips = (np.eye(3), np.diag([-1.0, -1.0, 1.0]))",
           "flips = [np.diag(d) for d in ((1, 1, 1), (-1, -1, 1), (-1, 1, -1), (1, -1, -1))]",
           ("test_sphere.py",),
           "all four sign choices turned: every candidate rotation listed twice, the two refined "
           "the same one", k="frame"),
    Mutant("frame_not_refined", "prepare/sphere.py",
           "refined = [chamfer.refine(candidates[k])", "refined = [(candidates[k])",
           ("test_sphere.py",),
           "the candidate frames taken without closest-point refinement (up to 15 degrees off)",
           k="reference_frames"),
    # --- designs: repeated measures, resampling, contrasts, tails, categories, interactions ---
    Mutant("change_reversed", "analysis/study.py",
           "return per_case[repeated.pairs[:, 1]] - per_case[repeated.pairs[:, 0]]",
           "return per_case[repeated.pairs[:, 0]] - per_case[repeated.pairs[:, 1]]",
           ("test_analysis_designs.py",),
           "each subject's change taken baseline minus later: every effect on it reversed"),
    Mutant("mean_change_not_sign_flipped", "analysis/study.py",
           "flips=subjects.mean_change_tested,", "flips=False,",
           ("test_analysis_designs.py",),
           "the mean change resampled by permutations of a column of ones (p = 1 everywhere)"),
    Mutant("blocks_ignored_in_the_permutations", "analysis/resampling.py",
           "for codes_of in (codes, blocks):", "for codes_of in (codes,):",
           ("test_analysis_designs.py",),
           "time within subjects permuted across subjects (the exchangeability blocks ignored)"),
    Mutant("whole_subjects_permuted_within", "analysis/study.py",
           'whole_blocks=repeated is not None and repeated.design == "blocks",',
           "whole_blocks=False,",
           ("test_analysis_designs.py",),
           "a subjects' group permuted within subjects, where it never moves (p = 1)"),
    Mutant("one_sided_tail_reversed", "analysis/glm.py",
           'return (t if tail == "greater" else -t), t',
           'return (-t if tail == "greater" else t), t',
           ("test_analysis_designs.py",),
           "--tail greater tests an effect below 0 and --tail less one above"),
    Mutant("one_sided_tail_dropped", "analysis/study.py",
           'tail=config.tail if single and not pooled else "both",', 'tail="both",',
           ("test_analysis_designs.py",),
           "--tail ignored: every signed map two-sided"),
    Mutant("contrast_not_adjusted_for_the_other_columns", "analysis/study.py",
           "nuisance=np.hstack([subjects.nuisance, interest @ complement]))",
           "nuisance=subjects.nuisance)",
           ("test_analysis_designs.py",),
           "a contrast tested without the effect columns it leaves (not c'b of the full model)"),
    Mutant("mean_change_at_nuisance_zero", "analysis/table.py",
           "nuisance_columns = nuisance_columns - nuisance_columns.mean(axis=0)",
           "nuisance_columns = nuisance_columns",
           ("test_analysis_designs.py",),
           "the mean change adjusted for a categorical subject column is the reference "
           "level's change, not the change at the nuisance's mean"),
    Mutant("subjects_not_adjusted_for_within", "analysis/table.py",
           "nuisance_columns = np.hstack([own, nuisance_columns])",
           "nuisance_columns = nuisance_columns",
           ("test_analysis_designs.py",),
           "time within subjects tested without each subject's own level (the subjects' "
           "spread left in the errors)"),
    Mutant("interaction_with_its_main_effect_tested", "config.py",
           "tested = test or ([] if interactions else [group] if group else covariates)",
           "tested = test or ([group] if group else covariates)",
           ("test_analysis_designs.py",),
           "an interaction tested together with the group instead of adjusted for it"),
    Mutant("categorical_levels_in_text_order", "analysis/table.py",
           "sorted(set(row[column] for row in design_rows), key=_level_order)",
           "sorted(set(row[column] for row in design_rows))",
           ("test_analysis_table.py",),
           "numeric codes of a categorical column in text order (10 before 2: another "
           "reference)"),
    # --- the resistant superimposition and the effect on size (analysis/) ---
    Mutant("robust_weights_ignored", "analysis/superimposition.py",
           "_normalised(weights * r)", "_normalised(weights)",
           ("test_analysis_superimposition.py",),
           "each case aligned with the area weights alone: least squares under another name"),
    Mutant("robust_mean_unweighted", "analysis/superimposition.py",
           "mean = _robust_mean(aligned, robust)", "mean = aligned.mean(axis=0)",
           ("test_analysis_superimposition.py",),
           "the mean the cases are aligned to is the plain mean (the changed points pull it)"),
    Mutant("biweight_scale_without_chi", "analysis/superimposition.py",
           "sigma = np.median(residuals, axis=1, keepdims=True) / np.sqrt(chi2.median(dimensions))",
           "sigma = np.median(residuals, axis=1, keepdims=True)",
           ("test_analysis_superimposition.py",),
           "the biweight scaled by the median residual norm (1.5 coordinate SDs in 3-D): "
           "4.685 loses its meaning, far points kept"),
    Mutant("biweight_without_cutoff", "analysis/superimposition.py",
           "return np.where(u < 1, (1 - u ** 2) ** 2, 0.0)", "return (1 - u ** 2) ** 2",
           ("test_analysis_superimposition.py",),
           "points beyond the biweight's cut-off weigh more again instead of nothing"),
    Mutant("biweight_planar_as_3d", "analysis/superimposition.py",
           "robust = biweight(np.linalg.norm(aligned - mean, axis=2), tuning, 2 if planar else 3)",
           "robust = biweight(np.linalg.norm(aligned - mean, axis=2), tuning, 3)",
           ("test_analysis_superimposition.py",),
           "2-D outlines' residuals scaled as 3-D ones (the scale 30 % too small)"),
    Mutant("size_of_the_scaled_shapes", "analysis/study.py",
           "sizes = np.array([centroid_size(x, unit) for x in used])",
           "sizes = np.array([centroid_size(x, unit) for x in aligned])",
           ("test_analysis_superimposition.py",),
           "the effect on centroid size measured after --size removed scaled every case to one "
           "size (no effect)", k="effect_on_size"),
    # --- the long table (analyze --long-table) ---
    Mutant("long_table_normal_reversed", "analyze.py",
           'normal = np.einsum("npd,pd->np", analysis.aligned - analysis.mean, analysis.normals)',
           'normal = np.einsum("npd,pd->np", analysis.mean - analysis.aligned, analysis.normals)',
           ("test_analysis_long_table.py",),
           "long.csv's normal displacement with its sign reversed (inward written as outward)"),
    Mutant("long_table_rows_by_position", "analyze.py",
           '+ [by_case[case].get(c, "") for c in columns])',
           '+ [rows[i].get(c, "") for c in columns])',
           ("test_analysis_long_table.py",),
           "long.csv gives a case the table row at its position (off after a left-out case)"),
    # --- the build folder (folders.py) ---
    Mutant("scores_written_coarse", "folders.py",
           '[[name] + [f"{v:.6g}" for v in row] for name, row in zip(names, scores)]',
           '[[name] + [f"{v:.3g}" for v in row] for name, row in zip(names, scores)]',
           ("test_folders.py",),
           "scores.csv keeps three significant digits"),
    Mutant("measures_se_of_the_value", "folders.py",
           'metrics.get(f"{key}_se",', "metrics.get(key,",
           ("test_folders.py",),
           "a build's measures read with each value as its own standard error"),
    Mutant("checkpoint_replaced_unasked", "folders.py",
           "KEPT_BUILD_FILES = (MODEL, CHECKPOINT)", "KEPT_BUILD_FILES = (MODEL,)",
           ("test_folders.py",),
           "a new build clears a resumable build's checkpoint without --overwrite"),
    Mutant("case_meshes_of_the_other_frame", "folders.py",
           "(ALIGNED if aligned else CORRESPONDENCE)", "(CORRESPONDENCE if aligned else ALIGNED)",
           ("test_folders.py",),
           "a build's shapes read from aligned/ (the model's frame) as if from its inputs' space"),
    Mutant("landmark_given_read_as_the_point", "folders.py",
           'given = np.array([float(row[f"given_{c}"]) for c in "xyz"])',
           'given = np.array([float(row[c]) for c in "xyz"])',
           ("test_folders.py",),
           "landmarks.csv's given landmark read from the corresponded point's columns"),
    # --- the empirical null of the unusual cases (model/outliers.py) ---
    Mutant("empirical_null_centre_unfloored", "model/outliers.py",
           "body = EmpiricalNull(max(centre, 0.0), max(spread, 1.0))",
           "body = EmpiricalNull(centre, max(spread, 1.0))",
           ("test_analysis_statistics.py",),
           "the null's centre allowed below 0: cases whose z-values sit low flag more than the "
           "normal theory would"),
    Mutant("empirical_null_spread_from_the_lower_quantile", "model/outliers.py",
           "/ float(norm.isf(1 - NULL_QUANTILE))", "/ float(norm.isf(NULL_QUANTILE))",
           ("test_analysis_statistics.py",),
           "the upper spread divided by Phi^-1(0.1) < 0: always floored to 1, the null's spread "
           "ignored"),
    Mutant("empirical_null_threshold_without_the_centre", "model/outliers.py",
           "z = self.centre + self.spread * norm.isf(alpha)",
           "z = self.spread * norm.isf(alpha)",
           ("test_analysis_statistics.py",),
           "the distance threshold drawn as if the null were centred at 0 (its flags and its "
           "threshold disagree)"),
    # --- G(M) from a subset of the cases (model/evaluation.py) ---
    Mutant("subsample_se_without_finite_population", "model/evaluation.py",
           "remaining = np.sqrt(max(1.0 - len(order) / n_s, 0.0) / len(order))",
           "remaining = np.sqrt(1.0 / len(order))",
           ("test_evaluation_subsample.py",),
           "the subset's standard error as if drawn with replacement (too large, not 0 when "
           "nearly every case is left out)"),
    Mutant("subset_drawn_from_the_evaluations_generator", "model/evaluation.py",
           "cases = leave_out_cases(n_s, generalization_cases, rng.spawn(1)[0])",
           "cases = leave_out_cases(n_s, generalization_cases, rng)",
           ("test_evaluation_subsample.py",),
           "the subset drawn from the specificity's generator: a limit moves its samples"),
    Mutant("subset_drawn_with_replacement", "model/evaluation.py",
           "return np.sort(rng.choice(n_shapes, size=limit, replace=False))",
           "return np.sort(rng.choice(n_shapes, size=limit, replace=True))",
           ("test_evaluation_subsample.py",),
           "a case left out twice in the subset (its error counted twice, another case's none)"),
    Mutant("subset_jackknife_keeps_only_the_group", "model/evaluation.py",
           "left_out = np.array([per_case[group_of != g].mean(axis=0) for g in range(count)])",
           "left_out = np.array([per_case[group_of == g].mean(axis=0) for g in range(count)])",
           ("test_evaluation_subsample.py",),
           "a subset's jackknife means of the group itself, not of the cases without it"),
    # --- the viewer's sample of a large population (report/viewer.py) ---
    Mutant("viewer_sample_named_by_position", "report/viewer.py",
           'cases = [str(names[i]) if i < len(names) else f"case {i + 1}" for i in shown]',
           'cases = [str(names[i]) if i < len(names) else f"case {i + 1}" '
           'for i in range(len(shown))]',
           ("test_viewer.py",),
           "the sampled cases under the names of the first cases"),
    Mutant("viewer_sample_distances_of_the_first_cases", "report/viewer.py",
           "kept = np.asarray(distances, dtype=np.float64)[shown]",
           "kept = np.asarray(distances, dtype=np.float64)[:len(shown)]",
           ("test_viewer.py",),
           "a sampled case coloured by the distances to its input of another case"),
    Mutant("viewer_sample_scores_unweighted", "report/viewer.py",
           "weighted = np.asarray(model.modes[0]) * np.asarray(model.weights)[:, None]",
           "weighted = np.asarray(model.modes[0])",
           ("test_viewer.py",),
           "the first mode's scores without the points' weights: the sample ranked on another "
           "score where the weights differ"),
    # --- the candidate frames (prepare/sphere.py frame_turns) ---
    Mutant("frame_twists_to_the_full_turn", "prepare/sphere.py",
           "angles = 2.0 * np.pi * np.arange(FRAME_TWISTS) / FRAME_TWISTS",
           "angles = 2.0 * np.pi * np.arange(FRAME_TWISTS) / (FRAME_TWISTS - 1)",
           ("test_sphere.py",),
           "the twists spread up to the full turn: the first and last the same rotation",
           k="frame"),
    # --- the time left in a build's reports (progress.TimeLeft) ---
    Mutant("time_left_rate_inverted", "progress.py",
           "elapsed * (1.0 - fraction) / fraction", "elapsed * fraction / (1.0 - fraction)",
           ("test_time_left.py",),
           "a counted stage's time left from the rate of what is left, not of what is done"),
    Mutant("time_left_budget_not_counted_down", "progress.py",
           "time_left_text(self.budget - elapsed)", "time_left_text(self.budget)",
           ("test_time_left.py",),
           "the optimisation's bound the whole budget at every report"),
    Mutant("time_left_counted_stage_from_its_first_report", "progress.py",
           "self.stage_start = now if fraction is None else self.last",
           "self.stage_start = now",
           ("test_time_left.py",),
           "a counted stage timed from its first report, whose step is already done: no "
           "estimate there, and too little time left after it"),
    Mutant("time_left_budget_from_the_stage_before", "progress.py",
           "self.stage_start = now if fraction is None else self.last",
           "self.stage_start = self.last",
           ("test_time_left.py",),
           "the budget counted from the last report of the stage before (the gap before the "
           "optimisation's first report taken off the budget)"),
    Mutant("time_left_one_budget_for_every_optimisation", "progress.py",
           "or (optimising and not self.optimising)", "or False",
           ("test_time_left.py",),
           "a landmark check's fold bounded by what the build's optimisation left of the budget"),
    Mutant("time_left_kind_lost_on_the_way", "progress.py",
           "return self.progress(fraction, Message(message, kind, rounds_left))",
           "return self.progress(fraction, message)",
           ("test_time_left.py",),
           "the reports' kind lost after the estimate: the command line, the worker and the "
           "module no longer know the optimisation's reports"),
    Mutant("time_left_rounds_timed_from_before_the_first", "progress.py",
           "schedule = elapsed / (self.rounds - 1) * rounds_left",
           "schedule = elapsed / self.rounds * rounds_left",
           ("test_time_left.py",),
           "the mean round taken over one report more than the intervals timed: every schedule "
           "estimate too short"),
    Mutant("time_left_said_after_the_last_round", "progress.py",
           "elif optimising and rounds_left != 0 and not", "elif optimising and not",
           ("test_time_left.py",),
           "the optimisation's last report still bounded by the budget, though no round is left"),
    Mutant("most_rounds_leave_out_the_next_round", "correspondence/strategies/fast.py",
           'schedule = ((rounds_per_level - at["round"])',
           'schedule = ((rounds_per_level - at["round"] - 1)',
           ("test_time_left.py",),
           "the rounds left counted without the round the schedule goes on with"),
    Mutant("rounds_left_counted_from_the_round_just_made", "correspondence/strategies/fast.py",
           "most_rounds(settings, levels, rounds_per_level, upcoming, sweep))",
           "most_rounds(settings, levels, rounds_per_level, at, sweep))",
           ("test_time_left.py",),
           "each report's bound one round too many, and blind to a level cut short"),
    Mutant("rounds_left_past_the_sweep_limit", "correspondence/strategies/fast.py",
           "return min(schedule, settings.max_sweeps - made)",
           "return min(schedule, settings.max_sweeps)",
           ("test_time_left.py",),
           "the sweep limit's rounds counted from the phase's start, not from the round made"),
    Mutant("rounds_left_of_this_phase_only", "correspondence/strategies/__init__.py",
           "message = Message(message, kind_of(message), left + after)",
           "message = Message(message, kind_of(message), left)",
           ("test_time_left.py",),
           "the full objective's rounds left out of the fixed-Delta phase's bound"),
    # --- the memory handed back, the locators' matrices computed where used ---
    Mutant("memory_release_in_a_loop_every_time", "memory.py",
           "and now - _LAST < at_most_every:",
           "and now - _LAST > at_most_every:",
           ("test_memory.py",),
           "a release inside a loop made every pass: the next pass faults the pages in again"),
    Mutant("face_inverse_determinant_summed_in_order", "correspondence/hotloops.py",
           "det = (ax * m[0, 0] + az * m[0, 2]) + ay * m[0, 1]",
           "det = ax * m[0, 0] + ay * m[0, 1] + az * m[0, 2]",
           ("test_sampling.py",),
           "a face's inverse no longer numpy's bit for bit: the samples, and so every build, "
           "differ in their last digits from a stored matrix's", k="inverse"),
    # --- the optimisation's blocks, here and on Dask (correspondence/strategies/) ---
    Mutant("curve_shift_gradient_reversed", "correspondence/strategies/blocks.py",
           "return np.append(self.basis.weights.T @ along, along.sum())",
           "return np.append(self.basis.weights.T @ along, -along.sum())",
           ("test_circle.py",),
           "a curve's origin shift moved up its objective's slope", k="fast"),
    Mutant("true_surfaces_newest_evicted", "model/surface_measures.py",
           "self.built.popitem(last=False)", "self.built.popitem(last=True)",
           ("test_evaluation.py",),
           "past the bound, the surface just built is the one dropped",
           k="surface_specificity"),
    Mutant("block_trials_all_dropped", "correspondence/strategies/blocks.py",
           "for k, (kept, samples) in self.trials.items() if k in keep}",
           "for k, (kept, samples) in self.trials.items() if False}",
           ("test_strategies.py",),
           "a trial kept for its gradient or commit dropped at the next sample",
           k="fast"),
    Mutant("locate_block_short_by_one", "correspondence/sampling.py",
           "todo[start:start + LOCATE_BLOCK]", "todo[start:start + LOCATE_BLOCK - 1]",
           ("test_sampling.py",),
           "the last point of every block of points located near their nearest vertices skipped",
           k="locate"),
    Mutant("set_aside_drops_located_faces", "correspondence/state.py",
           "                    part.points = None\n",
           "                    part.points = part.hint = None\n",
           ("test_coarse.py",),
           "the full grid's located faces set aside too (its points then located afresh)",
           k="set_aside"),
    Mutant("projected_gradient_kept_through_the_line_search",
           "correspondence/strategies/quasi_newton.py",
           "        del projected ", "        projected = projected ",
           ("test_quasi_newton.py",),
           "the projected gradient held through every evaluation of the line search",
           k="six_vectors"),
    # --- the prepared surfaces in a mapped file (prepare/mapped.py, memory.py) ---
    Mutant("mapped_padding_not_counted", "prepare/mapped.py",
           "    offset += padding\n", "",
           ("test_mapped.py",),
           "each array's recorded place ignores the padding before it: the views are shifted",
           k="read_only_views"),
    Mutant("mapped_pages_kept", "memory.py",
           "mapping.madvise(mmap.MADV_DONTNEED)", "mapping.madvise(mmap.MADV_NORMAL)",
           ("test_mapped.py",),
           "a release leaves the pages read of the mapped surfaces resident", k="release"),
    Mutant("helper_sent_every_mesh", "model/evaluation.py",
           'self.file = getattr(prepared, "file", None) if from_file else None',
           "self.file = None",
           ("test_mapped.py",),
           "a pool's process receives a copy of every mesh instead of reading the file",
           k="pool_process"),
    Mutant("cluster_last_stretch_dropped", "correspondence/strategies/spread.py",
           "edges = [len(self.active) * k // count for k in range(count + 1)]",
           "edges = [len(self.active) * k // count for k in range(count)]",
           ("test_dask.py",),
           "the last worker's stretch of examples never made", k="gives_the_local_correspondence",
           slow=True),
    Mutant("cluster_lost_stretch_keeps_one_trial", "correspondence/strategies/spread.py",
           "stretch.blocks.sample(number, x, keep)",
           "stretch.blocks.sample(number, x, ())",
           ("test_dask.py",),
           "a lost worker's stretch taken here keeps only the last trial sampled again",
           k="worker_lost_in_a_round or keeps_the_trials_the_round_kept", slow=True),
    Mutant("carried_fold_rule_ignored", "correspondence/carried.py",
           "if self.unfolded is not None and folds(self.positions, self.triangles):",
           "if False:",
           ("test_coarse.py",),
           "a carried grid keeps a warp that turned a triangle of the model's grid over",
           k="carried"),
    Mutant("carried_grid_not_moved", "correspondence/state.py",
           "            self.carried.move(warp)\n\n    def replay",
           "            pass\n\n    def replay",
           ("test_coarse.py",),
           "the coarse stage's accepted warps never reach the model's grid"),
    Mutant("carried_positions_not_recorded", "correspondence/state.py",
           'arrays[f"carried_{i}_{j}"] = carried.positions',
           'arrays[f"carried_{i}_{j}"] = part.grid',
           ("test_coarse.py",),
           "a resumed coarse stage starts its model-grid positions again from the grid"),
    Mutant("carried_first_positions_not_nested", "correspondence/state.py",
           "self.positions = finer.positions[:n].copy()",
           "self.positions = finer.positions[-n:].copy()",
           ("test_coarse.py",),
           "F after a coarse stage is measured at the wrong points of the model's grid"),
    Mutant("failed_task_settled", "parallel.py",
           "                or self.future.exception() is not None):",
           "                or False):",
           ("test_workers.py",),
           "a run that failed on the executor is taken as done and its arguments dropped",
           k="settled_task"),
    Mutant("resource_tracker_left_loud", "parallel.py",
           "        sys.warnoptions.append(RESOURCE_TRACKER_QUIET)",
           "        pass",
           ("test_workers.py",),
           "a second Ctrl-C ends the build with a warning of leaked semaphores",
           k="ended_at_once"),
    Mutant("accepted_warp_counted_twice", "correspondence/state.py",
           "            self.warps.append(warp)\n        self.counts[warp.kind] = self.counts.get(warp.kind, 0) + 1",
           "            self.warps.append(warp)\n        self.counts[warp.kind] = self.counts.get(warp.kind, 0) + 2",
           ("test_correspondence_record.py",),
           "cases.csv's warps and warp_kinds count every accepted warp twice",
           k="records_the_warps"),
    Mutant("single_pairs_kept_double", "correspondence/strategies/quasi_newton.py",
           "            pairs.append(CurvaturePair(s.astype(pairs_dtype, copy=False),\n"
           "                                       y.astype(pairs_dtype, copy=False),",
           "            pairs.append(CurvaturePair(s, y,",
           ("test_quasi_newton.py",),
           "--curvature-pairs single keeps the pairs in double precision: no memory saved",
           k="rounding_only"),
    Mutant("auto_pairs_single_below_the_switch", "correspondence/strategies/quasi_newton.py",
           '(choice == "auto" and size >= SINGLE_PRECISION_PAIRS_FROM)',
           '(choice == "auto" and size <= SINGLE_PRECISION_PAIRS_FROM)',
           ("test_quasi_newton.py", "test_strategies.py"),
           "auto rounds every small build's pairs to single precision and large builds keep double",
           k="precision"),
    Mutant("round_ignores_the_pairs_setting", "correspondence/strategies/fast.py",
           "                                   curvature_pairs=settings.curvature_pairs)",
           "                                   )",
           ("test_strategies.py",),
           "--curvature-pairs single is recorded but the rounds keep double-precision pairs",
           k="precision"),
    Mutant("pair_scale_of_the_oldest_pair", "correspondence/strategies/quasi_newton.py",
           "        q *= pairs[-1].scale",
           "        q *= pairs[0].scale",
           ("test_quasi_newton.py",),
           "the initial inverse Hessian is scaled by the oldest pair, not the newest",
           k="dense_bfgs"),
    Mutant("int16_tables_past_their_range", "correspondence/sampling.py",
           "    return np.int16 if count <= INT16_INDEX_LIMIT else np.int32",
           "    return np.int16 if count <= 2 * INT16_INDEX_LIMIT + 1 else np.int32",
           ("test_sampling.py",),
           "surfaces of 32,768-65,535 vertices or faces get int16 tables: their indices wrap",
           k="index_dtype or narrow"),
    Mutant("locator_faces_around_vertices_in_int32", "correspondence/sampling.py",
           "        self.vertex_faces = vertex_face_table(self.faces, len(self.sphere)).astype(index)",
           "        self.vertex_faces = vertex_face_table(self.faces, len(self.sphere)).astype("
           "np.int32)",
           ("test_sampling.py",),
           "the locator's largest table stays int32: no memory saved",
           k="narrow"),
    Mutant("located_faces_in_int64", "correspondence/sampling.py",
           "        face = np.full(n, -1, dtype=self.faces.dtype)",
           "        face = np.full(n, -1, dtype=np.int64)",
           ("test_sampling.py",),
           "every part keeps its walk hints in int64: four times the bytes",
           k="narrow"),
    Mutant("recorded_hints_kept_int64", "correspondence/state.py",
           "                    part.hint = part.hint.astype(part.faces.dtype)",
           "                    part.hint = part.hint",
           ("test_correspondence_record.py",),
           "a resumed build keeps an older checkpoint's int64 hints (and compiles its kernels again)",
           k="int64_faces"),
    Mutant("part_faces_a_second_copy", "correspondence/state.py",
           "        self.faces = self.locator.faces",
           "        self.faces = faces",
           ("test_state.py",),
           "every part holds its triangles twice, once in int64",
           k="narrow_copy"),
    Mutant("resumed_baselines_evaluated_again", "build.py",
           "        kept = folder.baselines(print_of) if resumed is not None else {}",
           "        kept = {}",
           ("test_resume.py",),
           "a resumed build evaluates its baselines again beside its first rounds",
           k="baselines_evaluation_its_first_run_kept", slow=True),
    Mutant("baselines_kept_only_at_the_end", "build.py",
           "            keep_baselines({name: outcome for name, (_, outcome) in pending.items()})",
           "            pass",
           ("test_resume.py",),
           "a build killed in its optimisation has kept no baseline evaluation",
           k="baselines_evaluation_its_first_run_kept", slow=True),
    Mutant("baselines_of_any_build_taken", "folders.py",
           "            if kept[\"fingerprint\"] != _digest(fingerprint):",
           "            if False:",
           ("test_folders.py",),
           "a resumed build takes baselines evaluated for other inputs or settings",
           k="baselines_evaluations"),
    Mutant("helper_rests_in_every_build", "build.py",
           "            if (settled() and len(prepared) >= HELPER_RESTS_FROM and executor is None",
           "            if (settled() and executor is None",
           ("test_workers.py",),
           "small builds end their helper too and pay a fresh start for the model's evaluation",
           k="large_build"),
    Mutant("resumed_record_kept", "correspondence/strategies/__init__.py",
           "    resume.record.clear()\n",
           "    pass\n",
           ("test_resume.py",),
           "a resumed build holds the checkpoint's arrays through its optimisation (1.5 GB at "
           "10,000 cases)",
           k="any_checkpoint"),
    Mutant("symmetric_box_lower_bound_zero", "correspondence/strategies/quasi_newton.py",
           "            return -upper",
           "            return 0.0 * upper",
           ("test_quasi_newton.py",),
           "the fast strategy's rounds keep every coefficient >= 0: half the fields' directions",
           k="symmetric"),
    Mutant("sample_scores_last_columns", "model/space.py",
           "rng.standard_normal((stop - start, rank))[:, :used] * sd[:used]",
           "rng.standard_normal((stop - start, rank))[:, rank - used:] * sd[:used]",
           ("test_evaluation.py",),
           "the specificity's samples take other normals than one draw of them all would",
           k="known_modes"),
    Mutant("covariance_axes_ascending", "model/space.py",
           "    return np.sqrt(np.clip(eigenvalues[::-1], 0.0, None)), vectors[:, ::-1]",
           "    return np.sqrt(np.clip(eigenvalues, 0.0, None)), vectors",
           ("test_evaluation.py",),
           "past the switch the model's modes come smallest first",
           k="past_the_switch"),
]


def check(mutants: list, chosen: list) -> list:
    """Problems of the list: an original that does not occur exactly once, a replacement equal
    to it, a name used twice; a test file of a ``chosen`` mutant that does not exist."""
    problems, names = [], set()
    for mutant in mutants:
        if mutant.name in names:
            problems.append(f"{mutant.name}: the name is used twice")
        names.add(mutant.name)
        path = PACKAGE / mutant.file
        if not path.is_file():
            problems.append(f"{mutant.name}: no file {mutant.file}")
            continue
        count = path.read_text(encoding="utf-8").count(mutant.original)
        if count != 1:
            problems.append(f"{mutant.name}: the original text occurs {count} times in "
                            f"{mutant.file} (must be once)")
        if mutant.original == mutant.replacement:
            problems.append(f"{mutant.name}: the replacement is the original")
        for test in mutant.tests if mutant in chosen else ():
            if not (TESTING / test.split("::")[0]).is_file():
                problems.append(f"{mutant.name}: no test file Testing/{test.split('::')[0]}")
    return problems


def run_tests(copy: Path, tests: tuple, k: str, slow: bool = False) -> tuple[int, str, float]:
    """(exit code, output, seconds) of the quick tests ``tests`` (``slow``: the slow ones too)
    with the package at ``copy``."""
    environment = dict(os.environ, PYTHONPATH=str(copy), PYTHONDONTWRITEBYTECODE="1")
    command = [sys.executable, "-m", "pytest", *tests, "-q", "-x",
               "-p", "no:cacheprovider", "-W", "ignore"] + ([] if slow else ["-m", "not slow"])
    if k:
        command += ["-k", k]
    started = time.perf_counter()
    try:
        result = subprocess.run(command, cwd=TESTING, env=environment, capture_output=True,
                                text=True, timeout=TIMEOUT)
        code, output = result.returncode, result.stdout + result.stderr
    except subprocess.TimeoutExpired as error:
        code, output = -1, f"timed out after {TIMEOUT} s\n{error.stdout or ''}"
    return code, output, time.perf_counter() - started


def failed_test(output: str) -> str:
    """The first failing test's id in pytest's summary ('' when none is named)."""
    found = re.search(r"^(?:FAILED|ERROR) (\S+)", output, flags=re.MULTILINE)
    return found.group(1) if found else ""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--list", action="store_true", help="list the mutants and check them")
    parser.add_argument("--only", action="append", metavar="NAME", help="run only this mutant")
    parser.add_argument("--no-baseline", action="store_true",
                        help="skip running each test selection on the unchanged package")
    arguments = parser.parse_args(argv)

    chosen = MUTANTS
    if arguments.only:
        unknown = sorted(set(arguments.only) - {m.name for m in MUTANTS})
        if unknown:
            print(f"no mutant named {', '.join(unknown)}", file=sys.stderr)
            return 2
        chosen = [m for m in MUTANTS if m.name in arguments.only]
    problems = check(MUTANTS, chosen)
    if problems:
        print("\n".join(problems), file=sys.stderr)
        return 2
    if arguments.list:
        for mutant in chosen:
            print(f"{mutant.name:40s} {mutant.file:28s} {' '.join(mutant.tests)}"
                  f"{' -k ' + mutant.k if mutant.k else ''}"
                  f"{' (slow tests too)' if mutant.slow else ''}\n    {mutant.description}")
        print(f"{len(chosen)} mutants; each original occurs once in its file")
        return 0

    with tempfile.TemporaryDirectory(prefix="mdlshapemodel-mutants-") as folder:
        copy = Path(folder)
        # copy2 keeps the modification times, which numba's cache and the .pyc files check
        shutil.copytree(PACKAGE, copy / "mdlshapemodel", copy_function=shutil.copy2)
        if not arguments.no_baseline:
            for selection in sorted({(m.tests, m.k, m.slow) for m in chosen}):
                code, output, seconds = run_tests(copy, *selection)
                if code != 0:
                    print(f"the tests {' '.join(selection[0])} fail without a mutant "
                          f"({seconds:.0f} s):\n{output[-3000:]}", file=sys.stderr)
                    return 2
        rows, survivors = [], []
        print(f"{'mutant':40s} {'result':9s} {'seconds':>7s}  by")
        for mutant in chosen:
            path = copy / "mdlshapemodel" / mutant.file
            original = path.read_bytes()
            stat = path.stat()
            try:
                path.write_text(original.decode("utf-8").replace(mutant.original,
                                                                 mutant.replacement),
                                encoding="utf-8")
                # another modification time, so that no cached .pyc of the original is used
                os.utime(path, (stat.st_atime, stat.st_mtime + 7))
                code, output, seconds = run_tests(copy, mutant.tests, mutant.k, mutant.slow)
            finally:
                path.write_bytes(original)
                os.utime(path, (stat.st_atime, stat.st_mtime))
            if code == 1:
                result, by = "killed", failed_test(output)
            elif code == 0:
                result, by = "SURVIVED", ""
                survivors.append(mutant.name)
            else:      # no test collected, a usage error, a time-out: not a kill
                result, by = "ERROR", (output.strip().splitlines() or ["?"])[-1][:80]
                survivors.append(mutant.name)
            rows.append((mutant.name, result, seconds, by))
            print(f"{mutant.name:40s} {result:9s} {seconds:7.0f}  {by}", flush=True)
        print(f"{len(rows) - len(survivors)} of {len(rows)} mutants killed")
        if survivors:
            print("not killed: " + ", ".join(survivors))
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
