"""What a build warns of reaches the module: a --label that no case holds."""

import numpy as np
import SimpleITK as sitk

import MDLShapeModel as module
from mdlshapemodel import BuildConfig
from synthetic import small_mask


def test_a_label_in_no_case_is_in_the_results_warnings(scene, tmp_path):
    paths = []
    for k, position in enumerate(np.linspace(-0.5, 0.5, 3)):
        paths.append(tmp_path / f"case_{k}.nii.gz")
        sitk.WriteImage(sitk.GetImageFromArray(small_mask(float(position)).astype(np.uint8)),
                        str(paths[-1]))
    config = BuildConfig(labels=[1, 4], points=42, strategy="none", baselines=[], workers=1,
                         evaluation_modes=1, specificity_samples=50, surface_samples=0)
    result = module.MDLShapeModelLogic().buildModel(paths, tmp_path / "out", config)
    assert result.warnings == ["label 4 is in none of the 3 label maps (labels found: 1)"]
    assert len(result.correspondenceModelNodes) == 3
