"""Optimisations run with a checkpoint at every step and resumed from one of them (shared by the
resumption tests of surfaces, test_resume.py, and of 2-D curves, test_circle.py)."""

from __future__ import annotations

import copy

import numpy as np

from mdlshapemodel.correspondence.state import state_record
from mdlshapemodel.correspondence.strategies import optimise
from mdlshapemodel.correspondence.strategies.base import Resumption
from mdlshapemodel.correspondence.trace import Trace

from synthetic import build_objectives


def assert_same_record(a: dict, b: dict):
    """Two state records (:func:`state_record`) alike bit for bit."""
    assert a.keys() == b.keys()
    for key in a:
        assert np.array_equal(a[key], b[key]), key


def optimised_with_checkpoints(state, settings, seed: int = 7):
    """``optimise`` with a checkpoint keeping, at every step, (point, state record, evaluations,
    generator state, trace rows): the final F, the trace and those checkpoints."""
    rng, trace, saved = np.random.default_rng(seed), Trace(), []

    def checkpoint(point, current):
        saved.append((point, copy.deepcopy(state_record(current)), current.evaluations,
                      copy.deepcopy(rng.bit_generator.state), list(trace.rows)))

    final = optimise(state, build_objectives(state), settings, rng, trace, checkpoint=checkpoint)
    return final, trace, saved


def resumed_from(state, settings, saved):
    """``optimise`` of a fresh ``state`` resumed from one of :func:`optimised_with_checkpoints`'
    checkpoints: the final F and the trace."""
    point, record, evaluations, generator, rows = saved
    rng = np.random.default_rng(0)
    rng.bit_generator.state = generator
    trace = Trace(rows=list(rows))
    given = dict(record)        # optimise empties the record it resumes from
    value = optimise(state, build_objectives(state), settings, rng, trace,
                     resume=Resumption(point, given, evaluations, 0.0))
    assert given == {}
    return value, trace
