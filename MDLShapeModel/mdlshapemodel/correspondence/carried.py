"""The coarse stage's carried grids: a finer grid's sample positions moved by every warp a coarser
part accepts, so that the coarse stage hands the model's grid its map without keeping the warps
(:mod:`.coarse`, :meth:`.state.PartState.carry`); and the two checks on warps it shares with the
state, a grid's folds and the warps' counts by kind.
"""

from __future__ import annotations

import numpy as np

from ..prepare.sphere import orientation
from .warps import Warp


def folds(positions: np.ndarray, triangles: np.ndarray) -> bool:
    """Whether any of ``triangles`` (indices into ``positions``, points on the sphere) is
    flipped."""
    return bool(np.any(orientation(positions, triangles) <= 0))


def kind_counts(warps) -> dict:
    """How many of ``warps`` are of each kind (only the kinds there are)."""
    counts = {}
    for warp in warps:
        counts[warp.kind] = counts.get(warp.kind, 0) + 1
    return counts


class CarriedGrid:
    """A finer grid's sample positions, moved by every warp a coarser part accepts
    (:meth:`PartState.carry`): the map of the coarse stage on the model's grid, without the
    warps.

    Like :meth:`PartState.replay_unfolded`, it keeps the positions every warp gives unless
    their composition turns a triangle of this grid over; then those before the first warp
    that did. So it holds, beside the positions and the counts of warps by kind, the positions
    and counts before that first warp (``unfolded``) once there is one.
    """

    def __init__(self, positions: np.ndarray, triangles: np.ndarray,
                 counts: dict | None = None):
        self.start = (positions, dict(counts or {}))
        self.triangles = triangles
        self.restart()

    def restart(self):
        """Back to the positions it started from."""
        self.positions, counts = self.start
        self.counts = dict(counts)
        self.unfolded = None        # (positions, counts) before the first warp that folded

    def move(self, warp: Warp):
        """Apply one more warp."""
        moved = warp.apply(self.positions)
        if self.unfolded is None and folds(moved, self.triangles):
            self.unfolded = (self.positions, dict(self.counts))
        self.positions = moved
        self.counts[warp.kind] = self.counts.get(warp.kind, 0) + 1

    def copy(self) -> "CarriedGrid":
        """An independent copy (the positions are never written in place: shared)."""
        twin = object.__new__(CarriedGrid)
        twin.__dict__.update(self.__dict__)
        twin.counts = dict(self.counts)
        return twin

    def settled(self) -> tuple:
        """(positions, counts by kind) the finer part takes: those of every warp, or where
        they turn a triangle over, those before the first warp that did."""
        if self.unfolded is not None and folds(self.positions, self.triangles):
            return self.unfolded
        return self.positions, self.counts
