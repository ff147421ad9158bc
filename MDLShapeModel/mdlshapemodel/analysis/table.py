"""The table of subjects: which cases have which group and covariate values.

A CSV file with a ``case`` column whose values are the build's case names; every other column is
a variable. A column's kind is declared by its role in the analysis
(:func:`~mdlshapemodel.config.analysis_roles`), never guessed from its values: the group and the
columns named categorical are categorical (coded as indicators of their levels), the other
covariates and nuisance columns numeric. A numeric column of a few whole numbers (a site coded
1, 2, 3) is kept numeric, with a note naming it (:data:`FEW_CODES`).

Missing values: in any column the analysis uses, an empty cell or a marker of
:data:`MISSING_MARKERS` (any letter case); in a numeric column, also any other value that is not
a finite number. A case with a missing value is left out of the analysis and listed with the
column and the value, as are cases missing from the table; rows that match no case are listed. A
numeric column with as many words (non-numbers other than the markers) as numbers among the
build's cases is not a numeric column: an error naming it, not a list of left-out cases.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import analysis_roles
from ..errors import InputError

CASE = "case"
# cells that mean "no value" in any column (compared in lower case, after stripping blanks);
# "none" is not one of them: it can be a level (no treatment)
MISSING_MARKERS = ("", "na", "n/a", "nan", "null", "?", ".", "-", "#n/a")
# the smallest group that is tested: fewer cases than this cannot estimate a group's spread
MIN_GROUP = 3
# a numeric column whose values are at most this many distinct whole numbers (and at least 3:
# two codes are a linear covariate either way) is noted as possibly a coded factor
FEW_CODES = 5


@dataclass
class LeftOut:
    """A build case that an analysis does not use, and why.

    Attributes
    ----------
    case : str
        The case's name.
    reason : str
        One line: "not in the table", or each missing value with its column.
    missing : dict
        The columns without a usable value and their cells as written (empty when the case is
        not in the table).
    """

    case: str
    reason: str
    missing: dict = field(default_factory=dict)


@dataclass
class Subjects:
    """The cases an analysis uses and the design made of the table.

    Attributes
    ----------
    cases : list of str
        The cases used, in the build's order.
    indices : ndarray
        Their rows in the build's list of cases.
    interest : ndarray (n, r)
        The effect's columns: indicators of the non-reference groups, or the covariates of
        interest (centred).
    nuisance : ndarray (n, c)
        The nuisance columns (numeric covariates centred; categorical ones as indicators).
    interest_names : list of str
        A name per interest column: the group level it indicates, or the covariate (a level is
        named ``group=level`` when other columns are tested with the group).
    interest_columns : list of str
        The table column of each interest column.
    tested : list of str
        The table columns whose effect is tested.
    adjusted_for : list of str
        The other table columns of the model.
    group : str or None
        The group column (tested or adjusted for).
    groups : list of str or None
        Each used case's group (None without ``--group``).
    levels : list of str
        The group levels, reference first (empty without ``--group``).
    left_out : list of LeftOut
        Build cases that are not used, and why.
    unmatched : list of str
        Table rows whose case is not one of the build's.
    levels_of : dict
        Each categorical column of the model: its levels, reference first.
    notes : list of str
        Warnings about the design that do not stop it (a numeric column that looks like coded
        categories).
    """

    cases: list
    indices: np.ndarray
    interest: np.ndarray
    nuisance: np.ndarray
    interest_names: list
    interest_columns: list
    tested: list
    adjusted_for: list
    group: str | None
    groups: list | None
    levels: list
    left_out: list = field(default_factory=list)
    unmatched: list = field(default_factory=list)
    levels_of: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)

    def n_per_group(self) -> dict | None:
        """Cases per group level, reference first (None without a group)."""
        if self.groups is None:
            return None
        return {level: self.groups.count(level) for level in self.levels}


def read_table(path) -> tuple[list, list]:
    """The header and rows (dicts) of a subjects table; InputError naming the file and the
    problem when it is not a CSV table with a ``case`` column."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such table")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (UnicodeDecodeError, OSError) as error:
        raise InputError(f"{path}: not a CSV text table ({error.__class__.__name__})") from None
    if "\x00" in text:
        raise InputError(f"{path}: not a CSV text table (binary data)")
    try:
        reader = csv.DictReader(text.splitlines())
        header = [name.strip() for name in (reader.fieldnames or [])]
        rows = [{(k or "").strip(): (v or "").strip() if isinstance(v, str) else ""
                 for k, v in row.items()} for row in reader]
    except csv.Error as error:
        raise InputError(f"{path}: not a CSV table ({error})") from None
    if CASE not in header:
        raise InputError(f"{path}: no '{CASE}' column (columns: {', '.join(header) or 'none'})")
    if len(header) < 2:
        raise InputError(f"{path}: no variable columns besides '{CASE}'")
    names = [row[CASE] for row in rows]
    repeated = sorted({n for n in names if n and names.count(n) > 1})
    if repeated:
        raise InputError(f"{path}: case {repeated[0]!r} has more than one row")
    return header, rows


def _number(text: str) -> float | None:
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def is_missing(text: str) -> bool:
    """Whether a cell is a missing-value marker (:data:`MISSING_MARKERS`), in any letter case.

    Examples
    --------
    >>> [is_missing(text) for text in ("", "NA", "NaN", " ? ", "none", "0")]
    [True, True, True, True, False, False]
    """
    return text.strip().lower() in MISSING_MARKERS


def _why_missing(column: str, text: str, numeric: bool) -> str | None:
    """Why a cell gives no value (None when it gives one)."""
    if text == "":
        return f"no value for {column!r}"
    if is_missing(text):
        return f"{column!r} is missing ({text!r})"
    if numeric and _number(text) is None:
        return f"{column!r} is not a number ({text!r})"
    return None


def _check_numeric(path: Path, rows: list, column: str, role: str):
    """InputError when a numeric column holds as many words as numbers among ``rows`` (words:
    values that are neither numbers nor missing-value markers): it is a categorical column."""
    values = [row[column] for row in rows]
    words = [v for v in values if not is_missing(v) and _number(v) is None]
    numbers = sum(_number(v) is not None for v in values)
    if words and len(words) >= numbers:
        examples = ", ".join(repr(v) for v in list(dict.fromkeys(words))[:3])
        raise InputError(f"{path}: {role} {column!r} is not numeric: {len(words)} of "
                         f"{len(values)} values are not numbers ({examples}); a categorical "
                         f"column goes to --group, or is declared with --categorical {column}")


def coded_factor_note(column: str, values: list) -> str | None:
    """A note when a numeric column's values look like codes of categories: between 3 and
    :data:`FEW_CODES` distinct whole numbers, each taken by more than one case (None otherwise).

    Examples
    --------
    >>> coded_factor_note("site", [1, 2, 3, 1, 2, 3])[:46]
    "numeric column 'site' takes only the values 1,"
    >>> coded_factor_note("age", [41, 45, 47, 52, 60, 61]) is None
    True
    """
    distinct = sorted(set(values))
    if not 3 <= len(distinct) <= FEW_CODES or any(v != round(v) for v in distinct):
        return None
    if len(values) < 2 * len(distinct):
        return None
    codes = ", ".join(f"{v:g}" for v in distinct)
    return (f"numeric column {column!r} takes only the values {codes}: it is used as a number "
            f"(one slope); if it codes categories (sites, scanners), declare it with "
            f"--categorical {column}")


def _level_order(text: str) -> tuple:
    """Levels in numeric order when they are numbers (2 before 10), else in text order."""
    number = _number(text)
    return (0, number, text) if number is not None else (1, 0.0, text)


def _indicators(values: list, levels: list) -> np.ndarray:
    return np.array([[v == level for level in levels[1:]] for v in values],
                    dtype=np.float64).reshape(len(values), len(levels) - 1)


def subjects(table, case_names: list, group: str | None = None, covariates=(),
             nuisance=(), reference: str | None = None, categorical=(), test=()) -> Subjects:
    """Match a subjects table to a build's cases and make the design of one analysis.

    Parameters
    ----------
    table : path
        The CSV table (see the module docstring).
    case_names : list of str
        The build's cases, in model order.
    group : str, optional
        A categorical column: the groups compared.
    covariates : sequence of str
        Columns tested without ``group`` (beside it, adjusted for unless named in ``test``):
        numeric unless named in ``categorical``.
    nuisance : sequence of str
        Columns adjusted for, never tested: numeric unless named in ``categorical``.
    reference : str, optional
        The group level the others are compared with (default: the first in sorted order).
    categorical : sequence of str
        Covariate or nuisance columns that are categorical, such as a site coded 1, 2, 3: coded
        as indicators of their levels other than the first (in numeric order when the levels
        are numbers), named ``column=level``; a tested one is one test over its levels.
    test : sequence of str
        The columns tested, each the group or a covariate (default: the group, else the
        covariates); every other column is adjusted for.

    Returns
    -------
    Subjects

    Raises
    ------
    InputError
        One line naming the file and the problem: no ``case`` column, an unknown column, a
        group with one level or fewer than 3 cases, a numeric column of words, no case matched
        or none with every value.
    ConfigError
        Roles that contradict each other (:func:`~mdlshapemodel.config.analysis_roles`).

    Examples
    --------
    ::

        design = subjects("subjects.csv", names, group="diagnosis", covariates=["age"],
                          test=["age"])
        design.tested, design.adjusted_for        # ['age'], ['diagnosis']
    """
    path = Path(table)
    roles = analysis_roles(group, covariates, nuisance, categorical, test)
    header, rows = read_table(path)
    used_columns = roles.tested + roles.adjusted_for
    for column in used_columns:
        if column not in header:
            raise InputError(f"{path}: no column {column!r} (columns: {', '.join(header)})")
        if column == CASE:
            raise InputError(f"{path}: '{CASE}' names the cases; it is not a variable")
    by_case = {row[CASE]: row for row in rows}
    matched = [by_case[name] for name in case_names if name in by_case]
    known = set(case_names)
    unmatched = [row[CASE] for row in rows if row[CASE] not in known]
    if not matched:
        raise InputError(f"{path}: no row matches a case of the build (cases like "
                         f"{case_names[0]!r}; table rows like {rows[0][CASE] if rows else None!r})")
    for column in roles.numeric:
        _check_numeric(path, matched, column, "covariate" if column in covariates else
                       "nuisance column")
    numeric = set(roles.numeric)
    left_out, chosen, indices = [], [], []
    for index, name in enumerate(case_names):
        row = by_case.get(name)
        if row is None:
            left_out.append(LeftOut(name, "not in the table"))
            continue
        reasons = {c: _why_missing(c, row[c], c in numeric) for c in used_columns}
        missing = {c: row[c] for c in used_columns if reasons[c]}
        if missing:
            left_out.append(LeftOut(name, "; ".join(reasons[c] for c in missing), missing))
            continue
        chosen.append(row)
        indices.append(index)
    if not chosen:
        counts = ", ".join(f"{c}: {sum(c in o.missing for o in left_out)}" for c in used_columns)
        raise InputError(f"{path}: no case of the build has a value in every column used "
                         f"(cases without one: {counts})")
    groups, levels = None, []
    if group:
        groups = [row[group] for row in chosen]
        levels = sorted(set(groups))
        if reference is not None:
            if reference not in levels:
                raise InputError(f"{path}: no case of group {group}={reference!r} (levels: "
                                 f"{', '.join(levels)})")
            levels = [reference] + [level for level in levels if level != reference]
        if len(levels) < 2:
            raise InputError(f"{path}: group column {group!r} has one level ({levels[0]!r}) "
                             "among the cases; a group test needs two or more")
        sizes = {level: groups.count(level) for level in levels}
        small = [level for level in levels if sizes[level] < MIN_GROUP]
        if small:
            raise InputError(f"{path}: group {group}={small[0]!r} has {sizes[small[0]]} "
                             f"case(s); each group needs at least {MIN_GROUP}")

    levels_of = {column: levels if column == group else
                 sorted(set(row[column] for row in chosen), key=_level_order)
                 for column in roles.categorical}
    notes = [note for column in roles.numeric
             if (note := coded_factor_note(column, [_number(row[column]) for row in chosen]))]

    def block(column: str) -> tuple[np.ndarray, list]:
        """The design columns of one table column and their names."""
        values = [row[column] for row in chosen]
        if column in numeric:
            numbers = np.array([_number(v) for v in values])
            return (numbers - numbers.mean())[:, None], [column]
        kinds = levels_of[column]
        named = [k if column == group and len(roles.tested) == 1 else f"{column}={k}"
                 for k in kinds[1:]]
        return _indicators(values, kinds), named

    def design(columns: list) -> tuple[np.ndarray, list, list]:
        blocks = [block(column) for column in columns]
        matrix = (np.hstack([b for b, _ in blocks]) if blocks
                  else np.zeros((len(chosen), 0)))
        names = [name for _, block_names in blocks for name in block_names]
        sources = [c for c, (_, block_names) in zip(columns, blocks) for _ in block_names]
        return matrix, names, sources

    interest, names, sources = design(roles.tested)
    nuisance_columns, _, _ = design(roles.adjusted_for)
    return Subjects(cases=[case_names[i] for i in indices], indices=np.array(indices),
                    interest=interest, nuisance=nuisance_columns, interest_names=names,
                    interest_columns=sources, tested=roles.tested,
                    adjusted_for=roles.adjusted_for, group=group, groups=groups, levels=levels,
                    left_out=left_out, unmatched=unmatched, levels_of=levels_of, notes=notes)
