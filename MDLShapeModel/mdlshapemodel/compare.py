"""``mdlshapemodel compare``: build folders -> the comparison's folder (compare.json, compare.csv,
compare.html), whole or absent.

The command's orchestration: each build's training shapes read through
:class:`~.folders.BuildFolder` (:func:`load_population`), compared by
:func:`~.report.compare.compare_populations` and written here; the page is rendered by
:func:`~.report.compare.comparison_page`.
"""

from __future__ import annotations

import json
from pathlib import Path

from .folders import BuildFolder
from .prepare import io
from .report.compare import (ROW_HEADER, Population, compare_populations, comparison_page,
                             comparison_rows)

# what write_comparison writes into its folder
COMPARE_FILES = ("compare.json", "compare.csv", "compare.html")


def load_population(output, label: str | None = None) -> Population:
    """Training shapes of a build's model (its output folder or its model file), in the model
    frame, labelled by the folder and the strategy (metrics.json's, else the model's) unless
    ``label`` is given."""
    folder = BuildFolder(output)
    model = folder.model()
    if label is None:
        strategy = (folder.metrics() or {}).get("strategy", model.metadata.get("strategy", ""))
        label = f"{folder.path.name} ({strategy})" if strategy else folder.path.name
    shapes = model.instance(model.scores)
    return Population(label, list(model.names), shapes, model.weights,
                      str(folder.path.resolve()))


def refuse_earlier_comparison(destination, overwrite: bool = False) -> None:
    """Refuse a folder that holds an earlier comparison unless ``overwrite`` (the rule of every
    command's output folder: :func:`~mdlshapemodel.prepare.io.refuse_earlier`)."""
    io.refuse_earlier(destination, io.earlier_outputs(destination, COMPARE_FILES), overwrite,
                      "comparison")


def write_comparison(result: dict, destination, overwrite: bool = False) -> Path:
    """compare.json, compare.csv and a self-contained compare.html with the plot, written
    whole or not at all into ``destination``
    (:func:`~mdlshapemodel.prepare.io.written_folder`; an earlier comparison there is refused
    unless ``overwrite``)."""
    refuse_earlier_comparison(destination, overwrite)
    destination = Path(destination)
    json_file, csv_file, page_file = COMPARE_FILES
    with io.written_folder(destination, COMPARE_FILES) as folder:
        io.write_text(folder / json_file, json.dumps(result, indent=2))
        io.write_csv(folder / csv_file, ROW_HEADER, comparison_rows(result))
        # the page's links are relative to ``destination``, where it ends up
        io.write_text(folder / page_file, comparison_page(result, destination))
    return destination / page_file


def compare_builds(outputs, destination, max_modes: int = 10, n_samples: int = 10_000,
                   seed: int = 0, overwrite: bool = False) -> tuple[dict, Path]:
    """Compare the models of the build folders ``outputs`` on the cases they share
    (:func:`~.report.compare.compare_populations`; the first is the reference) and write the
    comparison into ``destination`` (an earlier one there is refused, before any work, unless
    ``overwrite``). Returns the result and the page's path. Two builds of the same label (folder
    and strategy) are told apart by their place in ``outputs`` (``#k``)."""
    refuse_earlier_comparison(destination, overwrite)     # before any work
    populations = [load_population(path) for path in outputs]
    labels = [p.label for p in populations]
    for k, population in enumerate(populations):  # labels must be unique keys
        if labels.count(population.label) > 1:
            population.label = f"{population.label} #{k + 1}"
    result = compare_populations(populations, max_modes, n_samples, seed)
    return result, write_comparison(result, destination, overwrite)
