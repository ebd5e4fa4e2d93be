"""The sums of a frame's shift from its background, and the choice of the pixels they run
over, compiled (numba; docs/vision.md section 4).

- :func:`shift_sums`: the least-squares sums of the frame's registration to its background
  over some 30 000 chosen pixels (:func:`tracker.vision.photometry.fit_shift`, every frame);
- :func:`select_pixels`: the pixels of a band of rows whose gradient is above a threshold,
  with what the fit needs of them (:mod:`tracker.vision.shift_samples`, a stripe of the
  background model at a time);
- :func:`centred_gradients`: those gradients less their mean per gray level;
- :func:`mark_near_polyline`: the cells around the catheter that the fit leaves out
  (:func:`tracker.vision.shift_pixels.shift_grid_mask`, every frame).

As in :mod:`tracker.vision.kernels`: ``njit(cache=True, nogil=True)``, plain arrays of the
fixed dtypes given in each docstring, and :func:`warm_up` compiles (or loads) them all with
the argument types the segmentation passes.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def shift_sums(image, index, levels, gradient, cell, excluded, lut, gain, shift_x, shift_y,
               gate):
    """The sums of the frame's registration to its background on chosen pixels.

    Parameters
    ----------
    image : uint8 array (h w,)
        The frame, flat (row-major).
    index : int32 array (n,)
        The pixels' flat indices...
    levels : uint8 array (n,)
        ...the background there...
    gradient : float32 array (2, n)
        ...its smoothed gradient (x, y), gray levels per px...
    cell : int32 array (n,)
        ...and each pixel's cell in ``excluded`` (uint8, flat): pixels of cells not 0 are
        left out (the catheter and its surroundings).
    lut : float32 array (256,)
        The frame's tone curve.
    gain, shift_x, shift_y, gate : float
        The tone curve's slope, the shift so far (px) and the bound of the residual left by
        it (gray levels): pixels beyond it (the catheter, an occluder) take no part.

    Returns
    -------
    The number of pixels taken, the sum of their squared residuals left by the shift so
    far, the normal matrix of the gradients times the gain (G00, G01, G11) and those
    gradients times the residual ``image - lut[level]`` (two sums). Pixels black or
    saturated in either image are left out.
    """
    n = 0
    squares = g00 = g01 = g11 = b0 = b1 = 0.0
    sx = gain * shift_x
    sy = gain * shift_y
    for k in range(index.size):
        f = image[index[k]]
        b = levels[k]
        gx = np.float64(gradient[0, k])
        gy = np.float64(gradient[1, k])
        # frame(p) = f(bg(p - d)) ~ f(bg(p)) - f' grad(bg) . d
        residual = np.float64(f) - lut[b]
        left = residual + gx * sx + gy * sy
        # Every pixel summed with a weight of 0 or 1 rather than skipped: without branches
        # the loop runs in vector registers (fastmath's reassociation lets it; the sums
        # then differ from those in pixel order in the last bits only).
        use = ((excluded[cell[k]] == 0) & (f != 0) & (f != 255) & (b != 0) & (b != 255)
               & (abs(left) <= gate))
        w = 1.0 if use else 0.0
        n += use
        wx = w * gx
        wy = w * gy
        squares += w * left * left
        g00 += wx * gx
        g01 += wx * gy
        g11 += wy * gy
        b0 += wx * residual
        b1 += wy * residual
    # The gain taken out of the sums: the gradients times the gain.
    return n, squares, gain * gain * g00, gain * gain * g01, gain * gain * g11, gain * b0, gain * b1


@numba.njit(cache=True, nogil=True)
def select_pixels(image, y0, y1, smooth, derivative, border, threshold_sq, cell_px,
                  cells_width, sample, sample_stride):
    """The pixels of a band of rows whose gradient is strong, with what the shift's fit
    needs of them.

    The gradient is the correlation with ``derivative`` along one axis and ``smooth`` along
    the other (5 taps each, edges replicated), in float32.

    Parameters
    ----------
    image : uint8 array (h, w)
        The background (the rows beyond the band are read by the taps).
    y0, y1 : int
        The band: rows ``y0`` to ``y1 - 1``.
    smooth, derivative : float32 arrays (5,)
        The gradient's taps (a Gaussian and its derivative, gray levels per px).
    border : int
        Pixels this close to the image's border are not chosen (their taps reach past it).
    threshold_sq : float
        Pixels whose squared gradient magnitude exceeds it are chosen, (gray levels / px)^2.
    cell_px, cells_width : int
        The side of the cells of :func:`tracker.vision.shift_pixels.shift_grid_mask`, px,
        and their number per row of cells.
    sample : float32 array (ceil(h w / sample_stride),)
        Written: the squared magnitude (0 within ``border``) of every ``sample_stride``-th
        pixel of the band in row-major order of the whole image, for the next threshold.
    sample_stride : int

    Returns
    -------
    index : int32 (n,)
        The chosen pixels' flat indices in the image (row-major)...
    levels : uint8 (n,)
        ...the background there...
    gradient : float32 (2, n)
        ...the gradient (x, y)...
    cell : int32 (n,)
        ...and the cell of each.
    counts : float64 (256,)
        Per gray level of the background, the number of chosen pixels...
    sums : float64 (2, 256)
        ...and the sums of their gradients (x, y), for :func:`centred_gradients`.
    """
    height, width = image.shape
    s0, s1, s2, s3, s4 = smooth[0], smooth[1], smooth[2], smooth[3], smooth[4]
    d0, d1, d2, d3, d4 = derivative[0], derivative[1], derivative[2], derivative[3], derivative[4]
    # Room for every pixel of the band (few are chosen, and only their pages are touched):
    # arrays grown inside the loop would keep the compiler from optimising it.
    capacity = max(y1 - y0, 0) * width
    index = np.empty(capacity, np.int32)
    levels = np.empty(capacity, np.uint8)
    gradient = np.empty((2, capacity), np.float32)
    cell = np.empty(capacity, np.int32)
    # Each column's column of cells (an integer division per chosen pixel costs more than
    # the rest of its work).
    cell_column = np.empty(width, np.int32)
    q = r = 0
    for c in range(width):
        cell_column[c] = q
        r += 1
        if r == cell_px:
            q += 1
            r = 0
    counts = np.zeros(256)
    sums = np.zeros((2, 256))
    # Each row smoothed (vs) and differentiated (vd) across the rows, with two pixels of
    # replicated edge on either side, then the other way along the row (gx, gy): plain
    # loops over a row, which the compiler vectorises.
    vs = np.empty(width + 4, np.float32)
    vd = np.empty(width + 4, np.float32)
    gx = np.empty(width, np.float32)
    gy = np.empty(width, np.float32)
    m = np.empty(width, np.float32)
    last = height - 1
    threshold = np.float32(threshold_sq) if threshold_sq < 3e38 else np.float32(np.inf)
    n = 0
    for y in range(y0, y1):
        p0 = image[max(y - 2, 0)]
        p1 = image[max(y - 1, 0)]
        p2 = image[y]
        p3 = image[min(y + 1, last)]
        p4 = image[min(y + 2, last)]
        for c in range(width):
            a0 = np.float32(p0[c])
            a1 = np.float32(p1[c])
            a2 = np.float32(p2[c])
            a3 = np.float32(p3[c])
            a4 = np.float32(p4[c])
            vs[c + 2] = s0 * a0 + s1 * a1 + s2 * a2 + s3 * a3 + s4 * a4
            vd[c + 2] = d0 * a0 + d1 * a1 + d2 * a2 + d3 * a3 + d4 * a4
        vs[0] = vs[1] = vs[2]
        vd[0] = vd[1] = vd[2]
        vs[width + 2] = vs[width + 3] = vs[width + 1]
        vd[width + 2] = vd[width + 3] = vd[width + 1]
        for c in range(width):
            u = d0 * vs[c] + d1 * vs[c + 1] + d2 * vs[c + 2] + d3 * vs[c + 3] + d4 * vs[c + 4]
            v = s0 * vd[c] + s1 * vd[c + 1] + s2 * vd[c + 2] + s3 * vd[c + 3] + s4 * vd[c + 4]
            gx[c] = u
            gy[c] = v
            m[c] = u * u + v * v
        if border <= y < height - border:
            m[:border] = 0.0
            m[width - border:] = 0.0
        else:
            m[:] = 0.0
        base = y * width
        cell_row = (y // cell_px) * cells_width
        # The row's pixels in the threshold's sample: every sample_stride-th of the image.
        first = (-base) % sample_stride
        j = (base + first) // sample_stride
        for c in range(first, width, sample_stride):
            sample[j] = m[c]
            j += 1
        for c in range(width):
            if m[c] > threshold:
                b = p2[c]
                index[n] = base + c
                levels[n] = b
                gradient[0, n] = gx[c]
                gradient[1, n] = gy[c]
                cell[n] = cell_row + cell_column[c]
                counts[b] += 1.0
                sums[0, b] += gx[c]
                sums[1, b] += gy[c]
                n += 1
    return (index[:n].copy(), levels[:n].copy(), gradient[:, :n].copy(), cell[:n].copy(),
            counts, sums)


@numba.njit(cache=True, nogil=True)
def centred_gradients(levels, gradient, counts, sums):
    """Each gradient less the mean of the gradients of its gray level.

    ``levels`` (uint8 (n,)), ``gradient`` (float32 (2, n)); ``counts`` (float64 (256,)),
    ``sums`` (float64 (2, 256)): per gray level, the pixels and their gradients' sums.
    Returns float32 (2, n); the means are rounded to float32 before they are taken off.
    """
    means = np.empty((2, 256), np.float32)
    for b in range(256):
        count = max(counts[b], 1.0)
        means[0, b] = np.float32(sums[0, b] / count)
        means[1, b] = np.float32(sums[1, b] / count)
    out = np.empty_like(gradient)
    for k in range(levels.size):
        b = levels[k]
        out[0, k] = gradient[0, k] - means[0, b]
        out[1, k] = gradient[1, k] - means[1, b]
    return out


@numba.njit(cache=True, nogil=True)
def mark_near_polyline(mask, points, reach_px, cell_px):
    """Set to 1 the cells of ``mask`` whose centre is within ``reach_px`` of the polyline
    through the finite rows of ``points``.

    Parameters
    ----------
    mask : uint8 array (rows, columns)
        Cells of ``cell_px`` square: cell (i, j) holds the pixels from (j cell_px, i cell_px),
        its centre at ((j + 1/2) cell_px - 1/2, (i + 1/2) cell_px - 1/2), px.
    points : float array (n, 2)
        The polyline's vertices (x, y), px; rows that are not finite are left out (the
        polyline joins the others). A single vertex marks a disc.
    reach_px, cell_px : float
    """
    rows, columns = mask.shape
    n = 0
    finite = np.empty((points.shape[0], 2))
    for k in range(points.shape[0]):
        x, y = points[k, 0], points[k, 1]
        if np.isfinite(x) and np.isfinite(y):
            finite[n, 0] = x
            finite[n, 1] = y
            n += 1
    if n == 0:
        return
    reach2 = reach_px * reach_px
    half = 0.5 * cell_px - 0.5
    for k in range(max(n - 1, 1)):
        ax, ay = finite[k, 0], finite[k, 1]
        bx, by = finite[min(k + 1, n - 1), 0], finite[min(k + 1, n - 1), 1]
        dx, dy = bx - ax, by - ay
        length2 = dx * dx + dy * dy
        # The cells whose centre can be within reach: of the segment's box, widened.
        j0 = max(int(np.ceil((min(ax, bx) - reach_px - half) / cell_px)), 0)
        j1 = min(int(np.floor((max(ax, bx) + reach_px - half) / cell_px)), columns - 1)
        i0 = max(int(np.ceil((min(ay, by) - reach_px - half) / cell_px)), 0)
        i1 = min(int(np.floor((max(ay, by) + reach_px - half) / cell_px)), rows - 1)
        for i in range(i0, i1 + 1):
            cy = i * cell_px + half
            for j in range(j0, j1 + 1):
                cx = j * cell_px + half
                t = 0.0
                if length2 > 0.0:
                    t = min(max(((cx - ax) * dx + (cy - ay) * dy) / length2, 0.0), 1.0)
                ex = cx - ax - t * dx
                ey = cy - ay - t * dy
                if ex * ex + ey * ey <= reach2:
                    mask[i, j] = 1


def warm_up() -> None:
    """Compile (or load) this module's kernels on a tiny input, with the argument types the
    segmentation passes."""
    level = np.full((8, 8), 100, np.uint8)
    level[:, ::2] = 120
    taps = np.ones(5, np.float32)
    index, levels, gradient, cell, counts, sums = select_pixels(
        level, 0, 8, taps, taps, 1, 0.5, 4, 2, np.empty(10, np.float32), 7
    )
    gradient = centred_gradients(levels, gradient, counts, sums)
    lut = np.arange(256, dtype=np.float32)
    shift_sums(level.reshape(-1), index, levels, gradient, cell, np.zeros(4, np.uint8), lut,
               1.0, 0.0, 0.0, 8.0)
    mark_near_polyline(np.zeros((2, 2), np.uint8), np.zeros((2, 2)), 1.0, 4.0)
