"""What many test files share: where the shared real data is (../shared/data beside the
checkout, or the folder named by MDLSHAPEMODEL_DATA; tests that need it skip with a reason when
it is absent), running the command line or a script in a subprocess, always with a timeout,
central differences for gradient checks, and the unusual-case p-values written out from their
formulas."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

DATA = Path(os.environ.get("MDLSHAPEMODEL_DATA",
                           Path(__file__).resolve().parents[1].parent / "shared" / "data"))
HIPPOCAMPI = DATA / "hippocampus" / "labels"
HANDS = sorted((DATA / "hands2d").glob("hand-*.vtk"))

needs_hippocampi = pytest.mark.skipif(not HIPPOCAMPI.is_dir(),
                                      reason=f"shared hippocampus data not found at {HIPPOCAMPI}")


def hippocampi(count: int) -> list:
    """The first ``count`` shared hippocampus label maps, in sorted order, leaving out
    hippocampus_011 (hippocampus_010 again, byte for byte, which a build refuses)."""
    return [path for path in sorted(HIPPOCAMPI.glob("*.nii.gz"))
            if path.name != "hippocampus_011.nii.gz"][:count]


TIMEOUT = 900   # seconds for one subprocess: a hang fails the test instead of stalling the run


def run_cli(*arguments, timeout: float = TIMEOUT, **kwargs) -> subprocess.CompletedProcess:
    """``mdlshapemodel ARGUMENTS`` in a subprocess (text output captured; not checked)."""
    return subprocess.run([sys.executable, "-m", "mdlshapemodel.cli", *map(str, arguments)],
                          capture_output=True, text=True, timeout=timeout, **kwargs)


def run_cli_quietly(*arguments, **kwargs) -> subprocess.CompletedProcess:
    """:func:`run_cli` with Python's warnings off in the subprocess (``PYTHONWARNINGS=ignore``):
    its stderr holds only what the command line itself says."""
    environment = dict(kwargs.pop("env", None) or os.environ, PYTHONWARNINGS="ignore")
    return run_cli(*arguments, env=environment, **kwargs)


def run_python(code: str, *arguments, cwd=None, env=None, timeout: float = TIMEOUT
               ) -> subprocess.CompletedProcess:
    """``code`` run as a script in a fresh interpreter (text output captured; not checked): a
    crash in native code ends that process, not the test run."""
    return subprocess.run([sys.executable, "-c", code, *map(str, arguments)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


def central_difference(function, x, k: int, relative_step: float = 1e-4) -> float:
    """(f(x + h e_k) - f(x - h e_k)) / 2h with h = ``relative_step`` max(|x_k|, 1e-3)."""
    step = relative_step * max(abs(x[k]), 1e-3)
    plus, minus = x.copy(), x.copy()
    plus[k] += step
    minus[k] -= step
    return (function(plus) - function(minus)) / (2 * step)


def empirical_null_p(p_normal, training_p_normal=None):
    """p-values against the empirical null, from the formulas of docs/analysis.md item 9: the
    normal-theory p-values as z-values, each case's null from the *other* training cases' z
    (``training_p_normal`` None: ``p_normal`` are the training cases'), else all of
    ``training_p_normal``'s (new cases). p is the larger of the body's (a normal centred on the
    N z's median, at least 0, with their upper spread (90 % quantile - median) / z_0.9, at least
    1) and, from N = 15 on, the tail's: with the N z's sorted in decreasing order,
    r = N / 10 rounded half up, u the (r + 1)-th and S the sum of the first r's excesses over
    u, (r + 1) / (N + 1) exp(-r max(z - u, 0) / S)."""
    import numpy as np
    from scipy import stats

    def p_against(z, others):
        centre = max(float(np.median(others)), 0.0)
        spread = max((float(np.quantile(others, 0.9)) - float(np.median(others)))
                     / stats.norm.isf(0.1), 1.0)
        body = stats.norm.sf((z - centre) / spread)
        if len(others) < 15:
            return body
        ranked = sorted(others, reverse=True)
        r = int(np.floor(len(ranked) / 10 + 0.5))
        u, excess = ranked[r], sum(value - ranked[r] for value in ranked[:r])
        tail = (r + 1) / (len(ranked) + 1) * np.exp(-r * np.maximum(z - u, 0) / excess)
        return np.maximum(body, tail)

    z = stats.norm.isf(np.atleast_1d(np.asarray(p_normal, dtype=float)))
    if training_p_normal is None:
        return np.array([p_against(z[i], np.delete(z, i)) for i in range(len(z))])
    return p_against(z, stats.norm.isf(np.asarray(training_p_normal, dtype=float)))
