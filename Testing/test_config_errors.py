"""A refused setting is named by its field (``ConfigError.setting``) apart from the problem, so
that each face names it its own way; the message itself stays the command line's one line."""

import pytest

from mdlshapemodel.config import AnalysisConfig, BuildConfig, field_items
from mdlshapemodel.errors import ConfigError


@pytest.mark.parametrize("make, setting, problem", [
    (lambda: BuildConfig(points=5).validate(), "points", "must be at least 12 (got 5)"),
    (lambda: BuildConfig(max_time=-1.0).validate(), "max_time", "must be >= 0 (got -1.0)"),
    (lambda: BuildConfig(parts=["head=1", "head=2"]).validate(), "parts",
     "part names must differ (got ['head=1', 'head=2'])"),
    (lambda: AnalysisConfig(permutations=0).validate(), "permutations", None),
])
def test_a_refused_setting_carries_its_name_and_the_problem_without_it(make, setting, problem):
    with pytest.raises(ConfigError) as raised:
        make()
    assert raised.value.setting == setting
    assert str(raised.value) == f"{setting}: {raised.value.problem}"
    if problem is not None:
        assert raised.value.problem == problem


def test_a_list_setting_written_as_text_names_its_field():
    with pytest.raises(ConfigError, match="labels must be integers, got '1, a'") as raised:
        field_items("labels", "1, a")
    assert raised.value.setting == "labels"
    with pytest.raises(ConfigError) as raised:
        field_items("parts", "head=1, 2=x")
    assert raised.value.setting == "parts"


def test_an_error_of_no_one_setting_names_none():
    error = ConfigError("nothing to test: give a group column or a covariate")
    assert error.setting is None and error.problem == str(error)
