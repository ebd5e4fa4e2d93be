"""Where the catheter's pixels are in a frame (docs/vision.md section 4).

The foreground is ``f(background) - image > max(threshold_sigma x sigma', min_threshold_gray)``
with ``f`` the frame's tone curve (:mod:`tracker.vision.photometry`) and both images smoothed
(sigma' the noise after the smoothing): the whole image at half resolution
(:func:`coarse_region`), then the region found there, or around predicted points
(:func:`search_box`), at full resolution (:func:`foreground`, :func:`find_in_box`). The
catheter is the blob nearest the registered base and the blobs within ``max_gap_px`` of it
(:func:`pick_blobs`). Regions are ``(x0, y0, x1, y1)`` boxes in the image, px.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from tracker.vision.photometry import Photometry
from tracker.vision.settings import SegmentationSettings

Array = np.ndarray
Box = tuple[int, int, int, int]

_SMOOTHED_NOISE = 0.375  # standard deviation of white noise after the 3 x 3 Gaussian
_COARSE_NOISE = 0.1875  # ... after halving the resolution (2 x 2 means) and that Gaussian


def smooth_for_detection(image: Array) -> Array:
    """The image as the detection sees it: a 3 x 3 Gaussian ([1 2 1] / 4 each way). The
    tube (4 px wide or more) keeps its contrast, white noise drops to 0.375 of itself."""
    return cv2.GaussianBlur(image, (3, 3), 0)


def half_resolution(image: Array) -> Array:
    """The image at half resolution (means of 2 x 2 pixels), smoothed
    (:func:`smooth_for_detection`): white noise drops to 0.19 of itself, the tube (2 px
    wide or more at half resolution) keeps most of its contrast."""
    height, width = image.shape
    return smooth_for_detection(
        cv2.resize(image, (width // 2, height // 2), interpolation=cv2.INTER_AREA)
    )


def detection_backgrounds(background: Array) -> tuple[Array, Array]:
    """The background as the detection compares frames with it: smoothed
    (:func:`smooth_for_detection`) and at half resolution (:func:`half_resolution`, the
    search of the whole image)."""
    return smooth_for_detection(background), half_resolution(background)


def _below_table(lut: Array, threshold: float) -> Array:
    """``ceil(f(b) - threshold)`` at every background gray level b, saturated to 8 bits: for
    integer gray levels, ``image < f(b) - threshold`` is ``image < ceil(f(b) - threshold)``,
    one table lookup and one comparison."""
    table = lut - threshold
    np.ceil(table, out=table)
    np.minimum(table, 255, out=table)
    np.maximum(table, 0, out=table)
    return table.astype(np.uint8)


def search_box(points_px: Array, pad_px: float, shape: tuple[int, int]) -> Box:
    """The region ``(x0, y0, x1, y1)`` around image points, padded and clipped to the image.

    Non-finite points are left out; with none left (or ``pad_px <= 0``), the whole image.
    """
    height, width = shape
    whole = (0, 0, width, height)
    points = np.asarray(points_px, float).reshape(-1, 2)
    if points.size == 0 or pad_px <= 0:
        return whole
    lo, hi = points.min(axis=0), points.max(axis=0)
    if not np.isfinite(lo + hi).all():  # some points are not: leave them out
        points = points[np.isfinite(points).all(axis=1)]
        if points.size == 0:
            return whole
        lo, hi = points.min(axis=0), points.max(axis=0)
    (x_lo, y_lo), (x_hi, y_hi) = lo.tolist(), hi.tolist()
    box = (max(math.floor(x_lo - pad_px), 0), max(math.floor(y_lo - pad_px), 0),
           min(math.ceil(x_hi + pad_px) + 1, width), min(math.ceil(y_hi + pad_px) + 1, height))
    if box[2] - box[0] < 2 or box[3] - box[1] < 2:
        return whole
    return box


def coarse_region(
    image: Array,
    coarse_background: Array,
    photometry: Photometry,
    base_px: Array | None,
    settings: SegmentationSettings,
) -> tuple[Box, bool] | None:
    """The region ``(x0, y0, x1, y1)`` of the catheter's blobs found in the whole image at
    half resolution, with a margin of 4 px, and whether they pass near the base; None if
    there are none. (The smoother half-resolution image's blobs reach at least as far as
    the full resolution's.)"""
    s = settings
    threshold = max(
        s.threshold_sigma * _COARSE_NOISE * photometry.sigma_gray, s.min_threshold_gray
    )
    below = _below_table(photometry.lut, threshold)
    mask = cv2.compare(half_resolution(image), cv2.LUT(coarse_background, below), cv2.CMP_LT)
    base = None if base_px is None else (0.5 * float(base_px[0]), 0.5 * float(base_px[1]))
    picked = pick_blobs(mask, base, settings, scale=0.5)
    if picked is None:
        return None
    height, width = image.shape
    (x0, y0, x1, y1), base_ok = picked
    box = (max(2 * x0 - 4, 0), max(2 * y0 - 4, 0), min(2 * x1 + 4, width),
           min(2 * y1 + 4, height))
    return box, base_ok


def foreground(
    image: Array,
    smoothed_background: Array,
    photometry: Photometry,
    box: Box,
    settings: SegmentationSettings,
) -> Array:
    """The foreground in the box ``(x0, y0, x1, y1)``: ``f(background) - image >
    threshold``, both smoothed (:func:`smooth_for_detection`; ``f`` commutes with the
    smoothing to far below a gray level for a smooth tone curve), by one table lookup and
    one comparison."""
    s = settings
    bx0, by0, bx1, by1 = box
    threshold = max(
        s.threshold_sigma * _SMOOTHED_NOISE * photometry.sigma_gray, s.min_threshold_gray
    )
    below = _below_table(photometry.lut, threshold)
    return cv2.compare(
        smooth_for_detection(image[by0:by1, bx0:bx1]),
        cv2.LUT(smoothed_background[by0:by1, bx0:bx1], below),
        cv2.CMP_LT,
    )


def find_in_box(
    image: Array,
    smoothed_background: Array,
    photometry: Photometry,
    box: Box,
    base_px: Array | None,
    settings: SegmentationSettings,
) -> tuple[Box, Array, bool] | None:
    """The catheter's region in the search box ``(x0, y0, x1, y1)`` (:func:`foreground`).

    Returns ``(x0, y0, x1, y1)`` in the image, its foreground mask and whether the
    catheter passes near the base; None when there is nothing, or, for a box smaller than
    the image, when the catheter misses the base or comes within 3 px of the box's edge
    (it may run on outside).
    """
    bx0, by0, bx1, by1 = box
    mask = foreground(image, smoothed_background, photometry, box, settings)
    if base_px is not None:
        base_px = (float(base_px[0]) - bx0, float(base_px[1]) - by0)
    picked = pick_blobs(mask, base_px, settings)
    if picked is None:
        return None
    (x0, y0, x1, y1), base_ok = picked
    height, width = image.shape
    if (bx1 - bx0, by1 - by0) != (width, height):
        inner = (x0 > 0 or bx0 == 0, y0 > 0 or by0 == 0,
                 x1 < mask.shape[1] or bx1 == width, y1 < mask.shape[0] or by1 == height)
        if not (all(inner) and base_ok):
            return None
    return (x0 + bx0, y0 + by0, x1 + bx0, y1 + by0), mask[y0:y1, x0:x1], base_ok


def pick_blobs(
    mask: Array,
    base_px: tuple[float, float] | None,
    settings: SegmentationSettings,
    scale: float = 1.0,
) -> tuple[Box, bool] | None:
    """The catheter's blob and the blobs near it: ROI (x0, y0, x1, y1), base found.

    ``base_px`` is the base in the mask's pixels; ``scale`` the mask's resolution relative
    to the image's (the settings' areas and distances are in image pixels).
    """
    s = settings
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    blobs = []
    for c in contours:
        # Pixel area of a blob from its boundary polygon (Pick's theorem).
        area = cv2.contourArea(c) + 0.5 * cv2.arcLength(c, True) + 1.0
        if area >= s.min_area_px * scale**2:
            blobs.append((area, c, cv2.boundingRect(c)))
    if not blobs:
        return None
    base_ok = False
    main = max(range(len(blobs)), key=lambda i: blobs[i][0])
    if base_px is not None and math.isfinite(base_px[0]) and math.isfinite(base_px[1]):
        dist = [-cv2.pointPolygonTest(c, base_px, True) for _, c, _ in blobs]
        nearest = min(range(len(dist)), key=dist.__getitem__)
        if dist[nearest] <= s.base_search_px * scale:
            main, base_ok = nearest, True
    x, y, w, h = blobs[main][2]
    box = [x, y, x + w, y + h]
    # Pieces within the gap distance (an occluder split the catheter), transitively.
    rest = [b[2] for i, b in enumerate(blobs) if i != main]
    grown = True
    while grown and rest:
        grown = False
        for r in list(rest):
            gx = max(r[0] - box[2], box[0] - (r[0] + r[2]), 0)
            gy = max(r[1] - box[3], box[1] - (r[1] + r[3]), 0)
            if math.hypot(gx, gy) <= s.max_gap_px * scale:
                box = [min(box[0], r[0]), min(box[1], r[1]),
                       max(box[2], r[0] + r[2]), max(box[3], r[1] + r[3])]
                rest.remove(r)
                grown = True
    height, width = mask.shape
    m = 3
    roi = (max(box[0] - m, 0), max(box[1] - m, 0), min(box[2] + m, width),
           min(box[3] + m, height))
    return roi, base_ok
