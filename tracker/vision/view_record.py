"""Views' segmentations as one flat block of float64, and back: the segmentation worker's
answer (:mod:`tracker.vision.parallel`).

Pickling a :class:`ViewSegmentation` (some twenty arrays, a photometry, a flag) and reading
it back took 0.10-0.25 ms a side in the live loop, where it runs once a frame with cold
caches, on the frame's critical path. Here every field goes into its place in a block of
float64 with a few slice copies, and comes back the same: the same values, bit for bit
(float32 and bool survive float64 exactly), the same types and dtypes.

Layout of one view (``n`` markers, ``m`` centreline samples, ``k`` bands): the scalars
(:data:`_SCALARS`, ``n``, ``m`` and ``k`` among them), the fixed arrays (:data:`_FIXED`,
``(2,)`` and ``(2, 2)`` each), the photometry's shift and its covariance (6), the markers'
points, covariances and found flags (``7 n``), the tone curve (256), then the centreline
(``2 m``) and the bands (``2 k``). Views follow one another.
"""

from __future__ import annotations

import numpy as np

from tracker.vision.photometry import Photometry
from tracker.vision.segmentation import SegmentationFlag, ViewSegmentation

Array = np.ndarray

# flags, noise_sigma_gray, tip_extent_px, tube_radius_px, tip_width_ratio, n, m, k, then
# the photometry: 0 none, 1 without shift covariance, 2 with; sigma_gray, gain,
# clipped_fraction, fitted, dark_gray.
_SCALARS = 14
_FIXED = (
    ("base_px", 2), ("base_cov", 4), ("tip_px", 2), ("tip_cov", 4), ("tip_band_px", 2),
    ("tip_band_cov", 4), ("tip_direction", 2),
)  # fmt: skip
_FIXED_SIZE = sum(size for _, size in _FIXED)
_LUT = 256
_PHOTOMETRY_FIXED = 6  # shift_px (2), shift_cov_px2 (4)


def view_size(n_markers: int, centreline: int, bands: int) -> int:
    """The float64 a view takes in a block."""
    return (
        _SCALARS + _FIXED_SIZE + _PHOTOMETRY_FIXED + 7 * n_markers + _LUT
        + 2 * (centreline + bands)
    )  # fmt: skip


def write_views(block: Array, views) -> int:
    """Write ``views`` into ``block`` (float64, 1-D); the float64 written, or -1 when they
    do not fit (nothing to rely on is then in the block)."""
    at = 0
    for view in views:
        n = view.markers_found.shape[0]
        m, k = view.centreline_px.shape[0], view.bands_px.shape[0]
        end = at + view_size(n, m, k)
        if end > block.shape[0]:
            return -1
        p = view.photometry
        kind = 0 if p is None else (1 if p.shift_cov_px2 is None else 2)
        out = block[at:end]
        out[:_SCALARS] = (
            int(view.flags), view.noise_sigma_gray, view.tip_extent_px, view.tube_radius_px,
            view.tip_width_ratio, n, m, k, kind,
            *((0.0,) * 5 if p is None else (
                p.sigma_gray, p.gain, p.clipped_fraction, p.fitted, p.dark_gray,
            )),
        )  # fmt: skip
        i = _SCALARS
        for name, size in _FIXED:
            out[i : i + size] = getattr(view, name).reshape(-1)
            i += size
        if kind:
            out[i : i + 2] = p.shift_px
        if kind == 2:
            out[i + 2 : i + 6] = p.shift_cov_px2.reshape(-1)
        i += _PHOTOMETRY_FIXED
        out[i : i + 2 * n] = view.markers_px.reshape(-1)
        out[i + 2 * n : i + 6 * n] = view.markers_cov.reshape(-1)
        out[i + 6 * n : i + 7 * n] = view.markers_found
        i += 7 * n
        if kind:
            out[i : i + _LUT] = p.lut
        i += _LUT
        out[i : i + 2 * m] = view.centreline_px.reshape(-1)
        out[i + 2 * m : i + 2 * (m + k)] = view.bands_px.reshape(-1)
        at = end
    return at


def read_views(block: Array, count: int) -> tuple[ViewSegmentation, ...]:
    """The ``count`` views written at the start of ``block`` (copies: the block may be
    written again)."""
    views = []
    at = 0
    for _ in range(count):
        scalars = block[at : at + _SCALARS].tolist()
        n, m, k, kind = (int(v) for v in scalars[5:9])
        i = at + _SCALARS
        fixed = {}
        for name, size in _FIXED:
            part = block[i : i + size].copy()
            fixed[name] = part.reshape(2, 2) if size == 4 else part
            i += size
        shift = block[i : i + _PHOTOMETRY_FIXED].copy()
        i += _PHOTOMETRY_FIXED
        markers = block[i : i + 7 * n].copy()
        i += 7 * n
        photometry = None
        if kind:
            sigma_gray, gain, clipped, fitted, dark = scalars[9:14]
            photometry = Photometry(
                lut=block[i : i + _LUT].astype(np.float32),
                shift_px=shift[:2],
                sigma_gray=sigma_gray,
                gain=gain,
                clipped_fraction=clipped,
                fitted=bool(fitted),
                dark_gray=dark,
                shift_cov_px2=shift[2:].reshape(2, 2) if kind == 2 else None,
            )
        i += _LUT
        views.append(
            ViewSegmentation(
                flags=SegmentationFlag(int(scalars[0])),
                noise_sigma_gray=scalars[1],
                markers_px=markers[: 2 * n].reshape(n, 2),
                markers_cov=markers[2 * n : 6 * n].reshape(n, 2, 2),
                markers_found=markers[6 * n :] != 0.0,
                centreline_px=block[i : i + 2 * m].reshape(m, 2).copy(),
                bands_px=block[i + 2 * m : i + 2 * (m + k)].reshape(k, 2).copy(),
                tip_extent_px=scalars[2],
                tube_radius_px=scalars[3],
                tip_width_ratio=scalars[4],
                photometry=photometry,
                **fixed,
            )
        )
        at = i + 2 * (m + k)
    return tuple(views)
