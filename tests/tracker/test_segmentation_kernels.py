"""The segmentation's compiled kernels: each against a pure-numpy reference of what it
computes, on the arguments it was given while segmenting rendered frames; and every kernel
compiled or loaded before the first frame."""

import collections
import itertools

import cv2
import numba
import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from tests.fresh import last_value
from tests.tracker import segmentation_common
from tests.tracker.segmentation_common import BASE_W, Q_BENT
from tracker.vision import kernels, pixel_graph
from tracker.vision.pair import PairSegmenter
from tracker.vision.segmentation import SegmentationFlag

# A fixture shared with test_segmentation.py: pytest finds it under this name.
scene = segmentation_common.scene


# ------------------------------------------------------------------------ compiled kernels
# Each kernel against a pure-numpy reference of what it computes (the numpy steps it
# replaced, kept here only), on the arguments it was given while segmenting real frames.
@pytest.fixture(scope="module")
def kernel_calls(scene):
    """{kernel: [(args, result), ...]} while segmenting a pair (whole, then around predicted
    points), a catheter split by an occluder (joined again), and a view without its base."""
    catheter, rig, renderer = scene
    calls = collections.defaultdict(list)
    with pytest.MonkeyPatch.context() as patch:
        for module in (kernels, pixel_graph):
            for name, kernel in list(vars(module).items()):
                if isinstance(kernel, numba.core.registry.CPUDispatcher) and name[0] != "_":

                    def record(*args, _kernel=kernel, _calls=calls[name]):
                        _calls.append((args, _kernel(*args)))
                        return _calls[-1][1]

                    patch.setattr(module, name, record)
        rng = np.random.default_rng(4)
        clean = renderer.render(Q_BENT, 0.0, rng)
        u, v = clean.points_px[0][1].astype(int)
        occluded = renderer.render(Q_BENT, 0.0, rng, occluders=([(u - 7, v - 7, 14, 14)], []))
        segmenter = PairSegmenter(catheter, rig, np.eye(3), BASE_W, renderer.backgrounds)
        segmenter.segment(clean.images)
        segmenter.segment(clean.images, clean.points_px)
        assert segmenter.segment(occluded.images).views[0].flags & SegmentationFlag.FRAGMENTED
        segmenter.segmenter.segment(clean.images[1], renderer.backgrounds[1])  # no base
    return calls


def ref_geodesic_sweep(index, ys, xs, xy, seed, max_gap_px, ends, lengths):
    """The pixel graph as an explicit sparse matrix (8-neighbour edges of 1 and sqrt 2 px and
    the bridges, both ways) and scipy's Dijkstra; bridging as geodesic_sweep documents."""
    edges = [
        (np.flatnonzero(j >= 0), j[j >= 0], np.hypot(dy, dx))
        for dy, dx in itertools.product((-1, 0, 1), repeat=2)
        if dy or dx
        for j in [index[ys + 1 + dy, xs + 1 + dx]]
    ]
    bridges = [(int(a), int(b), float(g)) for (a, b), g in zip(ends, lengths, strict=True)]
    for _ in range(8):
        pieces = [(e[0], e[1], np.full(e[0].size, e[2])) for e in edges]
        pieces += [(np.array([a, b]), np.array([b, a]), np.full(2, g)) for a, b, g in bridges]
        rows, cols, data = (np.concatenate(p) for p in zip(*pieces, strict=True))
        graph = csr_matrix((data, (rows, cols)), shape=(ys.size, ys.size))
        dist = dijkstra(graph, indices=seed, min_only=True)
        reached = np.isfinite(dist)
        if reached.all() or max_gap_px <= 0:
            break
        far = int(np.argmax(np.where(reached, dist, -1)))
        out = np.flatnonzero(~reached)
        gaps = np.sqrt((xy[0, out] - xy[0, far]) ** 2 + (xy[1, out] - xy[1, far]) ** 2)
        if gaps.min() > max_gap_px:
            break
        bridges.append((far, int(out[np.argmin(gaps)]), float(gaps.min())))
    return dist, bridges


def test_geodesic_sweep_equals_scipy_dijkstra_to_the_last_bit(kernel_calls):
    """The distances of the bucket queue are those of scipy's Fibonacci heap, bit for bit
    (each is the least dist + length over its neighbours, one fixed point): on every sweep
    of the segmentation, and on random masks in pieces from random seeds."""
    calls = [args for args, _ in kernel_calls["geodesic_sweep"]]
    rng = np.random.default_rng(0)
    for _ in range(20):
        mask = rng.random((30, 40)) < 0.5
        mask[:, rng.integers(5, 35, 2)] = False  # cuts: pieces to bridge
        ys, xs = (np.ascontiguousarray(a, np.intp) for a in np.nonzero(mask))
        xy = np.array([xs + 3, ys + 5], float)
        index = pixel_graph.pixel_index(ys, xs, *mask.shape)
        calls.append((index, ys, xs, xy, int(rng.integers(ys.size)), 4.0, *pixel_graph.NO_BRIDGES))
    for args in calls:
        dist, ends, lengths = pixel_graph.geodesic_sweep(*args)
        expected, bridges = ref_geodesic_sweep(*args)
        assert np.array_equal(dist, expected)
        assert [
            (int(a), int(b), float(g)) for (a, b), g in zip(ends, lengths, strict=True)
        ] == bridges


def ref_bands(index, ys, xs, w, var_w, dist, band_contrast, min_area, x0, y0):
    """Band pixels (w >= band_contrast) in 8-connected groups (cv2.connectedComponents) of
    min_area or more: contrast-weighted centroids, their covariances sum(var (p - c)(p - c)^T)
    / W^2, distances (weighted mean, least, greatest) and pixels, in order of distance."""
    idx = np.flatnonzero(w >= band_contrast)
    mask = np.zeros((index.shape[0] - 2, index.shape[1] - 2), np.uint8)
    mask[ys[idx], xs[idx]] = 1
    n, labels = cv2.connectedComponents(mask, connectivity=8)
    groups = [idx[labels[ys[idx], xs[idx]] == k] for k in range(1, n)]
    bands = []
    for m in (g for g in groups if g.size >= min_area):
        weight = w[m] - band_contrast
        p = np.array([xs[m], ys[m]], float)
        c = p @ weight / weight.sum()
        r = p - c[:, None]
        cov = (r * var_w[m]) @ r.T / weight.sum() ** 2
        bands.append(
            (c + (x0, y0), cov, weight @ dist[m] / weight.sum(), dist[m].min(), dist[m].max(), m)
        )
    return sorted(bands, key=lambda b: b[2])


def ref_ends(
    xy, w, var_w, dist, line, label, centres, covs, along, base, tip, D, bin_px, slab_px, sigma_rad
):
    """Each end past its cut (the end band's centroid, or the centreline two bins in) by
    mass conservation: e = mass past the cut / mass per px in the slab behind it, pixels
    straddling a line counting by the fraction of their footprint; see kernels.ends."""
    out = np.full((2, kernels.END_FIELDS), np.nan)
    step = 2.0 * bin_px
    for row, (band, sign) in enumerate(((base, 1.0), (tip, -1.0))):
        if line.shape[1] < 4:
            break
        d_cut = along[band, 0] if band >= 0 else (step if sign > 0 else D - step)
        at = [d_cut, d_cut + sign * step, d_cut + sign * 2.0 * step]
        samples = np.array([np.interp(at, line[2], line[0]), np.interp(at, line[2], line[1])])
        cut = centres[band] if band >= 0 else samples[:, 0]
        d = 3.0 * cut - 4.0 * samples[:, 1] + samples[:, 2]
        if np.hypot(*d) < 1e-9:
            continue
        d /= np.hypot(*d)
        slab = (
            slab_px
            if band < 0
            else min(max(cut @ d - (d @ xy[:, label == band]).min(), 0.5), slab_px)
        )  # back to the band
        side = dist >= d_cut - slab - step if sign < 0 else dist <= d_cut + slab + step
        rel = xy - cut[:, None]
        near = side & ((rel * rel).sum(axis=0) <= (3.0 * step + slab) ** 2)
        t = d @ rel[:, near]
        part = np.clip(np.array([t, t + slab]) / np.abs(d).sum() + 0.5, 0.0, 1.0)
        part[1] -= part[0]
        mass, behind = part @ w[near]
        m = behind / slab
        if not m > 0:
            continue
        e = mass / m
        grad = np.array([1.0 / m, -e / (m * slab)])
        contrast = np.sort(w[near])[int(0.9 * (near.sum() - 1))]
        radius = 0.5 * m / max(contrast, 1e-6)
        var_e = grad @ ((part * var_w[near]) @ part.T) @ grad + (np.pi / 8.0 * radius) ** 2
        cov = (
            (covs[band] if band >= 0 else np.zeros((2, 2)))
            + var_e * np.outer(d, d)
            + ((e * sigma_rad) ** 2 * (np.eye(2) - np.outer(d, d)))
        )
        out[row] = [*(cut + e * d), *cov.ravel(), *d, e, radius, m]
    return out


def test_pixel_kernels_equal_their_numpy_references(kernel_calls):
    for (image, background, lut, dark, sigma, ys, xs, x0, y0), (w, var_w, xy) in kernel_calls[
        "contrast"
    ]:
        lit = lut[background[ys + y0, xs + x0]].astype(np.float64)
        bg = np.maximum(lit - dark, 1.0)
        assert np.array_equal(w, np.maximum(lit - image[ys + y0, xs + x0], 0.0) / bg)
        assert np.array_equal(var_w, (sigma / bg) ** 2)
        assert np.array_equal(xy, np.array([xs + x0, ys + y0], float))
    for (xy, x, y), k in kernel_calls["nearest"]:
        assert k == np.argmin((xy[0] - x) ** 2 + (xy[1] - y) ** 2)
    for (ys, xs, _, width), index in kernel_calls["pixel_index"]:
        assert np.array_equal(np.flatnonzero(index >= 0), np.sort((ys + 1) * (width + 2) + xs + 1))
        assert np.array_equal(index[ys + 1, xs + 1], np.arange(ys.size))
    for (dist, xy, w, bin_px), (bins, line) in kernel_calls["centreline"]:
        assert np.array_equal(bins, (dist / bin_px).astype(np.intp))
        sums = np.array([np.bincount(bins, weights=v) for v in (w, xy[0] * w, xy[1] * w, w * dist)])
        kept = sums[0] > 0
        assert np.array_equal(line, sums[1:, kept] / sums[0, kept])
    for (xy, dist, d_min), box in kernel_calls["extent_beyond"]:
        far = xy[:, dist >= d_min]
        assert box == (*far.min(axis=1), *far.max(axis=1))
    for args, (label, centres, covs, along) in kernel_calls["bands"]:
        expected = ref_bands(*args)
        assert len(expected) == len(centres) > 0
        for k, (c, cov, d, d_lo, d_hi, pixels) in enumerate(expected):
            np.testing.assert_allclose(centres[k], c, rtol=0, atol=1e-9)
            np.testing.assert_allclose(covs[k], cov, rtol=1e-9, atol=1e-15)
            np.testing.assert_allclose(along[k], (d, d_lo, d_hi), rtol=1e-12)
            assert np.array_equal(np.flatnonzero(label == k), pixels)
    for (bins, n_bins, along, bin_px), (count, typical_n) in kernel_calls["sample_counts"]:
        expected = np.bincount(bins, minlength=n_bins).astype(float)
        for _, d_lo, d_hi in along:
            expected[max(int(d_lo / bin_px) - 1, 0) : int(d_hi / bin_px) + 2] = 0.0
        expected[:2] = expected[-2:] = 0.0
        assert np.array_equal(count, expected)
        kept = expected[expected > 0]  # their median, if there are 3 or more to judge by
        np.testing.assert_equal(typical_n, np.median(kept) if kept.size >= 3 else np.nan)
    for args, result in kernel_calls["ends"]:
        np.testing.assert_allclose(result, ref_ends(*args), rtol=0, atol=1e-9)
    assert np.isfinite([result[:, 0] for _, result in kernel_calls["ends"]]).mean() > 0.8


def test_tip_kernel_equals_its_numpy_reference(kernel_calls):
    # (The photometric fit's kernel: tests/tracker/test_photometry.py.)
    assert kernel_calls["tip_tangent"]
    for args, (tangent, misfit) in kernel_calls["tip_tangent"]:
        expected, least = ref_tip_tangent(*args)
        np.testing.assert_allclose(tangent, expected, atol=1e-12)
        np.testing.assert_allclose(misfit, least, rtol=1e-12)


def ref_tip_tangent(linear, extent, cap_px, coarse, cap):
    """The least misfit over the coarse directions, then over the cap turned onto the best,
    then over the cap shrunk five times turned onto the best of those."""

    def cost(T):
        px, py, along, sin_a = np.split(linear @ T, 4)
        r_along = extent[:, None] - along - cap_px[:, None] * np.abs(sin_a)
        return (px**2 + py**2 - along**2 + r_along**2).sum(axis=0)

    t = coarse[:, np.argmin(cost(coarse))]
    for scale in (1.0, 0.2):  # the cap, then the cap shrunk five times
        u = np.cross(t, [1.0, 0.0, 0.0] if abs(t[0]) < 0.9 else [0.0, 1.0, 0.0])
        u = u / np.linalg.norm(u)
        a, b = scale * cap[0], scale * cap[1]
        shrunk = np.array([a, b, np.sqrt(np.maximum(1.0 - a * a - b * b, 0.0))])
        fine = np.array([u, np.cross(t, u), t]).T @ shrunk
        t = fine[:, np.argmin(cost(fine))]
    return t, cost(fine).min()


def test_kernels_are_ready_before_the_first_frame():
    """Making a segmenter compiles or loads every kernel (with the argument types the
    segmentation passes): segmenting then compiles nothing. In a fresh interpreter, as
    compiled versions only accumulate; and every kernel is cached and free of the GIL."""
    script = """
import numba, numpy as np
from models.catheter import default_catheter
from replay.simulation.render import Renderer, default_render_rig
from tracker.vision import kernels, photometry_kernels, pixel_graph, shift_kernels
from tracker.vision.pair import PairSegmenter
versions = lambda: {name: (len(f.signatures), f.targetoptions["nogil"], type(f._cache).__name__)
                    for m in (kernels, photometry_kernels, pixel_graph, shift_kernels)
                    for name, f in vars(m).items()
                    if isinstance(f, numba.core.registry.CPUDispatcher)}
catheter, rig, base = default_catheter(), default_render_rig(), np.array([0.0, 0.0, -15.0])
renderer = Renderer(catheter, rig, np.eye(3), base, seed=1)
segmenter = PairSegmenter(catheter, rig, np.eye(3), base, renderer.backgrounds)
before = versions()
pair = renderer.render(np.array([0.8, 0.7, 0.5]), 0.0, np.random.default_rng(0))
segmenter.segment(pair.images)
segmenter.segment(pair.images, pair.points_px)
segmenter.segmenter.segment(pair.images[0], renderer.backgrounds[0])
print(repr((before, versions())))
"""
    before, after = last_value(script)
    assert after == before
    for name, (count, nogil, cache) in before.items():  # helpers are inlined: no version
        assert nogil and cache == "FunctionCache" and count == int(name[0] != "_"), name
