"""The 8-neighbour graph of a mask's pixels and geodesic distances over it (the order of the
catheter's pixels from its base, docs/vision.md section 4)."""

from __future__ import annotations

import math

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

Array = np.ndarray

_OFFSETS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
_LENGTHS = np.array([np.hypot(dy, dx) for dy, dx in _OFFSETS])
_DY, _DX = (np.array(v, np.intp) for v in zip(*_OFFSETS, strict=True))
# Per-frame constants of n pixels are prefixes of longer arrays, kept and grown on demand (a
# view costs nothing; np.tile and np.arange cost a few us a frame).
_prefixes: dict[object, Array] = {}


def _prefix(key: object, size: int, make) -> Array:
    """The first ``size`` entries of the read-only array ``make(m)`` (at least m entries)
    kept under ``key``, made anew for twice the size when too short."""
    kept = _prefixes.get(key)
    if kept is None or kept.size < size:
        kept = make(2 * size)
        kept.flags.writeable = False
        _prefixes[key] = kept
    return kept[:size]


class PixelGraph:
    """The 8-neighbour graph of foreground pixels, edge lengths in px, for geodesic sweeps.

    Built straight into compressed sparse rows: pixels are numbered in row-major order, so
    each pixel's neighbour list is already grouped and no sort is needed. One graph serves
    frame after frame (:meth:`build`): its sparse matrix is kept, with room to spare, and
    only its arrays are replaced, since scipy's constructor checks them with some eighty
    Python calls, more than everything else a sweep does in Python. Not for several threads
    at once.
    """

    def __init__(self) -> None:
        self.n = 0
        self.xy = np.zeros((2, 0))
        self.graph = csr_matrix((1, 1))

    def build(self, ys: Array, xs: Array, shape: tuple[int, int], xy: Array) -> None:
        """The graph of these pixels.

        Parameters
        ----------
        ys, xs : intp arrays (n,)
            The pixels, row-major, in a box of ``shape`` (rows, columns).
        shape : (int, int)
        xy : float array (2, n)
            Their image coordinates (x row, y row), px: the lengths of the gaps bridged.
        """
        n = ys.size
        width = shape[1] + 2
        # Every pixel gets its eight neighbours in a padded index image; missing ones point
        # at an extra sink node n that has no way out, so no masking or sorting is needed.
        flat = ys * width
        flat += xs
        flat += width + 1
        index = np.full((shape[0] + 2) * width, n, np.int32)
        index[flat] = _prefix("numbers", n, lambda m: np.arange(m, dtype=np.int32))
        neighbours = flat.repeat(8)
        neighbours += _prefix(
            ("steps to the neighbours", width), 8 * n, lambda m: np.tile(_DY * width + _DX, m // 8)
        )
        if self.graph.shape[0] < n + 1:
            size = 2 * (n + 1)
            self.graph = csr_matrix((size, size))
        graph = self.graph
        # The nodes past the sink (room for larger masks) have no edges either.
        rows = _prefix("rows", graph.shape[0] + 1, lambda m: np.arange(0, 8 * m, 8, dtype=np.int32))
        graph.indptr = np.minimum(rows, 8 * n)
        graph.indices = index.take(neighbours)
        graph.data = _prefix("lengths", 8 * n, lambda m: np.tile(_LENGTHS, m // 8))
        self.n = n
        self.xy = xy

    def _bridge(self, a: int, b: int, length: float) -> None:
        g = self.graph.tocoo()
        keep = g.col < self.n
        g = g.__class__((g.data[keep], (g.row[keep], g.col[keep])), shape=g.shape)
        rows = np.concatenate([g.row, [a, b]])
        cols = np.concatenate([g.col, [b, a]])
        data = np.concatenate([g.data, [length, length]])
        self.graph = csr_matrix((data, (rows, cols)), shape=g.shape)

    def sweep(self, seed: int, max_gap_px: float) -> tuple[Array, bool]:
        """Geodesic distances from ``seed``, joining unreached pieces across gaps <= max_gap_px.

        Returns the distances (inf where unreached) and whether a gap was bridged (the
        bridges stay in the graph for later sweeps).
        """
        joined = False
        for _ in range(8):
            # min_only: the distances from the one seed as a row, not a (1, nodes) matrix.
            dist = dijkstra(self.graph, indices=seed, min_only=True)[: self.n]
            if math.isfinite(dist.max()) or max_gap_px <= 0:
                break
            reached = np.isfinite(dist)
            far = int(np.argmax(np.where(reached, dist, -1)))
            out = np.flatnonzero(~reached)
            x, y = self.xy
            dx, dy = x[out] - x[far], y[out] - y[far]
            gaps = np.sqrt(dx * dx + dy * dy)
            j = int(np.argmin(gaps))
            if gaps[j] > max_gap_px:
                break
            self._bridge(far, int(out[j]), float(gaps[j]))
            joined = True
        return dist, joined
