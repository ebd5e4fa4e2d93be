"""Geodesic distances along a mask: the order of the catheter's pixels from its base
(docs/vision.md section 4), compiled (numba).

The mask's pixels are the nodes of their 8-neighbour grid, edges 1 and sqrt 2 px long (no
graph is built: :func:`pixel_index` is an image of the pixels' numbers, and the sweep looks
up each pixel's neighbours in it). :func:`geodesic_sweep` is Dijkstra's algorithm from a
seed over it, with buckets one pixel wide for a queue; pieces of a catheter split by an
occluder are joined across gaps. The kernels are ``njit(cache=True, nogil=True)`` and take
arrays of fixed dtypes, as :mod:`tracker.vision.kernels` explains; :func:`warm_up` compiles
(or loads) them.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# The 8 neighbours (row, column steps) and the lengths of the edges to them, px, as the
# pixel graph has always had them (np.hypot: 1 and sqrt 2 correctly rounded).
_DY = (-1, -1, -1, 0, 0, 1, 1, 1)
_DX = (-1, 0, 1, -1, 1, -1, 0, 1)
_LENGTHS = tuple(float(np.hypot(dy, dx)) for dy, dx in zip(_DY, _DX, strict=True))

NO_BRIDGES = (np.zeros((0, 2), np.int64), np.zeros(0))
"""No gap bridged yet: the ``ends`` and ``lengths`` to start :func:`geodesic_sweep` with."""
for _array in NO_BRIDGES:
    _array.flags.writeable = False


@numba.njit(cache=True, nogil=True)
def nearest(xy, x, y):
    """The first of the points ``xy`` (float64 (2, n)) nearest to (x, y) (floats)."""
    best = np.inf
    k = 0
    for i in range(xy.shape[1]):
        dx = xy[0, i] - x
        dy = xy[1, i] - y
        d = dx * dx + dy * dy
        if d < best:
            best = d
            k = i
    return k


@numba.njit(cache=True, nogil=True)
def pixel_index(ys, xs, height, width):
    """The pixels' numbers in an int32 image (height + 2, width + 2), -1 elsewhere: pixel i
    at row ``ys[i] + 1``, column ``xs[i] + 1`` (a border of -1 all round, so every pixel
    has eight neighbours to look at). ``ys``, ``xs``: intp (n,), in a box (height, width)."""
    index = np.full((height + 2, width + 2), -1, np.int32)
    for i in range(ys.size):
        index[ys[i] + 1, xs[i] + 1] = i
    return index


@numba.njit(cache=True, nogil=True)
def _reach(dist, done, head, after, pixel, used, mask, v, dv):
    """Lower pixel v's distance to dv if that is shorter, filing it under its bucket
    ``int(dv)`` (the lists of :func:`_dijkstra`); returns the entries used."""
    if done[v] or not dv < dist[v]:
        return used
    dist[v] = dv
    bucket = int(dv) & mask
    pixel[used] = v
    after[used] = head[bucket]
    head[bucket] = used
    return used + 1


@numba.njit(cache=True, nogil=True)
def _dijkstra(index, ys, xs, seed, ends, lengths):
    """Shortest distances from ``seed`` over the 8-neighbour grid plus the bridges.

    Dijkstra with buckets one pixel wide (Dial's): no edge is shorter than 1 px (the grid's
    are 1 and sqrt 2, a bridge joins pixels that are not neighbours, 2 px or more apart), so
    a pixel's distance is final when its bucket ``[k, k + 1)`` comes up, and the pixels of a
    bucket may be taken in any order: no priority queue, a few times faster than a binary
    heap. The buckets are a ring (an edge reaches at most ``int(longest) + 1`` buckets
    ahead), each a linked list of entries (pixel, next entry); a pixel lowered again is
    filed again and its stale entries skipped.

    The distances are those of any correct shortest-path algorithm to the last bit: each is
    the least ``dist[u] + length`` over its neighbours, in floating point too (the sums only
    grow along a path), one and the same fixed point whatever the order of the work.
    """
    n = ys.size
    longest = _LENGTHS[0]
    for b in range(lengths.size):
        if not lengths[b] >= 1.0:
            raise ValueError("a bridge must be at least 1 px long (the buckets' width)")
        longest = max(longest, lengths[b])
    ring = 4  # a power of two, for a mask instead of a division
    while ring < int(longest) + 2:
        ring *= 2
    mask = ring - 1
    head = np.full(ring, -1, np.int64)
    # Each edge files at most one entry (when its first end is taken), plus the seed.
    capacity = 8 * n + 2 * lengths.size + 1
    pixel = np.empty(capacity, np.int64)
    after = np.empty(capacity, np.int64)
    dist = np.full(n, np.inf)
    done = np.zeros(n, np.bool_)
    bridged = np.zeros(n, np.bool_)
    for b in range(lengths.size):
        bridged[ends[b, 0]] = True
        bridged[ends[b, 1]] = True
    used = _reach(dist, done, head, after, pixel, 0, mask, seed, 0.0)
    taken = 0  # entries taken off the lists
    bucket = 0
    while taken < used:
        entry = head[bucket & mask]
        head[bucket & mask] = -1
        while entry >= 0:
            u = pixel[entry]
            entry = after[entry]
            taken += 1
            if done[u] or int(dist[u]) != bucket:
                continue  # stale: taken already, or filed again under an earlier bucket
            done[u] = True
            d = dist[u]
            row = ys[u] + 1
            col = xs[u] + 1
            for k in range(8):
                v = index[row + _DY[k], col + _DX[k]]
                if v >= 0:
                    used = _reach(dist, done, head, after, pixel, used, mask, v, d + _LENGTHS[k])
            if bridged[u]:
                for b in range(lengths.size):
                    if ends[b, 0] == u:
                        v = ends[b, 1]
                    elif ends[b, 1] == u:
                        v = ends[b, 0]
                    else:
                        continue
                    used = _reach(dist, done, head, after, pixel, used, mask, v, d + lengths[b])
        bucket += 1
    return dist


@numba.njit(cache=True, nogil=True)
def geodesic_sweep(index, ys, xs, xy, seed, max_gap_px, ends, lengths):
    """Geodesic distances from ``seed``, joining unreached pieces across gaps <= max_gap_px.

    While some pixels are unreached (at most 8 times): the unreached pixel nearest to the
    farthest one reached is bridged to it, if within ``max_gap_px``, and the sweep is run
    again (the last bridge of the 8th round is kept but not swept).

    Parameters
    ----------
    index : int32 array (h + 2, w + 2)
        :func:`pixel_index` of the pixels ``ys``, ``xs`` (intp (n,)).
    xy : float64 array (2, n)
        Their image coordinates, px: the lengths of the gaps bridged.
    seed : int
    max_gap_px : float
        0: no bridges.
    ends, lengths : int64 array (k, 2), float64 array (k,)
        The bridges already in the graph (pixel pairs, lengths px; :data:`NO_BRIDGES`, or
        what an earlier sweep over the same pixels returned: bridges join pixels that are
        not neighbours, so they are 2 px long or more).

    Returns
    -------
    dist : float64 (n,)
        inf where unreached.
    ends, lengths
        The bridges, with those added here last (more of them: a gap was bridged).
    """
    dist = _dijkstra(index, ys, xs, seed, ends, lengths)
    for round_ in range(8):
        if max_gap_px <= 0:
            break
        # The farthest pixel reached (the first of them) and whether any is unreached.
        far = -1
        farthest = -1.0
        unreached = False
        for i in range(dist.size):
            if dist[i] < np.inf:
                if dist[i] > farthest:
                    farthest = dist[i]
                    far = i
            else:
                unreached = True
        if not unreached:
            break
        fx = xy[0, far]
        fy = xy[1, far]
        gap = np.inf
        j = -1
        for i in range(dist.size):
            if dist[i] == np.inf:
                dx = xy[0, i] - fx
                dy = xy[1, i] - fy
                g = math.sqrt(dx * dx + dy * dy)
                if g < gap:
                    gap = g
                    j = i
        if gap > max_gap_px:
            break
        k = lengths.size
        grown_ends = np.empty((k + 1, 2), np.int64)
        grown_ends[:k] = ends
        grown_ends[k, 0] = far
        grown_ends[k, 1] = j
        grown = np.empty(k + 1)
        grown[:k] = lengths
        grown[k] = gap
        ends, lengths = grown_ends, grown
        if round_ < 7:
            dist = _dijkstra(index, ys, xs, seed, ends, lengths)
    return dist, ends, lengths


def warm_up() -> tuple:
    """Compile (or load) this module's kernels on a tiny mask, with the argument types the
    segmentation passes; returns that mask's pixels, coordinates, index and distances
    (ys, xs, xy, index, dist) for the other kernels' warm-up."""
    ys, xs = (np.ascontiguousarray(a, dtype=np.intp) for a in np.nonzero(np.ones((2, 5))))
    xy = np.array([xs, ys], np.float64)
    nearest(xy, 0.0, 0.0)
    index = pixel_index(ys, xs, 2, 5)
    dist, _, _ = geodesic_sweep(index, ys, xs, xy, 0, 30.0, *NO_BRIDGES)
    return ys, xs, xy, index, dist
