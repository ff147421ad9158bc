"""The fast strategy's per-example work on the workers of a Dask cluster (``--scheduler``).

:class:`ExamplesOnCluster` splits a phase's active examples into one stretch of consecutive rows
per worker. When the phase starts, a :class:`Holder` is made on each worker (a Dask actor: the
build's calls go to it directly, not through the scheduler, which answers each call in tens of
milliseconds on a busy machine where an actor answers in a few) and sent its examples' parts
(surfaces, point locators, sample positions, warps) once, which it keeps for the phase. Each
round it makes its :class:`~.blocks.BlockSet` of them; each evaluation it
receives its stretch of the parameters x (and which earlier trials to keep) and sends back its
examples' unposed samples (rows x n_p x 3); for the gradient it receives their rows of dF/dX with
their poses' scale and rotation, and sends back the gradient of its stretch. A commit is applied
by each worker to its own copies (:meth:`~.blocks.BlockSet.commit`) and, with what it returns, to
the build's. Eq. 14, dF/dX, the poses and the quasi-Newton steps stay in the build's process.

Why the parts are held per phase and not scattered per round: between the rounds of a phase
they change only by the commits, which keep both copies equal; sending them each round would
move every surface (about a megabyte per example) some fifty times per phase for nothing. The
actors go with the build's client: a build that ends, or dies, leaves nothing on the workers.

The arithmetic is :class:`~.blocks.BlockSet`'s, as in the build's own process, one call at a time
per worker with one BLAS thread (:class:`~mdlshapemodel.cluster.InTurn`): the optimisation gives
the same correspondence as without a cluster, bit for bit.

A worker that leaves the cluster (its process killed, its machine gone) while it holds a stretch
is not waited for: the build asks the scheduler which workers it has every
:data:`POLL_SECONDS` while it waits, and takes a lost stretch into its own process (a
:class:`~.blocks.BlockSet` of the build's parts, as they were at the start of the round, with
the round's kept trials sampled again), with a warning in the log. The rest of the phase runs that
stretch here; the next phase spreads over the workers there are then, and a phase that finds no
worker (or no scheduler) runs them all here.
"""

from __future__ import annotations

import logging
from concurrent.futures import CancelledError
from dataclasses import dataclass, field

import numpy as np

from ...cluster import InTurn
from ...errors import ArgumentError
from ...parallel import Threads
from ..state import CorrespondenceState
from .blocks import BlockSet

log = logging.getLogger("mdlshapemodel")

#: how often (seconds) the build asks the scheduler whether the workers it waits for are there
POLL_SECONDS = 1.0

class Holder:
    """On a worker: the examples of one stretch for a phase, and the round's block set of them.

    A Dask actor (made by :class:`ExamplesOnCluster`): its calls go from the build's process
    to the worker directly, not through the scheduler, and it lives as long as the build keeps
    it (a build that ends, or dies, takes it with it). Each call runs as
    :class:`~mdlshapemodel.cluster.InTurn` (one at a time per process, one BLAS thread)."""

    def __init__(self):
        self.examples = self.part_slices = self.blocks = None

    def hold(self, examples: list, part_slices: list) -> int:
        """Keep ``examples`` (each one's parts)."""
        self.examples, self.part_slices, self.blocks = examples, part_slices, None
        return len(examples)

    def call(self, method: str, *arguments):
        """``open`` the round's block set of the examples held (returns its
        :class:`~.blocks.Layout`), or call the set's ``method`` with ``arguments``."""
        return InTurn(self._call)(method, *arguments)

    def _call(self, method: str, *arguments):
        if method == "open":
            self.blocks = BlockSet(self.examples, self.part_slices, *arguments)
            return self.blocks.layout
        return getattr(self.blocks, method)(*arguments)


@dataclass
class _Stretch:
    """Consecutive active rows, the worker that holds their examples (``here``: the build's
    process, in ``blocks``) and the round's trials it was asked to sample and still keeps."""

    rows: slice
    worker: str | None
    blocks: BlockSet | None = None
    holder: object = None                          # the Dask actor on the worker, its future
    actor: object = None                           # and the actor itself
    trials: dict = field(default_factory=dict)     # number -> (x, keep) of kept trials

    @property
    def here(self) -> bool:
        return self.worker is None


class _Lost(Exception):
    """A worker left (or forgot its examples) while it held a stretch."""


class ExamplesOnCluster:
    """A phase's per-example work on the workers of the Dask ``client``: the interface of
    :class:`~.fast.ExamplesHere` (``open``, ``each``, ``commit``), and :meth:`close` (also as
    a context manager), which releases what the workers hold.

    Parameters
    ----------
    client : distributed.Client
        A client of the scheduler whose workers (those connected now) do the work.
    state : CorrespondenceState
        The state the phase optimises (its parts are sent to the workers).
    active : sequence of int
        The examples the phase moves.
    threads : Threads, optional
        Threads for a stretch taken here from a lost worker.
    """

    def __init__(self, client, state: CorrespondenceState, active,
                 threads: Threads | None = None):
        self.client, self.state = client, state
        self.threads = threads or Threads(1)
        self.active = np.array(list(active), dtype=np.int64)
        workers = sorted(self._workers())
        count = max(min(len(workers), len(self.active)), 1)
        edges = [len(self.active) * k // count for k in range(count + 1)]
        self.stretches = [_Stretch(slice(a, b), worker)
                          for a, b, worker in zip(edges, edges[1:], workers or [None])]
        self.opened = None          # the round's arguments of BlockSet
        if not workers:
            log.warning("the Dask cluster has no workers (or no scheduler) now: the "
                        "optimisation's per-example work runs in this process")
            return
        made = {k: client.submit(Holder, workers=[s.worker], allow_other_workers=False,
                                 actor=True, pure=False)
                for k, s in enumerate(self.stretches)}
        for k, actor in self._outcomes(made).items():
            if isinstance(actor, _Lost):
                self._take_here(self.stretches[k], actor)
            else:
                self.stretches[k].holder, self.stretches[k].actor = made[k], actor
        self._each("hold", [(self._parts(s), state.part_slices) for s in self.stretches])
        log.info("the optimisation's per-example work on %d Dask worker%s (%s examples each)",
                 count, "s" if count > 1 else "",
                 "-".join(sorted({str(s.rows.stop - s.rows.start) for s in self.stretches})))

    def _parts(self, stretch: _Stretch) -> list:
        return [self.state.examples[i].parts for i in self.active[stretch.rows]]

    def open(self, active: np.ndarray, level: int, support: float, pose_limits) -> list:
        """Make the round's block sets; (rows, :class:`~.blocks.Layout`) of each stretch."""
        if not np.array_equal(active, self.active):
            raise ArgumentError("a round's active examples are not those of its phase")
        self.opened = (level, support, list(pose_limits))
        for stretch in self.stretches:
            stretch.trials = {}
        layouts = self._each("open", [self.opened] * len(self.stretches))
        return [(s.rows, layout) for s, layout in zip(self.stretches, layouts)]

    def each(self, method: str, arguments: list) -> list:
        """Each stretch's block set's ``method`` called with its arguments, on its worker."""
        results = self._each(method, arguments)
        if method == "sample":      # what a stretch taken here would sample again
            for stretch, (number, x, keep) in zip(self.stretches, arguments):
                stretch.trials = {k: v for k, v in stretch.trials.items() if k in keep}
                stretch.trials[number] = (np.array(x, copy=True), keep)
        return results

    def commit(self, trial: int, parameters: list):
        """Commit ``trial`` on the workers' copies of the parts and on the state's."""
        settled = self._each("commit", [(trial, x) for x in parameters])
        # a stretch here has committed its block set, of the state's own parts
        changes = [(self.active[stretch.rows][row], j, arguments)
                   for stretch, changed in zip(self.stretches, settled) if not stretch.here
                   for row, j, arguments in changed]

        def commit(indices):     # on the threads: a part carrying a finer grid moves it
            for k in indices:
                i, j, arguments = changes[k]
                self.state.examples[i].parts[j].commit(*arguments)

        self.threads.over(len(changes), commit)

    def close(self):
        """Let the workers' actors go (the scheduler releases them, without waiting here)."""
        for stretch in self.stretches:
            stretch.holder = stretch.actor = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _each(self, method: str, arguments: list) -> list:
        futures = {}
        for k, (stretch, given) in enumerate(zip(self.stretches, arguments)):
            if not stretch.here:
                try:
                    futures[k] = (stretch.actor.hold(*given) if method == "hold"
                                  else stretch.actor.call(method, *given))
                except OSError as error:       # its worker is gone
                    futures[k] = error
        results = [None] * len(self.stretches)
        for k, stretch in enumerate(self.stretches):       # meanwhile, the stretches here
            if stretch.here:
                results[k] = self._here(stretch, method, arguments[k])
        for k, outcome in self._outcomes(futures).items():
            if isinstance(outcome, _Lost):
                self._take_here(self.stretches[k], outcome)
                results[k] = self._here(self.stretches[k], method, arguments[k])
            else:
                results[k] = outcome
        return results

    def _here(self, stretch: _Stretch, method: str, given: tuple):
        if method == "hold":
            return len(self._parts(stretch))
        if method == "open":
            stretch.blocks = BlockSet(self._parts(stretch), self.state.part_slices, *given,
                                      self.threads)
            return stretch.blocks.layout
        return getattr(stretch.blocks, method)(*given)

    def _take_here(self, stretch: _Stretch, why: _Lost):
        """The stretch of a lost worker, from now on in this process: its block set made of the
        state's parts (as at the start of the round: a commit reaches them only once every
        worker has committed), the round's kept trials sampled again."""
        log.warning("%s while it held examples %d-%d of %d of the optimisation: they are "
                    "optimised in this process from now on", why, stretch.rows.start + 1,
                    stretch.rows.stop, len(self.active))
        stretch.worker = stretch.holder = stretch.actor = None
        if self.opened is not None:
            stretch.blocks = BlockSet(self._parts(stretch), self.state.part_slices,
                                      *self.opened, self.threads)
        for number in sorted(stretch.trials):
            x, keep = stretch.trials[number]
            stretch.blocks.sample(number, x, keep)

    def _outcomes(self, futures: dict) -> dict:
        """Index -> result, or :class:`_Lost`, of each future; waits while the workers are
        there, asking the scheduler every :data:`POLL_SECONDS`."""
        outcomes = {k: _Lost(f"the Dask worker {self.stretches[k].worker} cannot be reached "
                             f"({future})") for k, future in futures.items()
                    if isinstance(future, OSError)}
        pending = {k: future for k, future in futures.items() if k not in outcomes}
        while pending:
            for k, future in list(pending.items()):
                if future.done():
                    outcomes[k] = self._outcome(pending.pop(k), self.stretches[k].worker)
            if not pending:
                break
            waited = next(iter(pending.values()))
            try:
                waited.result(timeout=POLL_SECONDS)
            except Exception:       # its error is taken above, at the next turn
                pass
            if waited.done():
                continue
            present = self._workers()
            for k in [k for k in pending if self.stretches[k].worker not in present]:
                getattr(pending.pop(k), "cancel", lambda: None)()    # (an actor's call: none)
                outcomes[k] = _Lost(f"the Dask worker {self.stretches[k].worker} left the "
                                    "cluster")
        return outcomes

    def _workers(self) -> set:
        if self.client.status != "running":
            return set()
        try:
            return set(self.client.nthreads())
        except OSError:         # the scheduler went away
            return set()

    def _outcome(self, future, worker: str):
        try:
            with self.client.as_current():   # an actor's proxy binds to the current client
                return future.result()
        except LookupError:                  # a new process at the worker's address
            return _Lost(f"the Dask worker {worker} lost its examples")
        except CancelledError:
            return _Lost(f"the Dask worker {worker}'s call was cancelled")
        except OSError:                      # its connection broke
            return _Lost(f"the Dask worker {worker} died")
        except Exception as error:
            from ...cluster import killed_on_cluster

            if killed_on_cluster(error):
                return _Lost(f"the Dask worker {worker} died")
            raise
