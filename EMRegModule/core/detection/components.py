"""Connected components of a boolean volume that arrives block of rows by block of rows (numpy axis 0).

:class:`GrowingComponents` labels each new block once (``scipy.ndimage.label``, 26-connected)
and joins its components to those of the block before through the two rows where the blocks
meet, so that a component spanning many blocks (a bone along the scan) is never labelled
again: the work is proportional to the rows read, not to the rows times the steps. Each
component keeps what the coarse candidate search asks of it: its sample count, the sums of its
sample coordinates (exact: integers summed in float64) and its bounding box. A component is
*complete* once the newest row does not touch it: no later row can join it any more. The
components are the same, with the same figures, however the rows are split into blocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

CONNECTIVITY_26 = np.ones((3, 3, 3), dtype=bool)
"""Face, edge and corner neighbours."""


@dataclass(frozen=True)
class Component:
    """A complete component: sample count, mean sample index (z, y, x), bounding box start and stop (z, y, x)."""

    count: int
    mean_zyx: np.ndarray
    start_zyx: np.ndarray
    stop_zyx: np.ndarray


class GrowingComponents:
    """26-connected components of rows ``0..n-1`` of a boolean volume, fed a block of rows at a time."""

    def __init__(self) -> None:
        self._rows = 0
        self._parent = np.zeros(1, dtype=np.int64)  # union-find over labels (0: background)
        self._count = np.zeros(1, dtype=np.int64)
        self._sums = np.zeros((1, 3))
        self._start = np.zeros((1, 3), dtype=np.int64)
        self._stop = np.zeros((1, 3), dtype=np.int64)
        self._last_row: np.ndarray | None = None  # labels of the newest row
        self._open = np.zeros(0, dtype=np.int64)  # roots of components not yet complete

    def add(self, block: np.ndarray, last: bool = False, min_count: int = 0) -> list[Component]:
        """Add the next rows (``block``, boolean z, y, x); the components they complete, ordered by their first
        sample. ``last``: no rows follow, so every component still open is complete too. ``min_count``: complete
        components of fewer samples are dropped unseen (noise specks: thousands of them in a noisy scan)."""
        labels, count = ndimage.label(block, structure=CONNECTIVITY_26)
        base = len(self._parent) - 1
        if count:
            self._grow(labels, count, base)
            np.add(labels, base, out=labels, where=labels > 0)
        if count and self._last_row is not None and len(block):
            for a, b in _touching(self._last_row, labels[0]):
                self._union(int(a), int(b))
        if len(block):
            self._last_row = labels[-1].copy()
        self._rows += len(block)
        pending = np.unique(self._roots(np.concatenate([self._open, np.arange(base + 1, base + count + 1)])))
        self._open = np.zeros(0, dtype=np.int64) if last or self._last_row is None else \
            np.unique(self._roots(np.unique(self._last_row[self._last_row > 0])))
        complete = np.setdiff1d(pending, self._open, assume_unique=True)
        complete = complete[self._count[complete] >= min_count]
        start = self._start[complete]
        complete = complete[np.lexsort((complete, start[:, 2], start[:, 1], start[:, 0]))]
        return [Component(int(self._count[root]), self._sums[root] / self._count[root], self._start[root].copy(),
                          self._stop[root].copy()) for root in complete]

    def _roots(self, labels: np.ndarray) -> np.ndarray:
        """The union-find roots of ``labels`` (all at once: parents are followed until none changes)."""
        roots = self._parent[labels]
        while True:
            up = self._parent[roots]
            if np.array_equal(up, roots):
                return roots
            roots = up

    def _grow(self, labels: np.ndarray, count: int, base: int) -> None:
        """Append the statistics of a block's ``count`` new labels (numbered ``base + 1 ..``)."""
        inside = np.flatnonzero(labels)  # raster order
        members = labels.ravel()[inside]
        order = np.argsort(members, kind="stable")  # by label (each of 1 .. count has samples)
        first = np.flatnonzero(np.r_[True, members[order][1:] != members[order][:-1]])
        counts = np.diff(np.r_[first, len(order)])
        coordinates = np.column_stack(np.unravel_index(inside[order], labels.shape)) + [self._rows, 0, 0]
        sums = np.add.reduceat(coordinates, first, axis=0).astype(float)  # integers: exact
        start = np.minimum.reduceat(coordinates, first, axis=0)
        stop = np.maximum.reduceat(coordinates, first, axis=0) + 1
        self._parent = np.concatenate([self._parent, np.arange(base + 1, base + count + 1)])
        self._count = np.concatenate([self._count, counts])
        self._sums = np.concatenate([self._sums, sums])
        self._start = np.concatenate([self._start, start])
        self._stop = np.concatenate([self._stop, stop])

    def _find(self, label: int) -> int:
        root = label
        while self._parent[root] != root:
            root = int(self._parent[root])
        while self._parent[label] != root:  # path compression
            self._parent[label], label = root, int(self._parent[label])
        return root

    def _union(self, a: int, b: int) -> None:
        a, b = self._find(a), self._find(b)
        if a == b:
            return
        keep, gone = min(a, b), max(a, b)
        self._parent[gone] = keep
        self._count[keep] += self._count[gone]
        self._sums[keep] += self._sums[gone]
        self._start[keep] = np.minimum(self._start[keep], self._start[gone])
        self._stop[keep] = np.maximum(self._stop[keep], self._stop[gone])


def _touching(previous: np.ndarray, first: np.ndarray) -> np.ndarray:
    """Distinct label pairs (previous row's, first new row's) of samples that are 26-neighbours across the rows."""
    pairs = []
    height, width = first.shape
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            a = previous[max(0, dy):height + min(0, dy), max(0, dx):width + min(0, dx)]
            b = first[max(0, -dy):height + min(0, -dy), max(0, -dx):width + min(0, -dx)]
            both = (a > 0) & (b > 0)
            if both.any():
                pairs.append(np.column_stack([a[both], b[both]]))
    return np.unique(np.concatenate(pairs), axis=0) if pairs else np.empty((0, 2), dtype=np.int64)
