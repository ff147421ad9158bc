"""Inputs -> cases of one or several parts: which file and which labels make each part of each case.

A case is a training example; an object may have several parts (III-E), each a closed surface of
its own. Parts come two ways:

- one label map per case, several parts: ``BuildConfig.parts`` (``--part head=1 --part tail=2``),
  each part the union of its labels in the same file;
- one file per part: a manifest (:func:`read_manifest`), a CSV table with the columns ``case``,
  ``part`` and ``file``.

Each part is prepared on its own (:func:`~.case.prepare_case` with the part's labels: the cache
keeps parts apart); :func:`joined` makes the multi-part case, or its rejection naming the part.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..config import BuildConfig, PartSpec, parse_part
from ..errors import ConfigError, InputError
from . import io
from .case import PreparedCase, PreparedPart, Rejection, prepare_case

#: the columns a manifest must have (others are ignored)
MANIFEST_COLUMNS = ("case", "part", "file")


@dataclass(frozen=True)
class PartInput:
    """Where one part of one case comes from."""

    part: str            # the part's name ("" for a one-part object)
    path: str            # the file
    labels: tuple = ()   # the labels whose union is the part (empty: the build's labels)


@dataclass(frozen=True)
class CaseInput:
    """One case to prepare: its name and its parts' inputs, in the object's part order; or,
    when ``problem`` is set, a case that is rejected before anything is read (e.g. a manifest
    that lacks one of its parts)."""

    name: str
    parts: tuple         # of PartInput
    problem: str = ""

    @property
    def path(self) -> str:
        return self.parts[0].path if self.parts else ""


def part_config(config: BuildConfig, part: PartInput) -> BuildConfig:
    """The settings that prepare one part: the build's, with the part's labels."""
    return replace(config, labels=list(part.labels)) if part.labels else config


def case_inputs(paths, config: BuildConfig) -> list[CaseInput]:
    """The cases of input files (each file one case): one part per file, or with
    ``config.parts`` one part per :class:`~.config.PartSpec`, each from the same label map.

    Raises :class:`ConfigError` when parts by labels are asked of a mesh (it has no labels).
    """
    specs = config.part_specs()
    cases = []
    for path in map(str, paths):
        if specs and not io.is_image(path):
            cases.append(CaseInput(io.case_name(path), (PartInput("", path),),
                                   "a mesh has no labels to split into parts: give each part "
                                   "its own file in a --manifest"))
        elif specs:
            cases.append(CaseInput(io.case_name(path), tuple(
                PartInput(spec.name, path, spec.labels) for spec in specs)))
        else:
            cases.append(CaseInput(io.case_name(path), (PartInput("", path),)))
    return cases


def read_manifest(path, config: BuildConfig) -> list[CaseInput]:
    """The cases of a manifest: a CSV table with a header and the columns ``case``, ``part`` and
    ``file`` (one row per part of a case; a file path absolute or relative to the manifest's
    folder). The parts are those of ``config.parts`` when given (their labels select within
    label maps), else every part named in the manifest, in the order of first appearance. A
    manifest whose rows all name one part (or none) is of a one-part object.

    A case that lacks a part, or has two files for one, is a :class:`CaseInput` with its
    ``problem`` (rejected, the other cases go on). Raises :class:`InputError` when the file is not
    such a table, and :class:`ConfigError` when it names parts that ``config.parts`` lacks.

    Examples
    --------
    A manifest ``cases.csv``::

        case,part,file
        s01,head,s01_head.nii.gz
        s01,tail,s01_tail.nii.gz
    """
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            rows = list(csv.DictReader(handle))
            header = [name.strip().lower() for name in (rows[0].keys() if rows else [])]
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a CSV text file") from None
    missing = [c for c in MANIFEST_COLUMNS if c not in header] if rows else []
    if not rows or missing:
        raise InputError(f"{path}: a manifest needs a header and rows with the columns "
                         f"{', '.join(MANIFEST_COLUMNS)}" + (f" (missing: {', '.join(missing)})"
                                                             if missing else " (no rows)"))
    table = []
    for number, row in enumerate(rows, start=2):
        row = {str(k).strip().lower(): (v or "").strip() for k, v in row.items() if k}
        if not row["case"] or not row["file"]:
            raise InputError(f"{path}, line {number}: a row needs a case and a file")
        if row["part"]:
            parse_part(row["part"])   # a name only: checked as --part's names are
        file = Path(row["file"])
        table.append((row["case"], row["part"], str(file if file.is_absolute()
                                                    else path.parent / file)))
    specs = config.part_specs()
    named = list(dict.fromkeys(part for _, part, _ in table))
    if specs:
        unknown = [part for part in named if part not in {s.name for s in specs}]
        if unknown:
            raise ConfigError(f"{path}: part {unknown[0]!r} is not among the --part parts "
                              f"({', '.join(s.name for s in specs)})")
    else:
        specs = [PartSpec(name) for name in named]
    one_part = len(specs) == 1
    cases = {}
    for case, part, file in table:
        cases.setdefault(case, []).append((part, file))
    result = []
    for case, rows in cases.items():
        files = {}
        problem = ""
        for part, file in rows:
            if part in files:
                problem = f"two files for part {part!r} in {path.name}"
            files[part] = file
        absent = [spec.name for spec in specs if spec.name not in files]
        if absent and not problem:
            problem = f"no file for part {absent[0]!r} in {path.name}"
        parts = tuple(PartInput("" if one_part else spec.name, files[spec.name], spec.labels)
                      for spec in specs if spec.name in files)
        result.append(CaseInput(case, parts, problem))
    return result


def joined(case: CaseInput, results: list):
    """The prepared case of ``case`` from one result of :func:`~.case.prepare_case` per part
    (in its order): a :class:`PreparedCase` with every part, or a :class:`Rejection` that names
    the first part that failed."""
    for part, result in zip(case.parts, results):
        if isinstance(result, Rejection):
            reason = f"part {part.part}: {result.reason}" if part.part else result.reason
            return Rejection(case.name, part.path, reason)
    if len(results) == 1:
        return replace(results[0], name=case.name)
    kinds = [result.is_curve for result in results]
    if len(set(kinds)) > 1:
        curve_part = case.parts[kinds.index(True)]
        surface_part = case.parts[kinds.index(False)]
        return Rejection(case.name, curve_part.path,
                         f"part {curve_part.part} is a 2-D curve and part {surface_part.part} a "
                         "surface: the parts of an object are of one kind")
    parts = [PreparedPart(part.part, result.path, result.map, result.repair,
                          result.smoothing_sigma, result.labels)
             for part, result in zip(case.parts, results)]
    return PreparedCase(case.name, parts, float(np.mean([r.voxel_size for r in results])),
                        any(r.mirrored for r in results))


def prepare_object(case: CaseInput, config: BuildConfig):
    """Prepare every part of one case here, one after the other (no cache): a
    :class:`PreparedCase` or the :class:`Rejection` of :func:`joined`. What ``fit`` uses for a
    new case; a build prepares the parts on its executor (:func:`~.batch.preprocess`)."""
    if case.problem:
        return Rejection(case.name, case.path, case.problem)
    return joined(case, [prepare_case(part.path, part_config(config, part))
                         for part in case.parts])
