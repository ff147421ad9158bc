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
class Repeated:
    """Repeated measures: which cases are one subject's, at which time.

    Attributes
    ----------
    subject : str
        The table's column naming each case's subject.
    time : str or None
        The one naming its time point (None: a subject's cases are alike, "blocks").
    times : list of str
        The time levels, the baseline first (empty without a time).
    design : str
        "change" (two times: one row per subject, its later case minus its baseline case),
        "within" (more times: one row per case, time tested within subjects) or "blocks" (no
        time: one row per case, the subjects' columns tested, whole subjects permuted).
    subjects : list of str
        The subjects, in the order of the design's rows ("change") or of the blocks
        ("within").
    pairs : ndarray (n_subjects, 2) or None
        "change": each subject's rows in :attr:`Subjects.cases` at the baseline and the later
        time.
    blocks : ndarray (n,) or None
        "within" and "blocks": each case's subject (an index into ``subjects``), its
        exchangeability block.
    """

    subject: str
    time: str | None
    times: list
    design: str
    subjects: list
    pairs: np.ndarray | None
    blocks: np.ndarray | None


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
    repeated : Repeated or None
        Repeated measures (``subject`` and ``time``). With two times ("change") the design's
        rows (``interest``, ``nuisance``, ``groups``) are the subjects, not the cases.
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
    repeated: Repeated | None = None

    @property
    def mean_change_tested(self) -> bool:
        """Whether the test is of the mean change (two times, nothing else tested): the
        one-sample test, no intercept in the nuisance, resampled by sign flips."""
        return (self.repeated is not None and self.repeated.design == "change"
                and self.tested == [self.repeated.time])

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
             nuisance=(), reference: str | None = None, categorical=(), test=(),
             subject: str | None = None, time: str | None = None,
             baseline: str | None = None, interactions=()) -> Subjects:
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
    subject, time : str, optional
        Repeated measures: the columns naming each case's subject and its time point. Without
        a time, every case is a row and the tested columns must be each subject's own (its
        cases agree): whole subjects are permuted (exchangeability blocks). With two
        times, each subject's change (the later case minus the baseline's) is analysed, one row
        per subject: the mean change is tested when no other column is, else the tested
        columns' effect on the change (the subject's values at the baseline; a categorical
        column must agree between the times). A subject without a case at both times is left
        out. With more times, the effect of time within subjects: the time (numeric unless
        named in ``categorical``) tested, each subject adjusted for, every case its subject's
        exchangeability block.
    baseline : str, optional
        The time the change is measured from (default: the first in numeric or sorted order).
    interactions : sequence of str
        Products "a:b" of two columns of the model, tested (each product of their design
        columns, centred, named ``a_name:b_name``) with their columns adjusted for: does the
        effect of one depend on the other?

    Returns
    -------
    Subjects

    Raises
    ------
    InputError
        One line naming the file and the problem: no ``case`` column, an unknown column, a
        group with one level or fewer than 3 cases, a numeric column of words, no case matched
        or none with every value; a subject with two cases at one time, a categorical column
        that changes within a subject, no subject with both times.
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
    roles = analysis_roles(group, covariates, nuisance, categorical, test, subject, time,
                           interactions)
    header, rows = read_table(path)
    used_columns = [c for c in roles.tested if c not in roles.interactions] + roles.adjusted_for
    used_columns += [c for c in (subject, time) if c and c not in used_columns]
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
    repeated, design_rows = None, chosen
    if subject is not None:
        repeated, kept, design_rows, incomplete = _repeated(path, chosen, roles, subject, time,
                                                            baseline)
        left_out += incomplete
        chosen, indices = [chosen[k] for k in kept], [indices[k] for k in kept]
        if repeated.design == "within":
            design_rows = chosen
            if time in categorical:
                roles.categorical.append(time)
            else:
                _check_numeric(path, chosen, time, "time column")
                numeric.add(time)
                roles.numeric.append(time)
    groups, levels = None, []
    if group:
        groups = [row[group] for row in design_rows]
        levels = _levels(path, group, groups, reference, sorted, "group",
                         "a group test needs two or more")
        sizes = {level: groups.count(level) for level in levels}
        small = [level for level in levels if sizes[level] < MIN_GROUP]
        if small:
            raise InputError(f"{path}: group {group}={small[0]!r} has {sizes[small[0]]} "
                             f"case(s); each group needs at least {MIN_GROUP}")

    levels_of = {column: levels if column == group else
                 repeated.times if column == time else
                 sorted(set(row[column] for row in design_rows), key=_level_order)
                 for column in roles.categorical}
    notes = [note for column in roles.numeric if column != time
             if (note := coded_factor_note(column, [_number(row[column]) for row in design_rows]))]

    def block(column: str) -> tuple[np.ndarray, list]:
        """The design columns of one table column (or interaction) and their names."""
        if column in roles.interactions:
            # every product of the two columns' design columns, each centred
            (left, left_names), (right, right_names) = (block(c) for c in column.split(":"))
            products = np.einsum("ni,nj->nij", left, right).reshape(len(design_rows), -1)
            return (products - products.mean(axis=0),
                    [f"{a}:{b}" for a in left_names for b in right_names])
        values = [row[column] for row in design_rows]
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
                  else np.zeros((len(design_rows), 0)))
        names = [name for _, block_names in blocks for name in block_names]
        sources = [c for c, (_, block_names) in zip(columns, blocks) for _ in block_names]
        return matrix, names, sources

    nuisance_columns, _, _ = design(roles.adjusted_for)
    if repeated is not None and repeated.design == "change" and roles.tested == [time]:
        # the mean change is tested: no intercept, every nuisance column centred so that the
        # mean change is the change at the nuisance's mean
        interest, names, sources = np.ones((len(design_rows), 1)), ["change"], [time]
        nuisance_columns = nuisance_columns - nuisance_columns.mean(axis=0)
    else:
        interest, names, sources = design(roles.tested)
    if repeated is not None and repeated.design == "within":
        constant = [c for c in roles.adjusted_for
                    if all(len({chosen[k][c] for k in np.flatnonzero(repeated.blocks == b)}) == 1
                           for b in range(len(repeated.subjects)))]
        if constant:
            raise InputError(f"{path}: {constant[0]!r} is the same at every time of each "
                             f"subject: the effect of {time} within subjects is adjusted for "
                             "each subject already (leave it out)")
        own = _indicators(list(repeated.blocks), list(range(len(repeated.subjects))))
        nuisance_columns = np.hstack([own, nuisance_columns])
    return Subjects(cases=[case_names[i] for i in indices], indices=np.array(indices),
                    interest=interest, nuisance=nuisance_columns, interest_names=names,
                    interest_columns=sources, tested=roles.tested,
                    adjusted_for=roles.adjusted_for, group=group, groups=groups, levels=levels,
                    left_out=left_out, unmatched=unmatched, levels_of=levels_of, notes=notes,
                    repeated=repeated)


def contrast_vector(design: Subjects, text: str, coefficients: dict) -> tuple[str, np.ndarray]:
    """A contrast of levels (:func:`~mdlshapemodel.config.parse_contrast`) as a vector over the
    effect columns: the tested categorical column whose levels it names, and c (r,) such that
    c'b is the contrast of the level means (b the effect columns' coefficients, the reference
    level's being 0).

    Raises
    ------
    InputError
        The levels are not all of one tested categorical column (naming the contrast and the
        levels there are).

    Examples
    --------
    ::

        column, c = contrast_vector(design, "mild-severe", {"mild": 1.0, "severe": -1.0})
    """
    for column in dict.fromkeys(design.interest_columns):
        levels = design.levels_of.get(column)
        if levels and set(coefficients) <= set(levels):
            c = np.zeros(len(design.interest_columns))
            at = [k for k, source in enumerate(design.interest_columns) if source == column]
            for level, value in coefficients.items():
                if level != levels[0]:
                    c[at[levels.index(level) - 1]] = value
            return column, c
    known = "; ".join(f"{column}: {', '.join(design.levels_of[column])}"
                      for column in dict.fromkeys(design.interest_columns)
                      if column in design.levels_of) or "none (no categorical column is tested)"
    raise InputError(f"contrast {text!r}: its levels are not all levels of one tested "
                     f"categorical column (levels: {known})")


def _whole_subjects(path: Path, chosen: list, roles, subject: str) -> tuple:
    """Cases blocked by subject, the tested columns the subjects' own (constant within each)."""
    order = list(dict.fromkeys(row[subject] for row in chosen))
    blocks = np.array([order.index(row[subject]) for row in chosen])
    for column in roles.tested:
        for b, name in enumerate(order):
            values = {chosen[k][column] for k in np.flatnonzero(blocks == b)}
            if len(values) > 1:
                raise InputError(f"{path}: {column!r} varies within subject {name!r} ("
                                 f"{', '.join(sorted(values))}): with --subject and no --time "
                                 "the tested columns are the subjects' (whole subjects are "
                                 "permuted); give --time to test a change within subjects")
    kept = list(range(len(chosen)))
    return Repeated(subject, None, [], "blocks", order, None, blocks), kept, chosen, []


def _levels(path: Path, column: str, values: list, first: str | None, order, what: str,
            need: str) -> list:
    """The levels of a column among the cases, in ``order``, ``first`` (when given) first;
    InputError naming the file when ``first`` is not one of them or there is only one."""
    levels = order(set(values))
    if first is not None:
        if first not in levels:
            raise InputError(f"{path}: no case of {what} {column}={first!r} (levels: "
                             f"{', '.join(levels)})")
        levels = [first] + [level for level in levels if level != first]
    if len(levels) < 2:
        raise InputError(f"{path}: {what} column {column!r} has one level ({levels[0]!r}) "
                         f"among the cases; {need}")
    return levels


def _repeated(path: Path, chosen: list, roles, subject: str, time: str | None,
              baseline: str | None) -> tuple:
    """The repeated-measures design of the chosen rows: (Repeated, the rows kept, the design's
    rows, the cases left out). Two times: each subject's pair of cases, the subject's row at the
    baseline its design row; more: every case, blocked by subject; no time: every case, whole
    subjects exchanged."""
    if time is None:
        return _whole_subjects(path, chosen, roles, subject)
    times = _levels(path, time, [row[time] for row in chosen], baseline,
                    lambda values: sorted(values, key=_level_order), "time",
                    "repeated measures need two or more")
    members = {}
    for k, row in enumerate(chosen):
        members.setdefault(row[subject], []).append(k)
    for name, ks in members.items():
        seen = {}
        for k in ks:
            if chosen[k][time] in seen:
                raise InputError(f"{path}: subject {name!r} has two cases at {time}="
                                 f"{chosen[k][time]!r} ({chosen[seen[chosen[k][time]]][CASE]}, "
                                 f"{chosen[k][CASE]})")
            seen[chosen[k][time]] = k
    order = list(members)
    if len(times) > 2:
        if roles.tested != [time]:
            raise InputError(f"{path}: time column {time!r} has {len(times)} levels: with more "
                             f"than two times the effect of {time} within subjects is tested "
                             f"(not {', '.join(roles.tested)}); a tested column's effect on the "
                             "change needs two times")
        kept = list(range(len(chosen)))
        blocks = np.array([order.index(row[subject]) for row in chosen])
        return (Repeated(subject, time, times, "within", order, None, blocks), kept, chosen,
                [])
    first, second = times
    pairs, incomplete = [], []
    for name in order:
        at = {chosen[k][time]: k for k in members[name]}
        if len(at) < 2:
            missing = second if first in at else first
            incomplete += [LeftOut(chosen[k][CASE], f"subject {name!r} has no case at {time}="
                                   f"{missing!r}") for k in members[name]]
            continue
        for column in roles.categorical:
            values = chosen[at[first]][column], chosen[at[second]][column]
            if values[0] != values[1]:
                raise InputError(f"{path}: {column!r} differs between the times of subject "
                                 f"{name!r} ({values[0]!r} at {first}, {values[1]!r} at "
                                 f"{second}); a categorical column of the change must be the "
                                 "subject's")
        pairs.append((at[first], at[second]))
    if not pairs:
        raise InputError(f"{path}: no subject has a case at both times ({first}, {second})")
    kept = sorted(k for pair in pairs for k in pair)
    position = {k: j for j, k in enumerate(kept)}
    rows_of_pairs = np.array([[position[a], position[b]] for a, b in pairs])
    names = [chosen[a][subject] for a, _ in pairs]
    return (Repeated(subject, time, times, "change", names, rows_of_pairs, None), kept,
            [chosen[a] for a, _ in pairs], incomplete)
