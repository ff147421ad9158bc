"""The table of subjects: which cases have which group and covariate values.

A CSV file with a ``case`` column whose values are the build's case names; every other column is
a variable (a categorical group, or numeric covariates). Cases missing from the table, or with an
empty value in a column the analysis uses, are left out and listed with the reason; rows that
match no case are listed. Categorical nuisance variables are coded as indicators.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError

CASE = "case"
# the smallest group that is tested: fewer cases than this cannot estimate a group's spread
MIN_GROUP = 3


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
        A name per interest column: the group level it indicates, or the covariate.
    groups : list of str or None
        Each used case's group (None without ``--group``).
    levels : list of str
        The group levels, reference first (empty without ``--group``).
    left_out : list of (case, reason)
        Build cases that are not used, and why.
    unmatched : list of str
        Table rows whose case is not one of the build's.
    """

    cases: list
    indices: np.ndarray
    interest: np.ndarray
    nuisance: np.ndarray
    interest_names: list
    groups: list | None
    levels: list
    left_out: list = field(default_factory=list)
    unmatched: list = field(default_factory=list)


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


def _numeric(path, rows: list, column: str, role: str) -> np.ndarray:
    values = [_number(row[column]) for row in rows]
    bad = [row[column] for row, v in zip(rows, values) if v is None]
    if bad:
        raise InputError(f"{path}: {role} '{column}' is not numeric (value {bad[0]!r}); a "
                         "categorical variable goes to --group or --nuisance")
    return np.array(values, dtype=np.float64)


def _indicators(values: list, levels: list) -> np.ndarray:
    return np.array([[v == level for level in levels[1:]] for v in values],
                    dtype=np.float64).reshape(len(values), len(levels) - 1)


def subjects(table, case_names: list, group: str | None = None, covariates=(),
             nuisance=(), reference: str | None = None) -> Subjects:
    """Match a subjects table to a build's cases and make the design of one analysis.

    Parameters
    ----------
    table : path
        The CSV table (see the module docstring).
    case_names : list of str
        The build's cases, in model order.
    group : str, optional
        A categorical column: the effect of interest is the difference between its levels
        (the covariates then join the nuisance).
    covariates : sequence of str
        Numeric columns: without ``group``, the effect of interest (their slopes); with it,
        adjusted for.
    nuisance : sequence of str
        Columns adjusted for (numeric, or categorical as indicators).
    reference : str, optional
        The group level the others are compared with (default: the first in sorted order).

    Returns
    -------
    Subjects

    Raises
    ------
    InputError
        One line naming the file and the problem: no ``case`` column, an unknown column, a
        group with one level or fewer than 3 cases, a non-numeric covariate, no case matched.
    """
    path = Path(table)
    header, rows = read_table(path)
    covariates, nuisance = list(covariates), list(nuisance)
    if group is None and not covariates:
        raise InputError("nothing to test: give a group column or a covariate")
    used_columns = ([group] if group else []) + covariates + nuisance
    for column in used_columns:
        if column not in header:
            raise InputError(f"{path}: no column {column!r} (columns: {', '.join(header)})")
        if column == CASE:
            raise InputError(f"{path}: '{CASE}' names the cases; it is not a variable")
    repeated = sorted({c for c in used_columns if used_columns.count(c) > 1})
    if repeated:
        raise InputError(f"column {repeated[0]!r} is given twice")
    by_case = {row[CASE]: row for row in rows}
    left_out, chosen, indices = [], [], []
    for index, name in enumerate(case_names):
        row = by_case.get(name)
        if row is None:
            left_out.append((name, "not in the table"))
            continue
        empty = [c for c in used_columns if row[c] == ""]
        if empty:
            left_out.append((name, f"no value for {empty[0]!r}"))
            continue
        chosen.append(row)
        indices.append(index)
    known = set(case_names)
    unmatched = [row[CASE] for row in rows if row[CASE] not in known]
    if not chosen:
        raise InputError(f"{path}: no row matches a case of the build (cases like "
                         f"{case_names[0]!r}; table rows like {rows[0][CASE] if rows else None!r})")
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
        interest = _indicators(groups, levels)
        names = levels[1:]
        adjust = covariates + nuisance
    else:
        interest = np.column_stack([_numeric(path, chosen, c, "covariate") for c in covariates])
        interest = interest - interest.mean(axis=0)
        names = covariates
        adjust = nuisance
    blocks = []
    for column in adjust:
        values = [row[column] for row in chosen]
        numbers = [_number(v) for v in values]
        if all(v is not None for v in numbers):
            numeric = np.array(numbers)
            blocks.append((numeric - numeric.mean())[:, None])
        else:
            blocks.append(_indicators(values, sorted(set(values))))
    nuisance_columns = (np.hstack(blocks) if blocks else np.zeros((len(chosen), 0)))
    return Subjects(cases=[case_names[i] for i in indices], indices=np.array(indices),
                    interest=interest, nuisance=nuisance_columns, interest_names=list(names),
                    groups=groups, levels=levels, left_out=left_out, unmatched=unmatched)
