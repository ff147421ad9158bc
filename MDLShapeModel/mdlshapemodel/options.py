"""The command line's ``build`` options: how it offers each :class:`~.config.BuildConfig` field.

The settings themselves (types, defaults, choices, checks) are the fields' own, in config.py; here
is what only the command line needs: the group its help lists an option in, the flag, the help
text (``%(default)s`` stands for the field's default), the value's name, how a list is given.
:data:`NOT_OFFERED` names the fields the command line leaves at their defaults, and why.
"""

from __future__ import annotations

from dataclasses import dataclass

from .config import (CURVE_POINTS, DUPLICATE_DISTANCE, GUIDED_SMOOTHNESS, LANDMARK_CHECK_FOLDS,
                     MAX_SMOOTHING_SIGMA, MIN_SURFACE_VERTICES, SMOOTHNESS, SURFACE_POINTS,
                     SURFACE_VERTICES_PER_POINT)

#: The option groups, in the order the help lists them.
OPTION_GROUPS = ("correspondence", "inputs and surfaces", "running and evaluation")
CORRESPONDENCE, INPUTS, RUNNING = OPTION_GROUPS


@dataclass(frozen=True)
class Option:
    """How the command line offers one :class:`~.config.BuildConfig` field.

    Attributes
    ----------
    group : str
        One of :data:`OPTION_GROUPS`.
    help : str
        What the setting does; ``%(default)s`` stands for the field's default (argparse fills it
        in).
    flag : str, optional
        The flag when it is not ``--`` and the field's name with hyphens. The flag of a bool
        field whose default is True switches it off (``--no-...``).
    metavar : str or tuple, optional
        The value's name in the help.
    repeatable : bool
        List fields: the flag may be given again and adds items (else the last one counts).
    split : bool
        List fields: one argument holds several items, separated by commas or spaces.
    off_flag, off_value, off_help : optional
        A second flag that sets the field to ``off_value`` whatever the first says; its help.
    """

    group: str
    help: str
    flag: str | None = None
    metavar: str | tuple | None = None
    repeatable: bool = False
    split: bool = True
    off_flag: str | None = None
    off_value: object = None
    off_help: str | None = None

    def __post_init__(self):
        if self.group not in OPTION_GROUPS:
            raise TypeError(f"unknown option group {self.group!r}")

    def flag_of(self, name: str) -> str:
        """The flag of the field ``name``."""
        return self.flag or "--" + name.replace("_", "-")


#: The ``build`` options, in the order of their fields.
BUILD_OPTIONS = {
    "labels": Option(
        INPUTS, "label value(s) whose union is the object, e.g. --label 1,2 "
                "(default: all non-zero)",
        flag="--label", metavar="L", repeatable=True),
    "parts": Option(
        INPUTS, "a part of a multi-part object: its name and the label value(s) whose union "
                "it is, e.g. --part head=1 --part tail=2 (repeatable; each part gets its own "
                "surface, sphere map and --points sample points, and one pose moves all parts)",
        flag="--part", metavar="NAME=LABELS", repeatable=True, split=False),
    "voxel_size": Option(
        INPUTS, "mm per voxel for mesh inputs (default: their mean edge length)"),
    "mirror": Option(
        INPUTS, "reflect inputs whose file name matches PATTERN (x -> -x), e.g. "
                "--mirror '*_rfemur*' to model right and left sides together; repeatable",
        metavar="PATTERN", repeatable=True, split=False),
    "allow_duplicates": Option(
        INPUTS, "model a case given twice (identical files, or shapes whose RMS distance is "
                f"below {100 * DUPLICATE_DISTANCE:g}%% of their size) as it is; by default the "
                "build names such cases and stops before the optimisation"),
    "surface_method": Option(
        INPUTS, "label map -> surface: Gaussian blur + flying edges, or 3D Slicer's "
                "conversion (flying edges + windowed sinc); either blurs more when the surface "
                "is not genus 0 (default %(default)s)",
        flag="--surface"),
    "smoothing_factor": Option(
        INPUTS, "slicer: smoothing factor 0..1 of the windowed-sinc filter (default %(default)s)"),
    "decimation": Option(
        INPUTS, "slicer: fraction of triangles removed before smoothing (default %(default)s)"),
    "smoothing_sigma": Option(
        INPUTS, "gaussian: blur of masks before contouring, voxels (default %(default)s)",
        flag="--smoothing"),
    "max_smoothing_sigma": Option(
        INPUTS, "largest blur of masks whose surface is not genus 0 (blurred more in steps of "
                f"0.5), voxels (default: max({MAX_SMOOTHING_SIGMA:g}, --smoothing))",
        flag="--max-smoothing"),
    "edge_length": Option(
        INPUTS, "edge length of the remeshed surfaces of label maps, voxels, unless that gives "
                "more than --target-vertices vertices (default %(default)s)"),
    "target_vertices": Option(
        INPUTS, "about how many vertices the surfaces mapped to the sphere have at most: finer "
                "ones are remeshed with longer edges than --edge-length (default: "
                f"max({MIN_SURFACE_VERTICES}, {SURFACE_VERTICES_PER_POINT} x --points))"),
    "correspondence": Option(
        CORRESPONDENCE, "'mdl': optimised by minimum description length; 'cpd': a template "
                        "case registered onto every case by coherent point drift, the common "
                        "alternative, for comparison (default %(default)s)"),
    "baselines": Option(
        CORRESPONDENCE, "other correspondences evaluated on the same cases and shown in the "
                        "report: comma-separated from none (the initial correspondence) and "
                        "cpd; '' for no baseline (default none)",
        metavar="LIST"),
    "points": Option(
        CORRESPONDENCE, "sample points per part: on the sphere (an icosphere when 10*4^k+2) "
                        f"for surfaces, default {SURFACE_POINTS}; equally spaced on the circle "
                        f"for 2-D curves, default {CURVE_POINTS}"),
    "placement": Option(
        CORRESPONDENCE, "where a surface's sample points lie: 'sphere', an even grid on the "
                        "sphere (an icosphere when --points is 10*4^k+2); 'surface', spread "
                        "evenly over the population's mean surface, so that thin processes and "
                        "ridges, which the sphere maps squeeze, get their share "
                        "(default %(default)s)"),
    "strategy": Option(
        CORRESPONDENCE, "optimisation strategy; 'none' keeps the initial (equal-spacing) "
                        "correspondence (default %(default)s)"),
    "warps": Option(
        CORRESPONDENCE, "one-at-a-time strategies: the warps each step draws from, uniformly, "
                        "comma-separated from symmetric (the paper's theta kernel), asymmetric "
                        "and shear (the Appendix's asymmetric theta and shear/twist maps) and "
                        "rotation (a global rotation of the parameter sphere) "
                        "(default symmetric)",
        metavar="LIST"),
    "scaling": Option(
        CORRESPONDENCE, "keep size: Procrustes and pose use rotation and translation only",
        flag="--no-scaling"),
    "delta_range": Option(
        CORRESPONDENCE, "coding accuracy range of eq. 14 in voxels (default %(default)s)",
        metavar=("MIN", "MAX")),
    "fixed_delta": Option(
        CORRESPONDENCE, "coding accuracy of the first phase (eq. 13), voxels "
                        "(default %(default)s)"),
    "sigma_g": Option(
        CORRESPONDENCE, "width distribution of random kernels (default 1/32)"),
    "max_time": Option(
        CORRESPONDENCE, "time budget of the optimisation (default %(default)s)",
        metavar="SECONDS"),
    "fixed_fraction": Option(
        CORRESPONDENCE, "share of --max-time spent on the fixed-Delta phase before the full "
                        "objective; 0 skips it (default %(default)s)"),
    "tolerance": Option(
        CORRESPONDENCE, "convergence: stop when a sweep gains less than this fraction of the "
                        "total gain, three times in a row (default %(default)s)"),
    "max_sweeps": Option(
        CORRESPONDENCE, "at most N sweeps over the examples (fast: rounds) per phase; unlike "
                        "--max-time, a budget that repeats exactly (default %(default)s)",
        metavar="N"),
    "coarse_points": Option(
        CORRESPONDENCE, "fast strategy: optimise on this many sample points per part (the "
                        "objective is measured there) and carry the maps over to --points; 0: "
                        "optimise on --points (default %(default)s)",
        metavar="N"),
    "curvature_pairs": Option(
        CORRESPONDENCE, "fast strategy: the precision of the quasi-Newton curvature pairs, the "
                        "largest part of a large build's memory; single halves it and changes "
                        "the optimisation's path by rounding; auto: single in rounds of 4 "
                        "million coefficients or more (about 2,000 surfaces), double below "
                        "(default %(default)s)"),
    "landmarks": Option(
        CORRESPONDENCE, "folder of landmark files that guide the correspondence, one per case "
                        "named after it (3D Slicer .mrk.json or .fcsv, or CSV label,x,y,z; "
                        "LPS unless the file says RAS): each label is kept at one place across "
                        "the cases (surfaces; a case may lack labels or have no file)",
        metavar="DIR"),
    "landmark_weight": Option(
        CORRESPONDENCE, "--landmarks: the objective's cost of a landmark one voxel from its "
                        "corresponded point is half this, in nats; 0: the landmarks do not "
                        "guide the correspondence, they only measure it (the report shows how "
                        "far it carries each one) (default %(default)s)"),
    "check_landmarks": Option(
        CORRESPONDENCE, "--landmarks: measure how far the correspondence carries each label "
                        "where it does not guide it: the optimisation runs again with the "
                        f"label left out of the guides (up to {LANDMARK_CHECK_FOLDS} labels one "
                        f"at a time, more in {LANDMARK_CHECK_FOLDS} groups: one more "
                        "optimisation each); the errors go to the build's metrics and report"),
    "smoothness": Option(
        CORRESPONDENCE, "surfaces: weight of a prior on smooth correspondence, the thin-plate "
                        "bending energy of each case's displacement from the mean shape, per "
                        f"squared voxel; 0: none (default {SMOOTHNESS:g}, "
                        f"{GUIDED_SMOOTHNESS:g} where landmarks guide)",
        metavar="W"),
    "seed": Option(
        CORRESPONDENCE, "random seed of the paper's strategies (fast draws no random "
                        "numbers): the same seed and inputs give the same model bit for bit, "
                        "unless --max-time cuts the runs at different points "
                        "(default %(default)s)"),
    "evaluation_modes": Option(
        RUNNING, "measures are reported for M = 1..this (default %(default)s)"),
    "specificity_samples": Option(
        RUNNING, "model samples for specificity (default %(default)s)"),
    "surface_samples": Option(
        RUNNING, "model samples for specificity measured surface to surface; 0 leaves out the "
                 "surface-to-surface measures (default %(default)s)"),
    "generalization_cases": Option(
        RUNNING, "the generalization leaves out every case up to this many cases, and beyond "
                 "them a random subset of this many, with its standard error (default "
                 "%(default)s)", metavar="N"),
    "workers": Option(
        RUNNING, "processes for per-case work (default: all cores, %(default)s)"),
    "scheduler": Option(
        RUNNING, "run the per-case work (preparing, CPD baseline, evaluations) on the Dask "
                 "cluster whose scheduler is at ADDRESS, e.g. tcp://10.0.0.5:8786, instead "
                 "of --workers local processes; the same model bit for bit (needs pip install "
                 "\"mdlshapemodel[dask]\" here and on the workers; see the README)",
        metavar="ADDRESS"),
    "cache_dir": Option(
        RUNNING, "where preprocessed cases are kept for rebuilds (default: "
                 "$MDLSHAPEMODEL_CACHE or ~/.cache/mdlshapemodel)",
        metavar="DIR", off_flag="--no-cache", off_value="",
        off_help="preprocess every case again and store nothing"),
    "strict": Option(
        RUNNING, "fail (exit 2) if any input is rejected"),
}

#: The fields of :class:`~.config.BuildConfig` the command line does not offer, and why.
NOT_OFFERED = {
    "max_amplitude": "the bound of a kernel amplitude A: the command line keeps the paper's "
                     "(Table I)",
}
