"""What a build warns of reaches the module: a --label that no case holds, an optimisation
stopped before it converged."""

import numpy as np
import SimpleITK as sitk

import MDLShapeModel as module
from mdlshapemodel import BuildConfig
from synthetic import small_mask


def label_maps(folder) -> list:
    """Three small label maps (label 1) in ``folder``."""
    paths = []
    for k, position in enumerate(np.linspace(-0.5, 0.5, 3)):
        paths.append(folder / f"case_{k}.nii.gz")
        sitk.WriteImage(sitk.GetImageFromArray(small_mask(float(position)).astype(np.uint8)),
                        str(paths[-1]))
    return paths


def test_a_label_in_no_case_is_in_the_results_warnings(scene, tmp_path):
    paths = label_maps(tmp_path)
    config = BuildConfig(labels=[1, 4], points=42, strategy="none", baselines=[], workers=1,
                         evaluation_modes=1, specificity_samples=50, surface_samples=0)
    result = module.MDLShapeModelLogic().buildModel(paths, tmp_path / "out", config)
    assert result.warnings == ["label 4 is in none of the 3 label maps (labels found: 1)"]
    assert len(result.correspondenceModelNodes) == 3
    assert result.converged is None          # strategy none: nothing was optimised


def test_an_optimisation_out_of_time_is_in_the_results(scene, tmp_path):
    config = BuildConfig(points=42, strategy="fast", max_time=0, baselines=[], workers=1,
                         evaluation_modes=1, specificity_samples=50, surface_samples=0)
    result = module.MDLShapeModelLogic().buildModel(label_maps(tmp_path), tmp_path / "out",
                                                    config)
    assert result.converged is False
    [warning] = result.warnings
    assert warning.startswith("the optimisation stopped at the time limit")
    assert "--resume --max-time" in warning
