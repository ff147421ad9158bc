"""The subjects table (mdlshapemodel.analysis.table): missing values leave a case out and are
listed, never change a column's kind; the kind of a column is its role; which columns are tested
and which adjusted for."""

from __future__ import annotations

import numpy as np
import pytest

from mdlshapemodel.analysis import subjects
from mdlshapemodel.errors import ConfigError, InputError

N = 12
NAMES = [f"case_{k:02d}" for k in range(N)]


def write(path, rows: list, header=("case", "group", "age", "site")):
    path.write_text("\n".join(",".join(map(str, row)) for row in [header, *rows]) + "\n")
    return path


def rows_of(ages=None, groups=None, sites=None) -> list:
    """One row per case: groups a/b alternating, ages spread, sites 1, 2, 3 in turn."""
    ages = ages or [40 + 3 * k for k in range(N)]
    groups = groups or ["a" if k % 2 else "b" for k in range(N)]
    sites = sites or [1 + k % 3 for k in range(N)]
    return [[NAMES[k], groups[k], ages[k], sites[k]] for k in range(N)]


@pytest.mark.parametrize("marker", ["NA", "nan", "NaN", "", "?", "N/A", "null"])
def test_a_missing_age_leaves_its_case_out_and_keeps_the_column_numeric(tmp_path, marker):
    ages = [40 + 3 * k for k in range(N)]
    ages[4] = marker
    with_marker = write(tmp_path / "marked.csv", rows_of(ages))
    without = write(tmp_path / "dropped.csv", [r for r in rows_of() if r[0] != "case_04"])
    design = subjects(with_marker, NAMES, group="group", covariates=["age"])
    assert [(o.case, o.missing) for o in design.left_out] == [("case_04", {"age": marker})]
    assert "age" in design.left_out[0].reason
    assert design.nuisance.shape == (N - 1, 1)             # age: one numeric column
    assert design.tested == ["group"] and design.adjusted_for == ["age"]
    direct = subjects(without, NAMES, group="group", covariates=["age"])
    assert design.cases == direct.cases and "case_04" not in design.cases
    np.testing.assert_array_equal(design.interest, direct.interest)
    np.testing.assert_array_equal(design.nuisance, direct.nuisance)


def test_a_stray_word_in_a_numeric_column_is_a_missing_value_listed_with_it(tmp_path):
    ages = [40 + 3 * k for k in range(N)]
    ages[3] = "old"
    design = subjects(write(tmp_path / "t.csv", rows_of(ages)), NAMES, covariates=["age"])
    assert [(o.case, o.missing) for o in design.left_out] == [("case_03", {"age": "old"})]
    assert design.left_out[0].reason == "'age' is not a number ('old')"
    assert design.interest.shape == (N - 1, 1)
    np.testing.assert_allclose(design.interest[:, 0] + np.mean(np.delete(ages, 3).astype(float)),
                               np.delete(ages, 3).astype(float))


def test_a_missing_group_leaves_its_case_out_instead_of_making_a_level(tmp_path):
    groups = ["a" if k % 2 else "b" for k in range(N)]
    groups[0] = "NA"
    design = subjects(write(tmp_path / "t.csv", rows_of(groups=groups)), NAMES, group="group")
    assert design.levels == ["a", "b"]
    assert [o.case for o in design.left_out] == ["case_00"]


@pytest.mark.parametrize("role", ["covariates", "nuisance"])
def test_a_numeric_column_of_words_is_refused_naming_the_file_the_column_and_values(tmp_path,
                                                                                   role):
    table = write(tmp_path / "t.csv", rows_of(ages=["F" if k % 3 else "M" for k in range(N)]))
    arguments = ({"covariates": ["age"]} if role == "covariates"
                 else {"group": "group", "nuisance": ["age"]})
    with pytest.raises(InputError) as error:
        subjects(table, NAMES, **arguments)
    message = str(error.value)
    assert str(table) in message and "'age' is not numeric" in message
    assert "'M', 'F'" in message and "12 of 12" in message
    assert "--categorical age" in message


def test_a_numeric_column_with_as_many_words_as_numbers_is_refused(tmp_path):
    ages = [40 + k if k % 2 else f"about {40 + k}" for k in range(N)]
    with pytest.raises(InputError, match="6 of 12 values are not numbers"):
        subjects(write(tmp_path / "t.csv", rows_of(ages)), NAMES, covariates=["age"])


def test_a_column_with_no_number_at_all_is_refused_in_one_line(tmp_path):
    table = write(tmp_path / "t.csv", rows_of(ages=["NA"] * N))
    with pytest.raises(InputError, match="no case of the build has a value in every column "
                                         r"used \(cases without one: group: 0, age: 12\)"):
        subjects(table, NAMES, group="group", covariates=["age"])


def test_a_numeric_coded_factor_is_categorical_when_declared_so(tmp_path):
    table = write(tmp_path / "t.csv", rows_of())
    numeric = subjects(table, NAMES, group="group", nuisance=["site"])
    assert numeric.nuisance.shape == (N, 1)
    np.testing.assert_allclose(numeric.nuisance[:, 0], [k % 3 - 1 for k in range(N)])
    factor = subjects(table, NAMES, group="group", nuisance=["site"], categorical=["site"])
    assert factor.nuisance.shape == (N, 2)                 # indicators of sites 2 and 3
    np.testing.assert_array_equal(factor.nuisance, [[k % 3 == 1, k % 3 == 2] for k in range(N)])
    assert factor.adjusted_for == ["site"]


def test_a_tested_categorical_covariate_is_one_test_over_its_levels(tmp_path):
    sites = [[1, 2, 10][k % 3] for k in range(N)]          # 10 after 2: levels in numeric order
    table = write(tmp_path / "t.csv", rows_of(sites=sites))
    design = subjects(table, NAMES, covariates=["site"], categorical=["site"])
    assert design.tested == ["site"] and design.interest_names == ["site=2", "site=10"]
    assert design.interest_columns == ["site", "site"]
    assert design.levels_of == {"site": ["1", "2", "10"]}
    np.testing.assert_array_equal(design.interest, [[s == 2, s == 10] for s in sites])
    assert design.notes == []


def test_a_numeric_column_of_few_whole_numbers_is_noted_by_name(tmp_path):
    table = write(tmp_path / "t.csv", rows_of())
    coded = subjects(table, NAMES, group="group", covariates=["age"], nuisance=["site"])
    assert len(coded.notes) == 1
    assert "'site' takes only the values 1, 2, 3" in coded.notes[0]
    assert "--categorical site" in coded.notes[0]
    declared = subjects(table, NAMES, group="group", covariates=["age"], nuisance=["site"],
                        categorical=["site"])
    assert declared.notes == []


def test_a_covariate_beside_a_group_is_tested_when_named_by_test(tmp_path):
    table = write(tmp_path / "t.csv", rows_of())
    adjusted = subjects(table, NAMES, group="group", covariates=["age"])
    assert adjusted.tested == ["group"] and adjusted.adjusted_for == ["age"]
    assert adjusted.interest_names == ["b"]
    tested = subjects(table, NAMES, group="group", covariates=["age"], test=["age"])
    assert tested.tested == ["age"] and tested.adjusted_for == ["group"]
    assert tested.interest_names == ["age"] and tested.interest_columns == ["age"]
    np.testing.assert_allclose(tested.interest[:, 0], 3 * np.arange(N) - 3 * (N - 1) / 2)
    np.testing.assert_array_equal(tested.nuisance, adjusted.interest)   # the group indicator
    both = subjects(table, NAMES, group="group", covariates=["age"], test=["group", "age"])
    assert both.interest_names == ["group=b", "age"] and both.nuisance.shape == (N, 0)


@pytest.mark.parametrize("arguments, message", [
    ({"group": "group", "nuisance": ["age"], "test": ["age"]},
     "test: 'age' is not the group or a covariate"),
    ({"group": "group", "categorical": ["site"]},
     "categorical: 'site' is not a column of the model (give it with --covariate site to test "
     "it, or --nuisance site)"),
    ({"group": "group", "covariates": ["group"]}, "column 'group' is given twice"),
    ({"nuisance": ["age"]}, "nothing to test"),
])
def test_roles_that_contradict_each_other_are_refused(tmp_path, arguments, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        subjects(write(tmp_path / "t.csv", rows_of()), NAMES, **arguments)
