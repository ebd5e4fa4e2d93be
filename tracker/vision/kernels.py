"""The segmentation's per-pixel steps, compiled (numba; docs/vision.md section 4).

Each view's catheter is a few thousand pixels, held as flat arrays (one value per pixel, in
row-major order of the region of interest) and a (2, n) array of image coordinates. In numpy
every step over them is a dozen calls of a few microseconds each; here each step is one
compiled loop:

- :func:`contrast`: each pixel's contrast (the fraction of the light it blocks) and its
  noise variance;
- (:mod:`tracker.vision.pixel_graph`: the geodesic distance of every pixel from the base
  along the mask;)
- :func:`centreline`: the centreline samples (contrast-weighted means per distance bin);
- :func:`bands`: the radio-opaque bands (8-connected groups of dark pixels), their
  centroids, covariances and distances from the base;
- :func:`sample_counts`: the pixels per centreline sample, for the self-overlap check;
- :func:`ends`: the base and the tip at sub-pixel precision (the mass beyond an end cut);
- :func:`extent_beyond`: the box of the far end;
- :func:`tip_tangent`: the search of the catheter's 3-D tangent at the tip over a few
  hundred directions (:mod:`tracker.vision.pair`).

The arithmetic of each pixel is written as the numpy steps it replaces did it (same
operations in the same order), so per-pixel values and the decisions taken on them are the
same; only sums over pixels that numpy left to BLAS may differ in the last bits (their
order; histograms are summed in pixel order, as np.bincount does).

Every kernel is ``njit(cache=True, nogil=True)``: compiled once to the ``__pycache__`` next
to this file, loaded from there afterwards, and free of the GIL (the views of a rig may run
in threads). :func:`warm_up` compiles (or loads) them all on a tiny input, so that no frame
of the live loop waits for the compiler; the segmenters call it when they are made. The
kernels take and return plain arrays of fixed dtypes (given in each docstring): another
dtype or layout would compile a second version on first use.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from tracker.vision import pixel_graph, shift_kernels


# ------------------------------------------------------------------------------ contrast
@numba.njit(cache=True, nogil=True)
def contrast(image, background, lut, dark_gray, sigma_gray, ys, xs, x0, y0):
    """Each pixel's contrast, its variance and its image coordinates.

    Parameters
    ----------
    image, background : uint8 arrays (h, w)
    lut : float32 array (256,)
        The frame's tone curve ``f`` at every background gray level.
    dark_gray, sigma_gray : float
        The frame's black level and noise, gray levels.
    ys, xs : intp arrays (n,)
        The pixels, in the region whose corner is at column ``x0``, row ``y0`` (ints).

    Returns
    -------
    w : float64 (n,)
        ``max(f(b) - image, 0) / max(f(b) - dark, 1)``: the fraction of the light the pixel
        blocks.
    var_w : float64 (n,)
        ``(sigma / max(f(b) - dark, 1))^2``: its noise variance.
    xy : float64 (2, n)
        Image coordinates (x row, y row), px.
    """
    n = ys.size
    w = np.empty(n)
    var_w = np.empty(n)
    xy = np.empty((2, n))
    for i in range(n):
        y = y0 + ys[i]
        x = x0 + xs[i]
        lit = np.float64(lut[background[y, x]])
        bg = lit - dark_gray
        if bg < 1.0:
            bg = 1.0
        blocked = lit - np.float64(image[y, x])
        if blocked < 0.0:
            blocked = 0.0
        w[i] = blocked / bg
        v = sigma_gray / bg
        var_w[i] = v * v
        xy[0, i] = x
        xy[1, i] = y
    return w, var_w, xy


# ---------------------------------------------------------------------------- centreline
@numba.njit(cache=True, nogil=True)
def centreline(dist, xy, w, bin_px):
    """Centreline samples: contrast-weighted means of the pixels per distance bin.

    ``dist`` (float64 (n,), finite), ``xy`` (float64 (2, n)), ``w`` (float64 (n,)),
    ``bin_px`` (float). Returns each pixel's bin ``int(dist / bin_px)`` (intp (n,)) and the
    samples (float64 (3, m)): x, y and distance from the base, of the bins with a positive
    weight, in order.
    """
    n = dist.size
    bins = np.empty(n, np.intp)
    m = 0
    for i in range(n):
        b = int(dist[i] / bin_px)
        bins[i] = b
        if b + 1 > m:
            m = b + 1
    sums = np.zeros((4, m))  # weight, weighted x, y and distance
    for i in range(n):
        b = bins[i]
        sums[0, b] += w[i]
        sums[1, b] += xy[0, i] * w[i]
        sums[2, b] += xy[1, i] * w[i]
        sums[3, b] += w[i] * dist[i]
    kept = 0
    for b in range(m):
        if sums[0, b] > 0:
            kept += 1
    line = np.empty((3, kept))
    j = 0
    for b in range(m):
        if sums[0, b] > 0:
            for r in range(3):
                line[r, j] = sums[r + 1, b] / sums[0, b]
            j += 1
    return bins, line


@numba.njit(cache=True, nogil=True)
def extent_beyond(xy, dist, d_min):
    """The box (x_lo, y_lo, x_hi, y_hi) of the pixels at ``dist >= d_min`` (float64 (2, n),
    float64 (n,), float; there must be some)."""
    x_lo = y_lo = np.inf
    x_hi = y_hi = -np.inf
    for i in range(dist.size):
        if dist[i] >= d_min:
            x_lo = min(x_lo, xy[0, i])
            x_hi = max(x_hi, xy[0, i])
            y_lo = min(y_lo, xy[1, i])
            y_hi = max(y_hi, xy[1, i])
    return x_lo, y_lo, x_hi, y_hi


@numba.njit(cache=True, nogil=True)
def _select(values, k):
    """The k-th smallest of a float64 array (NaN-free), which it reorders (quickselect:
    what np.partition gives at k)."""
    lo = 0
    hi = values.size - 1
    while lo < hi:
        pivot = values[(lo + hi) >> 1]
        i = lo
        j = hi
        while i <= j:
            while values[i] < pivot:
                i += 1
            while values[j] > pivot:
                j -= 1
            if i <= j:
                values[i], values[j] = values[j], values[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return values[k]


@numba.njit(cache=True, nogil=True)
def _median(values):
    """The median of a non-empty float64 array (sorted in place)."""
    values.sort()
    n = values.size
    return 0.5 * (values[(n - 1) // 2] + values[n // 2])


@numba.njit(cache=True, nogil=True)
def sample_counts(bins, n_bins, along, bin_px):
    """Pixels per centreline sample, and their median, for the self-overlap check.

    ``bins``: each pixel's sample (intp (n,)), at least ``n_bins`` of them. The samples of
    each band (from ``along[k, 1]`` to ``along[k, 2]`` px from the base, float64 (k, 3) as
    :func:`bands` gives them; a band seen end-on is a disc wider than the tube) and one more
    on either side, and the two samples at each end of the centreline, count 0. Returns the
    counts (float64) and the median of those above 0 (NaN when fewer than 3 are).
    """
    for i in range(bins.size):
        n_bins = max(n_bins, bins[i] + 1)
    count = np.zeros(n_bins)
    for i in range(bins.size):
        count[bins[i]] += 1.0
    for k in range(along.shape[0]):
        lo = max(int(along[k, 1] / bin_px) - 1, 0)
        hi = min(int(along[k, 2] / bin_px) + 2, n_bins)
        count[lo:hi] = 0.0
    count[:2] = 0.0
    count[max(n_bins - 2, 0) :] = 0.0
    kept = count[count > 0]
    if kept.size < 3:
        return count, np.nan
    return count, _median(kept)


# ----------------------------------------------------------------------------------- bands
@numba.njit(cache=True, nogil=True)
def _root(parent, i):
    """The root of i in the union-find forest ``parent``, halving the path on the way."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@numba.njit(cache=True, nogil=True)
def bands(index, ys, xs, w, var_w, dist, band_contrast, min_area, x0, y0):
    """The radio-opaque bands: 8-connected groups of pixels with ``w >= band_contrast``.

    Connected in the image, not along the geodesic distance (where the catheter hooks back,
    two bands can lie at the same distance from the base).

    Parameters
    ----------
    index : int32 array (h + 2, w + 2)
        :func:`pixel_graph.pixel_index` of the pixels ``ys``, ``xs`` (intp (n,)).
    w, var_w, dist : float64 arrays (n,)
        Contrast, its variance, geodesic distance from the base.
    band_contrast : float
    min_area : int
        Smaller groups are left out.
    x0, y0 : int
        The region's corner in the image.

    Returns
    -------
    label : int64 (n,)
        Each pixel's band (-1: none), bands numbered in order of ``d`` (the first of equal
        ones the first found in row-major order).
    centres : float64 (k, 2)
        Centroids weighted by the contrast beyond ``band_contrast``, image px.
    covs : float64 (k, 2, 2)
        Their covariances ``sum(var (p - c)(p - c)^T) / W^2`` (the contrast's noise through
        the centroid), px^2.
    along : float64 (k, 3)
        Distances from the base: weighted mean ``d``, least and greatest, px.
    """
    n = ys.size
    # Union-find over the band pixels, looking back at the four neighbours already seen.
    parent = np.arange(n)
    for i in range(n):
        if not w[i] >= band_contrast:
            continue
        row = ys[i] + 1
        col = xs[i] + 1
        for dy, dx in ((-1, -1), (-1, 0), (-1, 1), (0, -1)):
            j = index[row + dy, col + dx]
            if j >= 0 and w[j] >= band_contrast:
                a = _root(parent, i)
                b = _root(parent, j)
                if a != b:
                    parent[max(a, b)] = min(a, b)
    # Groups numbered by their first pixel; per group the sums of the contrast beyond the
    # threshold (W, Wx, Wy, Wd) and of the variance (V, Vx, Vy, Vxx, Vxy, Vyy).
    group = np.full(n, -1, np.int64)
    n_groups = 0
    for i in range(n):
        if w[i] >= band_contrast:
            r = _root(parent, i)
            if group[r] < 0:
                group[r] = n_groups
                n_groups += 1
            group[i] = group[r]
    size = np.zeros(n_groups, np.int64)
    sums = np.zeros((n_groups, 10))
    d_lo = np.full(n_groups, np.inf)
    d_hi = np.full(n_groups, -np.inf)
    for i in range(n):
        g = group[i]
        if g < 0:
            continue
        bx = np.float64(xs[i])
        by = np.float64(ys[i])
        c = w[i] - band_contrast
        v = var_w[i]
        size[g] += 1
        sums[g, 0] += c
        sums[g, 1] += c * bx
        sums[g, 2] += c * by
        sums[g, 3] += c * dist[i]
        sums[g, 4] += v
        sums[g, 5] += v * bx
        sums[g, 6] += v * by
        sums[g, 7] += v * np.float64(xs[i] * xs[i])
        sums[g, 8] += v * np.float64(xs[i] * ys[i])
        sums[g, 9] += v * np.float64(ys[i] * ys[i])
        d_lo[g] = min(d_lo[g], dist[i])
        d_hi[g] = max(d_hi[g], dist[i])
    kept = np.flatnonzero(size >= min_area)
    k = kept.size
    centres = np.empty((k, 2))
    covs = np.empty((k, 2, 2))
    along = np.empty((k, 3))
    for j in range(k):
        W, Wx, Wy, Wd, V, Vx, Vy, Vxx, Vxy, Vyy = sums[kept[j]]
        safe = W if W > 0 else 1.0
        cx = Wx / safe
        cy = Wy / safe
        along[j, 0] = Wd / safe
        safe = W * W if W > 0 else 1.0
        cov_xy = (Vxy - cx * Vy - cy * Vx + cx * cy * V) / safe
        centres[j, 0] = cx + x0
        centres[j, 1] = cy + y0
        covs[j, 0, 0] = (Vxx - 2.0 * cx * Vx + cx * cx * V) / safe
        covs[j, 0, 1] = cov_xy
        covs[j, 1, 0] = cov_xy
        covs[j, 1, 1] = (Vyy - 2.0 * cy * Vy + cy * cy * V) / safe
        along[j, 1] = d_lo[kept[j]]
        along[j, 2] = d_hi[kept[j]]
    # In order along the catheter (a stable sort: equal distances keep the order found).
    order = np.argsort(along[:, 0], kind="mergesort")
    rank = np.full(n_groups, -1, np.int64)
    for j in range(k):
        rank[kept[order[j]]] = j
    label = np.full(n, -1, np.int64)
    for i in range(n):
        if group[i] >= 0:
            label[i] = rank[group[i]]
    return label, centres[order], covs[order], along[order]


# ------------------------------------------------------------------------------------ ends
END_FIELDS = 11
"""A row of :func:`ends`: the end (x, y), its covariance (xx, xy, yx, yy), the unit
direction toward it (x, y), its distance past the cut, the tube's image radius and its
contrast per unit length; all NaN when there is no end."""


@numba.njit(cache=True, nogil=True)
def _end_mass(xy, w, var_w, dist, at_tip, d_limit, cut_x, cut_y, reach_sq, dx, dy, slab):
    """The contrast beyond an end cut and in the slab behind it, with their noise.

    The pixels taken are those on the end's side of the distance ``d_limit`` (``dist >=``
    it at the tip, ``<=`` at the base) within ``sqrt(reach_sq)`` of the cut (cut_x, cut_y).
    Each counts with the fraction of its footprint (extent ``|dx| + |dy|`` along the unit
    direction (dx, dy) toward the end) past the cut, ``p0``, and in the slab
    ``[-slab, 0]`` behind it, ``p1``.

    Returns ``sum p0 w``, ``sum p1 w``, ``sum p0 p0 var``, ``sum p0 p1 var``,
    ``sum p1 p1 var`` and the 90th percentile of the pixels' contrast (the plateau, robust
    to noise; NaN with no pixels).
    """
    n = dist.size
    span = abs(dx) + abs(dy)
    taken = np.empty(n)
    m = 0
    mass = behind = s00 = s01 = s11 = 0.0
    for i in range(n):
        if at_tip:
            if not dist[i] >= d_limit:
                continue
        elif not dist[i] <= d_limit:
            continue
        rx = xy[0, i] - cut_x
        ry = xy[1, i] - cut_y
        if not rx * rx + ry * ry <= reach_sq:
            continue
        t = dx * rx + dy * ry
        p0 = min(max(t / span + 0.5, 0.0), 1.0)
        p1 = min(max((t + slab) / span + 0.5, 0.0), 1.0) - p0
        mass += p0 * w[i]
        behind += p1 * w[i]
        v = var_w[i]
        s00 += p0 * v * p0
        s01 += p0 * v * p1
        s11 += p1 * v * p1
        taken[m] = w[i]
        m += 1
    plateau = np.nan
    if m > 0:
        plateau = _select(taken[:m], int(0.9 * (m - 1)))
    return mass, behind, s00, s01, s11, plateau


@numba.njit(cache=True, nogil=True)
def _end(out, xy, w, var_w, dist, label, band, band_cov, d_cut, cut_x, cut_y, samples,
         at_tip, step, end_slab_px, direction_sigma):
    """One end of the centreline into ``out`` (a row of :func:`ends`, left NaN if none).

    The end lies past the cut (cut_x, cut_y), ``d_cut`` from the base, by mass
    conservation: the pixels past it carry ``M = e m`` of contrast, with m the mass per unit
    length measured on a slab behind the cut, so ``e = M / m`` (pixels straddling the cut
    count with the fraction of their footprint on each side). ``samples`` (p0x, p0y, p1x,
    p1y) are the centreline one and two band-lengths back from the cut; ``band`` the end
    band's number (-1: none) and ``band_cov`` its centroid's covariance (2, 2).
    """
    p0x, p0y, p1x, p1y = samples
    dx = 3.0 * cut_x - 4.0 * p0x + p1x  # toward the end in both cases
    dy = 3.0 * cut_y - 4.0 * p0y + p1y
    norm = math.hypot(dx, dy)
    if norm < 1e-9:
        return
    dx, dy = dx / norm, dy / norm
    slab = end_slab_px
    if band >= 0:
        # The slab reaches back to where the band starts, at least half a pixel.
        least = np.inf
        for i in range(label.size):
            if label[i] == band:
                least = min(least, dx * xy[0, i] + dy * xy[1, i])
        slab = min(max(-(least - (cut_x * dx + cut_y * dy)), 0.5), end_slab_px)
    reach = 3.0 * step + slab
    d_limit = (d_cut - slab - step) if at_tip else (d_cut + slab + step)
    mass, behind, s00, s01, s11, contrast = _end_mass(
        xy, w, var_w, dist, at_tip, d_limit, cut_x, cut_y, reach * reach, dx, dy, slab
    )
    m_per_px = behind / slab
    if not m_per_px > 0:
        return
    e = mass / m_per_px
    # The noise of e through its gradient a p0 + b p1 over the pixels.
    a, b = 1.0 / m_per_px, -e / (m_per_px * slab)
    var_e = a * a * s00 + 2.0 * a * b * s01 + b * b * s11
    # The end disc of a tube seen obliquely sticks out past the end point by up to pi/4 of
    # the radius (m / 2 per unit contrast); half of that is the uncertainty of a single
    # view (the pair's tip from both views removes it).
    radius_px = 0.5 * m_per_px / max(contrast, 1e-6)
    var_e = var_e + (math.pi / 8.0 * radius_px) ** 2
    # Across: the end moves sideways with the direction's error.
    var_across = (e * direction_sigma) ** 2
    dxx, dxy, dyy = dx * dx, dx * dy, dy * dy
    out[0] = cut_x + e * dx
    out[1] = cut_y + e * dy
    out[2] = band_cov[0, 0] + var_e * dxx + var_across * (1.0 - dxx)
    out[3] = band_cov[0, 1] + var_e * dxy - var_across * dxy
    out[4] = band_cov[1, 0] + var_e * dxy - var_across * dxy
    out[5] = band_cov[1, 1] + var_e * dyy + var_across * (1.0 - dyy)
    out[6] = dx
    out[7] = dy
    out[8] = e
    out[9] = radius_px
    out[10] = m_per_px


@numba.njit(cache=True, nogil=True)
def ends(xy, w, var_w, dist, line, label, centres, covs, along, base_band, tip_band, D,
         bin_px, end_slab_px, direction_sigma):
    """The base and the tip end of the centreline, at sub-pixel precision.

    The cut at an end is the end band's centroid, or without a band the centreline two
    bins from the end; the direction there is the centreline's tangent from a second-order
    one-sided difference of samples one and two band-lengths back (samples right at an end
    are skewed: the end's far corner is geodesically farthest).

    Parameters
    ----------
    xy, w, var_w, dist : the pixels (float64 (2, n), (n,), (n,), (n,))
    line : float64 (3, m)
        The centreline samples (:func:`centreline`).
    label, centres, covs, along : the bands (:func:`bands`)
    base_band, tip_band : int
        The end bands' numbers, -1 for none.
    D : float
        The largest distance from the base, px.
    bin_px, end_slab_px, direction_sigma : float
        The settings ``bin_px``, ``end_slab_px`` and ``tip_direction_sigma_rad``.

    Returns
    -------
    float64 (2, END_FIELDS)
        The base's row and the tip's (:data:`END_FIELDS`).
    """
    out = np.full((2, END_FIELDS), np.nan)
    if line.shape[1] < 4:
        return out
    step = 2.0 * bin_px
    no_cov = np.zeros((2, 2))
    samples = np.empty(4)
    for end in range(2):
        at_tip = end == 1
        band = tip_band if at_tip else base_band
        sign = -1.0 if at_tip else 1.0
        if band >= 0:
            d_cut = along[band, 0]
            cut_x, cut_y = centres[band, 0], centres[band, 1]
            band_cov = covs[band]
        else:
            d_cut = D - step if at_tip else step
            cut_x = np.interp(d_cut, line[2], line[0])
            cut_y = np.interp(d_cut, line[2], line[1])
            band_cov = no_cov
        for k in range(2):
            d = d_cut + sign * step if k == 0 else d_cut + sign * (2.0 * step)
            samples[2 * k] = np.interp(d, line[2], line[0])
            samples[2 * k + 1] = np.interp(d, line[2], line[1])
        _end(out[end], xy, w, var_w, dist, label, band, band_cov, d_cut, cut_x, cut_y,
             samples, at_tip, step, end_slab_px, direction_sigma)
    return out


# ------------------------------------------------------------------------------ pair: tip
@numba.njit(cache=True, nogil=True)
def _tangent_costs(linear, extent, cap_px, directions, costs):
    """The misfit of :func:`tip_tangent` for each column of ``directions`` (3, k) into
    ``costs`` (k,)."""
    n = extent.size
    for j in range(directions.shape[1]):
        tx, ty, tz = directions[0, j], directions[1, j], directions[2, j]
        total = 0.0
        for k in range(n):
            px = linear[k, 0] * tx + linear[k, 1] * ty + linear[k, 2] * tz
            r = n + k
            py = linear[r, 0] * tx + linear[r, 1] * ty + linear[r, 2] * tz
            r += n
            along = linear[r, 0] * tx + linear[r, 1] * ty + linear[r, 2] * tz
            r += n
            sin_a = linear[r, 0] * tx + linear[r, 1] * ty + linear[r, 2] * tz
            # |p|^2 - along^2 is p's offset across the measured direction, squared; the end
            # disc adds to the extent along it whatever that is.
            r_along = extent[k] - along - cap_px[k] * abs(sin_a)
            total += px * px + py * py - along * along + r_along * r_along
        costs[j] = total


@numba.njit(cache=True, nogil=True)
def tip_tangent(linear, extent, cap_px, coarse, cap):
    """The unit 3-D tangent at the tip band that best explains every view's far end.

    Parameters
    ----------
    linear : float64 (4 n, 3)
        For n views, rows of linear maps of a direction t: per view (in blocks of n rows)
        the image vector ``p`` of half a band along t (x, then y), p's part along the
        measured image direction, and ``sin a`` (t's part along the viewing ray).
    extent, cap_px : float64 (n,)
        How far each view's image reaches past the band's centroid, and the end disc's
        largest stick-out (pi/4 of the tube's image radius), px.
    coarse : float64 (3, k)
        Directions over the sphere...
    cap : float64 (3, m)
        ...and a cap of finer ones around +z, turned onto the best coarse one, then shrunk
        five times and turned onto the best of those.

    Returns the best direction (float64 (3,)) and its misfit: the sum over the views of
    p's offset across the measured direction squared plus the squared error of the extent,
    ``extent - p . direction - cap_px |sin a|`` (px^2).
    """
    costs = np.empty(coarse.shape[1])
    _tangent_costs(linear, extent, cap_px, coarse, costs)
    t = coarse[:, np.argmin(costs)].copy()
    cost = 0.0
    # The cap around the best coarse direction, then the cap shrunk five times around the
    # best of those (its directions 3 degrees apart would leave the tip, half a band away,
    # up to 0.08 px off across the catheter).
    for scale in (1.0, 0.2):
        t, cost = _best_in_cap(linear, extent, cap_px, cap, t, scale)
    return t, cost


@numba.njit(cache=True, nogil=True)
def _best_in_cap(linear, extent, cap_px, cap, t, scale):
    """The best direction of :func:`tip_tangent` among those of ``cap`` (around +z), its
    angles from +z scaled by ``scale``, turned so that +z goes to ``t``; and its misfit."""
    # The cap turned so that +z goes to t: columns u, t x u, t.
    e = (1.0, 0.0, 0.0) if abs(t[0]) < 0.9 else (0.0, 1.0, 0.0)
    u = np.array([t[1] * e[2] - t[2] * e[1], t[2] * e[0] - t[0] * e[2], t[0] * e[1] - t[1] * e[0]])
    u /= math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
    v = np.array([t[1] * u[2] - t[2] * u[1], t[2] * u[0] - t[0] * u[2], t[0] * u[1] - t[1] * u[0]])
    fine = np.empty(cap.shape)
    for j in range(cap.shape[1]):
        a = scale * cap[0, j]
        b = scale * cap[1, j]
        c = math.sqrt(max(1.0 - a * a - b * b, 0.0))
        for r in range(3):
            fine[r, j] = u[r] * a + v[r] * b + t[r] * c
    costs = np.empty(cap.shape[1])
    _tangent_costs(linear, extent, cap_px, fine, costs)
    k = np.argmin(costs)
    return fine[:, k].copy(), costs[k]


# ---------------------------------------------------------------------------- warm-up
def warm_up() -> None:
    """Compile every kernel of the segmentation (here, in :mod:`tracker.vision.pixel_graph`,
    :mod:`tracker.vision.photometry_kernels` and :mod:`tracker.vision.shift_kernels`), or
    load it from the cache, on a tiny input with the argument types the segmentation passes,
    so that the first frame does not wait for it."""
    ys, xs, xy, index, dist = pixel_graph.warm_up()
    background = np.full(index.shape, 200, np.uint8)
    image = background - 160
    lut = np.arange(256, dtype=np.float32)
    w, var_w, _ = contrast(image, background, lut, 0.0, 1.0, ys, xs, 1, 1)
    bins, line = centreline(dist, xy, w, 1.0)
    extent_beyond(xy, dist, 1.0)
    label, centres, covs, along = bands(index, ys, xs, w, var_w, dist, 0.6, 1, 0, 0)
    sample_counts(bins, int(bins.max()) + 1, along, 1.0)
    # The base with a band, the tip without.
    ends(xy, w, var_w, dist, line, label, centres, covs, along, 0, -1, float(dist.max()),
         1.0, 2.0, 0.05)
    # Here, not at the top: photometry_kernels takes _select from this module.
    from tracker.vision import photometry_kernels

    photometry_kernels.warm_up()
    shift_kernels.warm_up()
    directions = np.eye(3)
    tip_tangent(np.ones((8, 3)), np.ones(2), np.ones(2), directions, directions)
