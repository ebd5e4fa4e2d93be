"""The 8-neighbour graph of a mask's pixels and geodesic distances over it (the order of the
catheter's pixels from its base, docs/vision.md section 4)."""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

Array = np.ndarray

_OFFSETS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
_LENGTHS = np.array([np.hypot(dy, dx) for dy, dx in _OFFSETS])
_DY, _DX = (np.array(v) for v in zip(*_OFFSETS, strict=True))
# The edge lengths of n pixels and the row starts of their neighbour lists are prefixes of
# these, grown on demand (a view costs nothing; np.tile and np.arange cost a few us a frame).
_tiled: dict[str, Array] = {"lengths": _LENGTHS, "steps": np.arange(0, 9, 8, dtype=np.int32)}


def _tiled_lengths(n: int) -> Array:
    """``np.tile(_LENGTHS, n)`` (read-only)."""
    if _tiled["lengths"].size < 8 * n:
        _tiled["lengths"] = np.tile(_LENGTHS, 2 * n)
        _tiled["lengths"].flags.writeable = False
    return _tiled["lengths"][: 8 * n]


def _steps_of_8(n: int) -> Array:
    """``np.arange(0, 8 n + 1, 8)`` as int32 (read-only)."""
    if _tiled["steps"].size < n + 1:
        _tiled["steps"] = np.arange(0, 16 * n + 1, 8, dtype=np.int32)
        _tiled["steps"].flags.writeable = False
    return _tiled["steps"][: n + 1]


class PixelGraph:
    """The 8-neighbour graph of foreground pixels, edge lengths in px, for geodesic sweeps.

    Built straight into compressed sparse rows: pixels are numbered in row-major order, so
    each pixel's neighbour list is already grouped and no sort is needed.
    """

    def __init__(self, ys: Array, xs: Array, shape: tuple[int, int], xy: Array) -> None:
        n = ys.size
        width = shape[1] + 2
        # Every pixel gets its eight neighbours; missing ones point at an extra sink node n
        # that has no way out, so no masking or sorting is needed.
        index = np.full((shape[0] + 2) * width, n, np.int32)
        flat = (ys + 1) * width + (xs + 1)
        index[flat] = np.arange(n, dtype=np.int32)
        nb = index[flat[:, None] + (_DY * width + _DX)]
        indptr = np.empty(n + 2, np.int32)
        indptr[: n + 1] = _steps_of_8(n)
        indptr[n + 1] = 8 * n
        lengths = _tiled_lengths(n)
        self.n = n
        self.xy = xy
        self.graph = csr_matrix((lengths, nb.ravel(), indptr), shape=(n + 1, n + 1))

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
            dist = dijkstra(self.graph, directed=True, indices=seed)[: self.n]
            reached = np.isfinite(dist)
            if reached.all() or max_gap_px <= 0:
                break
            far = int(np.argmax(np.where(reached, dist, -1)))
            out = np.flatnonzero(~reached)
            gaps = np.linalg.norm(self.xy[out] - self.xy[far], axis=1)
            j = int(np.argmin(gaps))
            if gaps[j] > max_gap_px:
                break
            self._bridge(far, int(out[j]), float(gaps[j]))
            joined = True
        return dist, joined
