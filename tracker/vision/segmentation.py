"""Marker segmentation: images -> the 2-D points the estimators consume (DESIGN.md sections 4, 6).

The paper's approach, per view (:class:`Segmenter`):

1. background subtraction against a prior image of the empty scene (the catheter is darker
   than the scene: ``diff = background - image``), with a per-frame noise estimate from the
   residual of the whole (mostly empty) image;
2. a threshold at a multiple of that noise, mask clean-up (closing, small blobs removed),
   and the catheter chosen as the blob nearest the registered base;
3. the centreline: mask pixels ordered by their geodesic distance from the base along the
   mask (a shortest-path sweep on the pixel graph; pieces of a catheter split by an occluder
   are joined across gaps up to ``max_gap_px``), sampled every ``bin_px``;
4. the radio-opaque bands (pixels blocking more than ``band_contrast`` of the light), ordered
   along the centreline and assigned to the base, to the catheter's markers and to the tip;
5. the base and the tip as the two ends of the centreline, at sub-pixel precision by mass
   conservation (the end lies ``mass beyond a cut / mass per unit length`` past the cut,
   which blur and anti-aliasing do not change), and the band centres as contrast-weighted
   centroids;
6. checks that the order along the catheter can be trusted: the far end must carry the tip
   band, must not run into the image border, and must be thinner than the base (the distal
   tube is); the mask must not touch or cross itself.

Then per synchronised pair (:func:`segment_pair`, :class:`PairSegmenter`), with the rig: an
epipolar check of every point found in both views, and the tip placed in 3-D from the tip
band's centre (unbiased in both views however the tip points) and the catheter's tangent,
which removes the bias of a single view's far end when the tip points toward a camera.

Every point comes with a covariance propagated from the per-frame noise estimate through the
centroid / end formulas (plus a small floor), and a flag saying what went wrong when a point
is missing. Bad input is either a flagged result (no catheter, the tip out of the image, a
hidden marker, a view where the catheter overlaps itself) or one ``ValueError`` / ``OSError``
(an image of the wrong size or type, an unreadable file), never a silent wrong point.

Points are in px (distorted pixels of the camera, as :class:`models.imaging.PinholeView`
expects them); :func:`frame_points` and :func:`segment_pair` map them onto the rows
``[tip, marker_0, ...]`` of :class:`tracker.types.Frame`. Thresholds are
:class:`SegmentationSettings`, read from the ``[segmentation]`` table of a TOML file
(docs/vision.md).
"""

from __future__ import annotations

import enum
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from models.catheter import Catheter
from models.imaging import BiplaneRig
from tracker.types import Frame

Array = np.ndarray

SETTINGS_FORMAT = "cathtrack-segmentation"


class SegmentationFlag(enum.IntFlag):
    """What went wrong in one view (0 when nothing did)."""

    NONE = 0
    NO_CATHETER = enum.auto()  # no blob large enough: every point is missing
    BASE_NOT_FOUND = enum.auto()  # nothing near the registered base: the base end was guessed
    TIP_NOT_FOUND = enum.auto()  # no tip band at the far end (hidden, or the catheter split)
    TIP_AT_BORDER = enum.auto()  # the centreline runs into the image border
    MARKER_MISSING = enum.auto()  # a marker band was not found (hidden or merged)
    EXTRA_BANDS = enum.auto()  # more dark bands than markers: the assignment is by position
    FRAGMENTED = enum.auto()  # the catheter mask was in pieces, joined across a gap
    NOISY = enum.auto()  # the frame's noise estimate is above max_noise_gray
    OVERLAP = enum.auto()  # the catheter touches, crosses or folds onto itself: points withheld


@dataclass(frozen=True)
class SegmentationSettings:
    """Tunable thresholds of the segmentation (TOML table ``[segmentation]``).

    Parameters
    ----------
    threshold_sigma : float
        Foreground if ``background - image`` exceeds this many noise standard deviations...
    min_threshold_gray : float
        ...and at least this many gray levels.
    band_contrast : float
        A pixel is part of a radio-opaque band if it blocks at least this fraction of the
        background light, ``(background - image) / background``; between the tube's and the
        bands' attenuation.
    band_length_mm : float
        Length of a marker band (used to predict where bands lie along the catheter).
    min_area_px, min_band_area_px : int
        Smallest catheter blob and smallest band, px.
    closing_px : int
        Side of the square closing kernel of the mask clean-up (0 or 1: none).
    max_gap_px : float
        Pieces of the catheter separated by at most this (an occluder) are joined.
    base_search_px : float
        The catheter must pass within this distance of the registered base.
    border_px : float
        A centreline end this close to the image border has left the image.
    bin_px : float
        Spacing of the centreline samples along the catheter.
    end_slab_px : float
        Longest slab behind an end cut used for the mass per unit length.
    sigma_floor_px : float
        Added in quadrature to every point's standard deviation (rendering and model errors
        the noise propagation does not see).
    max_noise_gray : float
        Frames noisier than this are flagged NOISY.
    noise_stride_px : int
        Stride of the pixel grid the noise is estimated on.
    overlap_ratio : float
        A part of the mask this many times thicker than the typical tube (largest
        inscribed disc), with 1.1 times this ratio more pixels per centreline sample, means
        the catheter touches or crosses itself in the view (the proximal tube is only about
        1.3 times the median in both).
    max_tip_width_ratio : float
        The tube at the tip band may be at most this fraction of its width at the base band
        (the distal segment is thinner: 0.89 / 1.2 = 0.74); a wider far end means the
        catheter folds back onto itself in the view. Set it above 1 for a catheter of one
        diameter.
    tip_band : bool
        The catheter has a radio-opaque band at the tip: the far end of the centreline is
        only taken as the tip when that band is there (otherwise: TIP_NOT_FOUND).
    epipolar_gate_px : float
        Pair check: a point's two rays may miss each other by at most this (or four
        standard deviations of the point, if more), as reprojection residual, px.
    tip_direction_sigma_rad : float
        Uncertainty of the catheter's direction at the tip band (the image direction for a
        single view's far end, the 3-D tangent when both views place the tip), rad.
    """

    threshold_sigma: float = 6.0
    min_threshold_gray: float = 10.0
    band_contrast: float = 0.6
    band_length_mm: float = 1.0
    min_area_px: int = 30
    min_band_area_px: int = 3
    closing_px: int = 3
    max_gap_px: float = 30.0
    base_search_px: float = 15.0
    border_px: float = 2.0
    bin_px: float = 3.0
    end_slab_px: float = 2.0
    sigma_floor_px: float = 0.05
    max_noise_gray: float = 20.0
    noise_stride_px: int = 8
    overlap_ratio: float = 1.45
    epipolar_gate_px: float = 3.0
    max_tip_width_ratio: float = 0.88
    tip_band: bool = True
    tip_direction_sigma_rad: float = 0.05

    def __post_init__(self) -> None:
        positive = (
            "threshold_sigma", "band_length_mm", "bin_px", "end_slab_px", "max_noise_gray",
            "base_search_px", "overlap_ratio", "epipolar_gate_px", "max_tip_width_ratio",
        )
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and np.isfinite(value) and value > 0):
                raise ValueError(f"segmentation setting {name} must be positive, got {value!r}")
        non_negative = (
            "min_threshold_gray", "max_gap_px", "border_px", "sigma_floor_px",
            "tip_direction_sigma_rad",
        )
        for name in non_negative:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and np.isfinite(value) and value >= 0):
                raise ValueError(f"segmentation setting {name} must be >= 0, got {value!r}")
        if not (isinstance(self.band_contrast, int | float) and 0 < self.band_contrast < 1):
            raise ValueError(
                "segmentation setting band_contrast must lie in (0, 1),"
                f" got {self.band_contrast!r}"
            )
        for name in ("min_area_px", "min_band_area_px", "closing_px", "noise_stride_px"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ValueError(
                    f"segmentation setting {name} must be an integer >= 0, got {value!r}"
                )
        if not isinstance(self.tip_band, bool):
            raise ValueError(
                f"segmentation setting tip_band must be true or false, got {self.tip_band!r}"
            )
        if self.noise_stride_px < 1:
            raise ValueError("segmentation setting noise_stride_px must be >= 1")


def segmentation_settings_from_dict(
    table: dict[str, Any], source: str = "settings"
) -> SegmentationSettings:
    """Settings from a parsed ``[segmentation]`` table; unknown keys are an error."""
    if not isinstance(table, dict):
        raise ValueError(f"{source}: [segmentation] must be a table")
    known = {f.name for f in fields(SegmentationSettings)}
    unknown = sorted(set(table) - known)
    if unknown:
        raise ValueError(
            f"{source}: unknown segmentation setting(s) {', '.join(unknown)};"
            f" known: {', '.join(sorted(known))}"
        )
    try:
        return SegmentationSettings(**table)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{source}: {exc}") from None


def load_segmentation_settings(path: str | Path) -> SegmentationSettings:
    """Read the ``[segmentation]`` table of a TOML settings file (defaults for missing keys)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"cannot read settings file {path}: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: malformed TOML: {exc}") from None
    fmt = data.get("format", SETTINGS_FORMAT)
    if fmt != SETTINGS_FORMAT:
        raise ValueError(f"{path}: 'format' must be \"{SETTINGS_FORMAT}\", got {fmt!r}")
    return segmentation_settings_from_dict(data.get("segmentation", {}), str(path))


# ----------------------------------------------------------------------------- image input
def read_grayscale(path: str | Path) -> Array:
    """An 8-bit grayscale image from a file, or one clear error (OSError) if unreadable."""
    path = Path(path)
    if not path.is_file():
        raise OSError(f"cannot read image {path}: no such file")
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise OSError(f"cannot read image {path}: not an image OpenCV can decode")
    return image


def check_image(image: Any, name: str = "image", shape: tuple[int, int] | None = None) -> Array:
    """An 8-bit single-channel image (h, w) of the expected shape, or a ValueError saying why."""
    if not isinstance(image, np.ndarray):
        raise ValueError(f"{name} must be a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise ValueError(f"{name} must be 8-bit (uint8) grayscale, got dtype {image.dtype}")
    if image.ndim != 2:
        raise ValueError(
            f"{name} must be a single-channel (h, w) grayscale image, got shape {image.shape}"
            " (convert colour images with cv2.cvtColor(..., cv2.COLOR_BGR2GRAY))"
        )
    if shape is not None and image.shape != tuple(shape):
        raise ValueError(
            f"{name} is {image.shape[1]}x{image.shape[0]} px, expected {shape[1]}x{shape[0]} px"
            " (the size of the background image / camera)"
        )
    return image


# ------------------------------------------------------------------------------- results
@dataclass(frozen=True)
class ViewSegmentation:
    """What one view shows, px.

    Attributes
    ----------
    flags : SegmentationFlag
    noise_sigma_gray : float
        Per-frame estimate of the image noise (background-subtracted), gray levels.
    base_px, tip_px : arrays (2,)
        Proximal and distal ends of the centreline (NaN if not found).
    base_cov, tip_cov : arrays (2, 2)
        Their covariances, px^2.
    markers_px : array (n_markers, 2)
        The catheter's markers in the order of ``marker_arclengths_mm`` (a marker at the tip
        is the tip point); NaN rows for markers not found.
    markers_cov : array (n_markers, 2, 2)
    markers_found : array (n_markers,) of bool
    centreline_px : array (m, 2)
        Centreline samples from the base to the tip.
    bands_px : array (k, 2)
        Centroids of every band found, in order along the catheter.
    tip_band_px, tip_band_cov : arrays (2,), (2, 2)
        Centroid of the band at the tip (the projection of its centre, unbiased however the
        tip points) and its covariance; NaN if not found.
    tip_direction : array (2,)
        Unit image direction of the catheter at the tip band, toward the tip.
    tip_extent_px : float
        How far the catheter's image reaches past the tip band's centroid along
        ``tip_direction`` (mass beyond the centroid / mass per unit length), px.
    tube_radius_px : float
        Radius of the distal tube in the image, px (mass per unit length / contrast / 2).
    tip_width_ratio : float
        Width of the tube at the tip band over that at the base band (about 0.89 / 1.2).
    """

    flags: SegmentationFlag
    noise_sigma_gray: float
    base_px: Array
    base_cov: Array
    tip_px: Array
    tip_cov: Array
    markers_px: Array
    markers_cov: Array
    markers_found: Array
    centreline_px: Array
    bands_px: Array
    tip_band_px: Array
    tip_band_cov: Array
    tip_direction: Array
    tip_extent_px: float = float("nan")
    tube_radius_px: float = float("nan")
    tip_width_ratio: float = float("nan")

    @property
    def tip_found(self) -> bool:
        return bool(np.all(np.isfinite(self.tip_px)))


def frame_points(seg: ViewSegmentation) -> tuple[Array, Array, Array]:
    """One view's segmentation as the rows ``[tip, marker_0, ...]`` of a pipeline Frame.

    Returns
    -------
    uv : array (1 + n_markers, 2)
        px, NaN rows for points not found.
    cov : array (1 + n_markers, 2, 2)
        px^2, from the per-frame noise estimate; NaN where the point is missing.
    found : array (1 + n_markers,) of bool
        The quality flag of each row.
    """
    uv = np.vstack([seg.tip_px[None], seg.markers_px])
    cov = np.concatenate([seg.tip_cov[None], seg.markers_cov])
    found = np.concatenate([[seg.tip_found], seg.markers_found])
    uv = np.where(found[:, None], uv, np.nan)
    cov = np.where(found[:, None, None], cov, np.nan)
    return uv, cov, found


# ---------------------------------------------------------------------------- the segmenter
def _noise_sigma(image: Array, background: Array, stride: int) -> float:
    """Robust standard deviation of image - background on a sparse grid, gray levels.

    The catheter covers a small part of the image: the median absolute difference ignores
    it (0.6745 sigma for Gaussian noise about the static prior), and the root mean square of
    the differences within four of those sigmas refines it. Integer differences: everything
    comes from one histogram.
    """
    o = stride // 2
    a = np.abs(image[o::stride, o::stride].astype(np.int16) - background[o::stride, o::stride])
    hist = np.bincount(a.ravel(), minlength=256)
    cdf = np.cumsum(hist)
    mad = float(np.searchsorted(cdf, 0.5 * cdf[-1]))
    clip = int(4.0 * max(1.4826 * mad, 1.0))
    h = hist[: clip + 1].astype(np.float64)
    v = np.arange(clip + 1, dtype=np.float64)
    n = h.sum()
    return float(np.sqrt((h @ v**2) / n)) if n > 10 else 1.4826 * mad


def _ends_cut(
    xy: Array,
    w: Array,
    var_w: Array,
    cut: Array,
    direction: Array,
    slab_px: float,
) -> tuple[float, float]:
    """Position of a tube's end past ``cut`` along ``direction`` by mass conservation.

    The pixels past the cut carry ``M = e m`` of contrast, with m the mass per unit length
    measured on the slab ``[-slab, 0]`` behind it, so the end lies at ``e = M / m`` (px).
    Pixels straddling the cut count with the fraction of their footprint on each side.
    Returns e, its variance from the pixel noise and m (contrast x px).
    """
    t = (xy - cut) @ direction
    lam = abs(direction[0]) + abs(direction[1])  # a pixel's extent along the direction
    beyond = np.minimum(np.maximum(t / lam + 0.5, 0.0), 1.0)
    slab = np.minimum(np.maximum((t + slab_px) / lam + 0.5, 0.0), 1.0) - beyond
    M = float(beyond @ w)
    m = float(slab @ w) / slab_px
    if not m > 0:
        return float("nan"), float("nan"), float("nan")
    e = M / m
    grad = beyond / m - e * slab / (m * slab_px)
    return e, float((grad**2) @ var_w), m


def _interpolate(points: Array, along: Array, at: Array) -> Array:
    """Points (m, 2) sampled at increasing ``along`` (m,), linearly interpolated at ``at`` (k,)."""
    return np.stack([np.interp(at, along, points[:, 0]), np.interp(at, along, points[:, 1])], -1)


def _weighted_centroid(xy: Array, w: Array, var_w: Array) -> tuple[Array, Array]:
    W = float(w.sum())
    c = (w @ xy) / W
    d = xy - c
    cov = (d * var_w[:, None]).T @ d / W**2
    return c, cov


class Segmenter:
    """Segments one view of one catheter model.

    Parameters
    ----------
    catheter : Catheter
        Gives the markers (their arclengths, in order) and the length: every marker is a
        band centred on its arclength (a marker at the tip arclength, if a model has one, is
        the tip point). The base and the tip carry bands too.
    settings : SegmentationSettings
    """

    def __init__(self, catheter: Catheter, settings: SegmentationSettings = SegmentationSettings()):
        self.catheter = catheter
        self.settings = settings
        L = catheter.length_mm
        b = settings.band_length_mm
        markers = np.asarray(catheter.marker_arclengths_mm, float)
        self.n_markers = markers.size
        self.marker_is_tip = np.abs(markers - L) < 1e-6
        self.has_tip_band = bool(settings.tip_band)
        interior = np.flatnonzero(~self.marker_is_tip)
        self.interior_markers = interior
        # Expected band centres as fractions of the length: used only when bands are missing.
        centres = np.clip(markers[interior], b / 2, L - b / 2)
        self.interior_fractions = centres / L
        k = max(int(settings.closing_px), 1)
        self._kernel = np.ones((k, k), np.uint8) if k > 1 else None

    # ---------------------------------------------------------------- public
    def segment(
        self, image: Array, background: Array, base_px: Array | None = None
    ) -> ViewSegmentation:
        """Segment one image against the prior image of the empty scene.

        Parameters
        ----------
        image, background : arrays (h, w), uint8
            The frame and the empty scene (same camera, same size).
        base_px : array (2,), optional
            The registered base projected into this view, px; it picks the catheter among
            the blobs and says which end is the base. Without it the base is the thicker end
            (the proximal segment is wider).
        """
        background = check_image(background, "background image")
        image = check_image(image, "image", background.shape)
        s = self.settings
        sigma = _noise_sigma(image, background, s.noise_stride_px)
        flags = SegmentationFlag.NOISY if sigma > s.max_noise_gray else SegmentationFlag.NONE
        diff = cv2.subtract(background, image)
        threshold = max(s.threshold_sigma * sigma, s.min_threshold_gray)
        _, mask = cv2.threshold(diff, threshold, 255, cv2.THRESH_BINARY)
        picked = self._pick_blobs(mask, base_px)
        if picked is None:
            return self._empty(flags | SegmentationFlag.NO_CATHETER, sigma)
        (x0, y0, x1, y1), base_ok = picked
        if not base_ok:
            flags |= SegmentationFlag.BASE_NOT_FOUND
        return self._segment_roi(
            image, background, diff, mask, (x0, y0, x1, y1), base_px if base_ok else None,
            sigma, flags,
        )

    # ---------------------------------------------------------------- steps
    def _empty(self, flags: SegmentationFlag, sigma: float) -> ViewSegmentation:
        n = self.n_markers
        nan2 = np.full(2, np.nan)
        return ViewSegmentation(
            flags=flags,
            noise_sigma_gray=sigma,
            base_px=nan2,
            base_cov=np.full((2, 2), np.nan),
            tip_px=nan2.copy(),
            tip_cov=np.full((2, 2), np.nan),
            markers_px=np.full((n, 2), np.nan),
            markers_cov=np.full((n, 2, 2), np.nan),
            markers_found=np.zeros(n, bool),
            centreline_px=np.zeros((0, 2)),
            bands_px=np.zeros((0, 2)),
            tip_band_px=nan2.copy(),
            tip_band_cov=np.full((2, 2), np.nan),
            tip_direction=nan2.copy(),
        )

    def _pick_blobs(self, mask: Array, base_px: Array | None):
        """The catheter's blob and the blobs near it: ROI (x0, y0, x1, y1), base found."""
        s = self.settings
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        blobs = []
        for c in contours:
            # Pixel area of a blob from its boundary polygon (Pick's theorem).
            area = cv2.contourArea(c) + 0.5 * cv2.arcLength(c, True) + 1.0
            if area >= s.min_area_px:
                blobs.append((area, c, cv2.boundingRect(c)))
        if not blobs:
            return None
        base_ok = False
        main = max(range(len(blobs)), key=lambda i: blobs[i][0])
        if base_px is not None:
            p = tuple(float(v) for v in np.asarray(base_px, float).reshape(2))
            if np.all(np.isfinite(p)):
                dist = [-cv2.pointPolygonTest(c, p, True) for _, c, _ in blobs]
                nearest = int(np.argmin(dist))
                if dist[nearest] <= s.base_search_px:
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
                if np.hypot(gx, gy) <= s.max_gap_px:
                    box = [min(box[0], r[0]), min(box[1], r[1]),
                           max(box[2], r[0] + r[2]), max(box[3], r[1] + r[3])]
                    rest.remove(r)
                    grown = True
        height, width = mask.shape
        m = 3
        roi = (max(box[0] - m, 0), max(box[1] - m, 0), min(box[2] + m, width),
               min(box[3] + m, height))
        return roi, base_ok

    def _segment_roi(self, image, background, diff, mask, roi, base_px, sigma, flags):
        s = self.settings
        x0, y0, x1, y1 = roi
        height, width = image.shape
        m = mask[y0:y1, x0:x1]
        if self._kernel is not None:
            m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, self._kernel)
        n_lab, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        big = stats[:, cv2.CC_STAT_AREA] >= s.min_area_px
        big[0] = False
        if not big.any():
            return self._empty(flags | SegmentationFlag.NO_CATHETER, sigma)
        # Usually every blob in the region is large: keep the mask as it is.
        keep = m if big[1:].all() else big[labels].view(np.uint8)
        ys, xs = np.nonzero(keep)
        bg = background[y0:y1, x0:x1][ys, xs].astype(np.float64)
        bg = np.maximum(bg, 1.0)
        w = diff[y0:y1, x0:x1][ys, xs] / bg
        var_w = (sigma / bg) ** 2
        xy = np.column_stack([xs + x0, ys + y0]).astype(np.float64)
        # ---- pixel graph (8-neighbours) and the geodesic sweep from the base
        graph = _PixelGraph(ys, xs, m.shape, xy)
        if base_px is not None:
            seed = int(np.argmin(np.sum((xy - np.asarray(base_px, float)) ** 2, axis=1)))
            dist, joined = graph.sweep(seed, s.max_gap_px)
        else:
            # Double sweep: the farthest pixel from anywhere is an end; the thicker end is the base.
            d0, joined = graph.sweep(0, s.max_gap_px)
            end_a = int(np.argmax(np.where(np.isfinite(d0), d0, -1)))
            dist, j2 = graph.sweep(end_a, s.max_gap_px)
            joined = joined or j2
            reach = np.isfinite(dist)
            D = dist[reach].max()
            span = 4.0 * s.bin_px
            area_a = np.count_nonzero(reach & (dist <= span))
            area_b = np.count_nonzero(reach & (dist >= D - span))
            if area_b > area_a:
                end_b = int(np.argmax(np.where(reach, dist, -1)))
                dist, _ = graph.sweep(end_b, 0.0)
        if joined:
            flags |= SegmentationFlag.FRAGMENTED
        reach = np.isfinite(dist)
        if not reach.all():
            xy, w, var_w, dist = xy[reach], w[reach], var_w[reach], dist[reach]

        def thickness_of() -> Array:
            radius = cv2.distanceTransform(keep, cv2.DIST_L2, cv2.DIST_MASK_5)
            return radius[ys[reach], xs[reach]]

        band_pixel = w >= s.band_contrast
        D = float(dist.max())
        # ---- centreline samples
        bins = (dist / s.bin_px).astype(np.int64)
        count = np.bincount(bins, weights=w)
        cx = np.bincount(bins, weights=w * xy[:, 0])
        cy = np.bincount(bins, weights=w * xy[:, 1])
        cd = np.bincount(bins, weights=w * dist)
        ok = count > 0
        centreline = np.column_stack([cx[ok] / count[ok], cy[ok] / count[ok]])
        centre_dist = cd[ok] / count[ok]
        # ---- bands along the catheter, and checks that the view is not self-overlapping
        bands = self._bands(xy, w, var_w, dist, band_pixel, roi, m.shape)
        overlap = self._overlapping(bins, thickness_of, bands)
        tol = max(3.0, 2.0 * s.bin_px)
        base_band = tip_band = None
        if bands and bands[0]["d_min"] <= tol:
            base_band = bands.pop(0)
        if self.has_tip_band and bands and bands[-1]["d_max"] >= D - tol:
            tip_band = bands.pop(-1)
        # ---- ends
        line = (centreline, centre_dist)
        base, base_cov, _, _, _, base_mass = self._end(
            xy, w, var_w, dist, line, base_band, at_tip=False, D=D
        )
        tip, tip_cov, tip_direction, tip_extent, tube_radius, tip_mass = self._end(
            xy, w, var_w, dist, line, tip_band, at_tip=True, D=D
        )
        # Both end bands block the same fraction of light, so the ratio of their contrast
        # per unit length is the ratio of the tube widths there, whatever the blur: the
        # distal tube is thinner. A far end as wide as the base is the catheter folded back
        # onto itself in this view (its bending plane seen edge-on), with another band there.
        far = xy[dist >= D - tol]
        at_border = (
            far[:, 0].min() < s.border_px
            or far[:, 1].min() < s.border_px
            or far[:, 0].max() > width - 1 - s.border_px
            or far[:, 1].max() > height - 1 - s.border_px
        )
        width_ratio = tip_mass / base_mass if base_band is not None else float("nan")
        folded = bool(
            tip_band is not None and not at_border and width_ratio > s.max_tip_width_ratio
        )
        nan2 = np.full(2, np.nan)
        if overlap or folded:
            # The order along the catheter is unreliable: report nothing rather than a guess.
            flags |= SegmentationFlag.OVERLAP
            tip = tip_direction = nan2
            tip_band = None
            bands = []
        if at_border:
            # The catheter runs out of the image: what ends there is not the tip.
            flags |= SegmentationFlag.TIP_AT_BORDER
            tip = tip_direction = nan2
            tip_band = None
        elif self.has_tip_band and tip_band is None and not flags & SegmentationFlag.OVERLAP:
            # The far end carries no band: the tip is hidden, or the distal segment curls back
            # over itself in this view and its band may have merged with another. Either way
            # the bands cannot be told apart safely.
            flags |= SegmentationFlag.TIP_NOT_FOUND
            tip = tip_direction = nan2
            bands = []
        if not np.all(np.isfinite(tip)) and not flags & (
            SegmentationFlag.OVERLAP | SegmentationFlag.TIP_AT_BORDER
        ):
            flags |= SegmentationFlag.TIP_NOT_FOUND  # too short a centreline for an end
        # ---- markers
        n_mk = self.n_markers
        markers = np.full((n_mk, 2), np.nan)
        markers_cov = np.full((n_mk, 2, 2), np.nan)
        found = np.zeros(n_mk, bool)
        if np.all(np.isfinite(tip)):
            markers[self.marker_is_tip] = tip
            markers_cov[self.marker_is_tip] = tip_cov
            found[self.marker_is_tip] = True
        interior = self.interior_markers
        if interior.size:
            assigned, extra = self._assign(bands, base_band, tip_band, D)
            if extra:
                flags |= SegmentationFlag.EXTRA_BANDS
            for k, band in zip(interior, assigned, strict=True):
                if band is not None:
                    markers[k], markers_cov[k], found[k] = band["c"], band["cov"], True
            if not found[interior].all():
                flags |= SegmentationFlag.MARKER_MISSING
        floor = s.sigma_floor_px**2 * np.eye(2)
        all_bands = [b for b in ([base_band] + bands + [tip_band]) if b is not None]
        return ViewSegmentation(
            flags=flags,
            noise_sigma_gray=sigma,
            base_px=base,
            base_cov=base_cov + floor,
            tip_px=tip,
            tip_cov=tip_cov + floor,
            markers_px=markers,
            markers_cov=markers_cov + floor,
            markers_found=found,
            centreline_px=centreline,
            bands_px=np.array([b["c"] for b in all_bands]).reshape(-1, 2),
            tip_band_px=nan2 if tip_band is None else tip_band["c"],
            tip_band_cov=np.full((2, 2), np.nan) if tip_band is None else tip_band["cov"] + floor,
            tip_direction=tip_direction if tip_band is not None else nan2,
            tip_extent_px=float(tip_extent) if tip_band is not None else float("nan"),
            tube_radius_px=float(tube_radius),
            tip_width_ratio=float(width_ratio),
        )

    def _overlapping(self, bins: Array, thickness_of, bands: list) -> bool:
        """Whether the catheter touches, crosses or folds onto itself in this view.

        Two signs. A stretch of the centreline where the mask has many more pixels per
        sample than usual and is also much thicker than the typical tube (largest inscribed
        disc, from the distance transform; side by side, or a crossing); either alone is not
        enough, since the inscribed disc is coarse at a few pixels and tight projected bends
        fan the samples out. And a "band" much longer than a band can look (the tube folded
        onto itself is as dark as a band).

        ``thickness_of()`` returns each pixel's inscribed radius; it is only called when the
        counts are suspicious.
        """
        s = self.settings
        n_bins = int(bins.max()) + 1
        count = np.bincount(bins, minlength=n_bins).astype(float)
        # A band seen end-on is a disc wider than the tube: leave its samples and their
        # neighbours out.
        for b in bands:
            count[max(int(b["d_min"] / s.bin_px) - 1, 0) : int(b["d_max"] / s.bin_px) + 2] = 0.0
        count[:2] = 0.0
        count[-2:] = 0.0
        ok = count > 0
        if ok.sum() < 3:
            return False
        typical_n = float(np.median(count[ok]))
        wide = ok & (count > 1.1 * s.overlap_ratio * typical_n)
        if wide.any():
            thickness = np.zeros(n_bins)
            np.maximum.at(thickness, bins, thickness_of())
            typical_r = float(np.median(thickness[ok]))
            if np.any(thickness[wide] > s.overlap_ratio * typical_r):
                return True
        longest = 1.6 * typical_n / s.bin_px + 2.0 * s.bin_px
        return any(b["d_max"] - b["d_min"] > longest for b in bands)

    def _bands(self, xy, w, var_w, dist, band_pixel, roi, shape):
        """Connected groups of band pixels (8-neighbours), ordered along the catheter.

        Connected in the image, not along the geodesic distance: where the catheter hooks
        back, two bands can lie at the same distance from the base.
        """
        s = self.settings
        idx = np.flatnonzero(band_pixel)
        if idx.size == 0:
            return []
        bx = (xy[idx, 0] - roi[0]).astype(np.intp)
        by = (xy[idx, 1] - roi[1]).astype(np.intp)
        bmask = np.zeros(shape, np.uint8)
        bmask[by, bx] = 1
        n_lab, labels = cv2.connectedComponents(bmask, connectivity=8)
        lab = labels[by, bx]
        order = np.argsort(lab, kind="stable")
        cuts = np.flatnonzero(np.diff(lab[order])) + 1
        bands = []
        for sel in np.split(idx[order], cuts):
            if sel.size < s.min_band_area_px:
                continue
            excess = w[sel] - s.band_contrast
            c, cov = _weighted_centroid(xy[sel], excess, var_w[sel])
            d = dist[sel]
            bands.append(
                dict(c=c, cov=cov, d=float(excess @ d / excess.sum()), d_min=float(d.min()),
                     d_max=float(d.max()), sel=sel)
            )
        bands.sort(key=lambda b: b["d"])
        return bands

    def _end(self, xy, w, var_w, dist, line, band, at_tip, D):
        """Sub-pixel end of the centreline (tip or base) and its covariance.

        The cut is the end band's centroid (or a centreline sample two bins from the end);
        the direction is the centreline tangent there, from a second-order one-sided
        difference of samples one and two band-lengths back (samples right at an end are
        skewed: the end's far corner is geodesically farthest).

        Returns the end (2,), its covariance (2, 2), the unit direction toward the end, the
        end's distance past the cut (px), the tube's image radius (px) and its contrast per
        unit length (contrast x px: the band's contrast times the tube's image width).
        """
        s = self.settings
        nan = (
            np.full(2, np.nan), np.full((2, 2), np.nan), np.full(2, np.nan), np.nan, np.nan, np.nan
        )
        centreline, centre_dist = line
        if centreline.shape[0] < 4:
            return nan
        step = 2.0 * s.bin_px
        sign = -1.0 if at_tip else 1.0
        if band is not None:
            d_cut = band["d"]
            p = _interpolate(centreline, centre_dist, d_cut + sign * np.array([step, 2 * step]))
            cut, cut_cov = band["c"], band["cov"]
        else:
            d_cut = D - step if at_tip else step
            p = _interpolate(centreline, centre_dist, d_cut + sign * np.array([0, step, 2 * step]))
            cut, p = p[0], p[1:]
            cut_cov = np.zeros((2, 2))
        direction = 3.0 * cut - 4.0 * p[0] + p[1]  # toward the end in both cases
        norm = np.hypot(direction[0], direction[1])
        if norm < 1e-9:
            return nan
        direction = direction / norm
        if band is not None:
            t_band = (xy[band["sel"]] - cut) @ direction
            slab = min(max(-float(t_band.min()), 0.5), s.end_slab_px)
        else:
            slab = s.end_slab_px
        reach = 3.0 * step + slab
        near = (dist >= d_cut - slab - step) if at_tip else (dist <= d_cut + slab + step)
        near = np.flatnonzero(near)
        rel = xy[near] - cut
        near = near[np.einsum("ij,ij->i", rel, rel) <= reach**2]
        e, var_e, m_per_px = _ends_cut(xy[near], w[near], var_w[near], cut, direction, slab)
        if not np.isfinite(e):
            return nan
        # The end disc of a tube seen obliquely sticks out past the end point by up to
        # pi/4 of the radius (m / 2 per unit contrast); half of that is the uncertainty of a
        # single view (segment_pair removes it with both views).
        w_near = w[near]
        k = int(0.9 * (w_near.size - 1))
        contrast = float(np.partition(w_near, k)[k])  # the plateau, robust to noise
        radius_px = 0.5 * m_per_px / max(contrast, 1e-6)
        var_e = var_e + (np.pi / 8.0 * radius_px) ** 2
        dd = np.outer(direction, direction)
        # Across: the end moves sideways with the direction's error.
        var_across = (e * s.tip_direction_sigma_rad) ** 2
        cov = cut_cov + var_e * dd + var_across * (np.eye(2) - dd)
        return cut + e * direction, cov, direction, e, radius_px, m_per_px

    def _assign(self, bands, base_band, tip_band, D):
        """Interior bands -> interior markers: in order when the count matches, else by position."""
        n = self.interior_markers.size
        if len(bands) == n:
            return list(bands), False
        if not bands:
            return [None] * n, False
        start = base_band["d"] if base_band is not None else 0.0
        end = tip_band["d"] if tip_band is not None else D
        span = max(end - start, 1e-9)
        frac = np.array([(b["d"] - start) / span for b in bands])
        out: list = [None] * n
        used = set()
        for j in np.argsort(np.abs(frac[:, None] - self.interior_fractions[None, :]).min(axis=0)):
            costs = np.abs(frac - self.interior_fractions[j])
            for i in np.argsort(costs):
                if i not in used and costs[i] <= 0.25:
                    out[j] = bands[i]
                    used.add(int(i))
                    break
        return out, len(bands) > n


_OFFSETS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
_LENGTHS = np.array([np.hypot(dy, dx) for dy, dx in _OFFSETS])


class _PixelGraph:
    """The 8-neighbour graph of foreground pixels, edge lengths in px, for geodesic sweeps.

    Built straight into compressed sparse rows: pixels are numbered in row-major order, so
    each pixel's neighbour list is already grouped and no sort is needed.
    """

    def __init__(self, ys: Array, xs: Array, shape: tuple[int, int], xy: Array) -> None:
        n = ys.size
        width = shape[1] + 2
        index = np.full((shape[0] + 2) * width, -1, np.int32)
        flat = (ys + 1) * width + (xs + 1)
        index[flat] = np.arange(n, dtype=np.int32)
        offsets = np.array([dy * width + dx for dy, dx in _OFFSETS])
        nb = index[flat[:, None] + offsets]
        # Every pixel gets its eight neighbours; missing ones point at an extra sink node
        # that has no way out, so no masking or sorting is needed.
        nb[nb < 0] = n
        indptr = np.append(np.arange(0, 8 * n + 1, 8, dtype=np.int32), 8 * n)
        lengths = np.tile(_LENGTHS, n)
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


# ------------------------------------------------------------------------------- the pair
@dataclass(frozen=True)
class PairSegmentation:
    """Both views of a synchronised pair, and the rows of a pipeline Frame.

    Attributes
    ----------
    front, side : ViewSegmentation
    uv_front, uv_side : arrays (1 + n_markers, 2)
        Rows ``[tip, marker_0, ...]``, px, NaN for points not found or rejected.
    cov_front, cov_side : arrays (1 + n_markers, 2, 2)
        px^2, NaN where the point is missing.
    rejected : array (1 + n_markers,) of bool
        Rows found in both views whose rays do not meet (epipolar check): withheld in both,
        since one of the two views has picked the wrong point (the catheter overlapping
        itself in that view).
    tip_refined : bool
        The tip was placed from the tip band in both views (see :func:`segment_pair`).
    """

    front: ViewSegmentation
    side: ViewSegmentation
    uv_front: Array
    uv_side: Array
    cov_front: Array
    cov_side: Array
    rejected: Array
    tip_refined: bool = False

    def frame(
        self,
        time_s: float,
        q: Array,
        q_dot: Array | None = None,
        images: tuple[Array, Array] | None = None,
        delta_L_true_rad: float | None = None,
    ) -> Frame:
        """The pipeline frame of this pair at the given time and joint values."""
        return Frame(
            time_s=float(time_s),
            q=np.asarray(q, float),
            q_dot=None if q_dot is None else np.asarray(q_dot, float),
            uv_front=self.uv_front,
            uv_side=self.uv_side,
            cov_front=self.cov_front,
            cov_side=self.cov_side,
            images=images,
            delta_L_true_rad=delta_L_true_rad,
        )


def _unit_sphere(n: int) -> Array:
    """n nearly uniform unit vectors (Fibonacci lattice), shape (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z**2)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


_COARSE = _unit_sphere(200)  # about 15 degrees apart
_CAP_RAD = np.radians(16.0)


def _cap(n: int, angle_rad: float) -> Array:
    """n nearly uniform unit vectors within ``angle_rad`` of +z, shape (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - (1.0 - np.cos(angle_rad)) * k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z**2)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


_FINE = _cap(100, _CAP_RAD)  # about 3 degrees apart


def _cross(a: Array, b: Array) -> Array:
    """Cross product of two 3-vectors (np.cross is slow for single vectors)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _around(t: Array, cap: Array) -> Array:
    """The cap's directions turned so that +z goes to the unit vector t."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(t[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = _cross(t, helper)
    u /= np.sqrt(u @ u)
    v = _cross(t, u)
    return cap @ np.stack([u, v, t])


def _tip_from_band(
    rig: BiplaneRig,
    front: ViewSegmentation,
    side: ViewSegmentation,
    centre_w: Array,
    jacobians: tuple[Array, Array],
    half_band_mm: float,
) -> tuple[Array, float]:
    """The tip in {W}: the tip band's centre moved half a band along the 3-D tangent.

    The band's centroid is the projection of its centre in both views whatever the
    foreshortening, so the centre ``centre_w`` is triangulated from the two centroids. The
    tangent t is the unit vector that best explains, in both views, where the image ends
    past the centroid: ``half_band t`` projects to an image vector p (short when t points at
    the camera), and the end disc of the tube sticks out past the tip by
    ``pi/4 R |sin a|`` (R the tube's image radius, a the angle between t and the image
    plane). Per view the residuals are p's offset across the measured direction and the
    measured extent minus ``p . direction + pi/4 R |sin a|``, px; their squares are summed
    over both views and minimised over the sphere of directions (a coarse grid, then a fine
    cap around its best). A view where the tip points at the camera has a short p and an end
    that is a disc: its poorly defined direction then costs little, which is what makes this
    robust where intersecting the two planes of the image directions is not.

    ``jacobians`` are the views' projection Jacobians at the centre (px/mm). Returns the tip
    in {W} and the misfit (the smallest sum of squared residuals, px^2).
    """
    terms = []
    for view, seg, J in zip((rig.front, rig.side), (front, side), jacobians, strict=True):
        x_cam = view.R_cam_w @ centre_w + view.t_cam_w
        ray = (x_cam / np.sqrt(x_cam @ x_cam)) @ view.R_cam_w  # viewing ray in {W}
        terms.append((half_band_mm * J.T, ray, 0.25 * np.pi * seg.tube_radius_px,
                      seg.tip_extent_px, seg.tip_direction))

    def cost(T: Array) -> Array:
        total = np.zeros(T.shape[0])
        for JT, ray, cap_px, extent, direction in terms:
            p = T @ JT
            along = p @ direction
            across = p - along[:, None] * direction
            # The end disc adds to the extent along the measured direction whatever that is:
            # seen end-on the band is a disc and its measured direction means little.
            r_along = extent - along - cap_px * np.abs(T @ ray)
            total += np.einsum("ij,ij->i", across, across) + r_along**2
        return total

    best = _COARSE[int(np.argmin(cost(_COARSE)))]
    fine = _around(best, _FINE)
    costs = cost(fine)
    k = int(np.argmin(costs))
    return centre_w + half_band_mm * fine[k], float(costs[k])


def segment_pair(
    segmenter: Segmenter,
    images: tuple[Array, Array],
    backgrounds: tuple[Array, Array],
    base_px: tuple[Array | None, Array | None] = (None, None),
    rig: BiplaneRig | None = None,
) -> PairSegmentation:
    """Segment a synchronised (front, side) pair into the fields of a pipeline Frame.

    Parameters
    ----------
    segmenter : Segmenter
    images, backgrounds : pairs of uint8 arrays (h, w)
        Front and side frames and their empty-scene priors.
    base_px : pair of arrays (2,) or None
        The registered base projected into each view.
    rig : BiplaneRig, optional
        The calibrated pinhole rig of the images. With it, two cross-view steps run:
        rows whose rays miss each other by more than the epipolar gate are withheld
        (``rejected``), and when both views see the tip band the tip is placed in 3-D from
        the band's centre and the catheter's tangent and projected back into both views.
        This removes the bias of a single view's far end when the tip points toward the
        camera (the end disc of the tube sticks out past the end point).
    """
    s = segmenter.settings
    front = segmenter.segment(images[0], backgrounds[0], base_px[0])
    side = segmenter.segment(images[1], backgrounds[1], base_px[1])
    uv_f, cov_f, _ = frame_points(front)
    uv_s, cov_s, _ = frame_points(side)
    rejected = np.zeros(uv_f.shape[0], bool)
    if rig is None:
        return PairSegmentation(front, side, uv_f, uv_s, cov_f, cov_s, rejected)
    if rig.kind != "pinhole":
        raise ValueError("segment_pair needs the pinhole rig the images were taken with")
    tip_rows = np.concatenate([[True], segmenter.marker_is_tip])
    both_bands = bool(
        np.all(np.isfinite(front.tip_band_px)) and np.all(np.isfinite(side.tip_band_px))
    )
    # Epipolar check: each row on its own points; the tip by its band centroids.
    check_f, check_s = uv_f.copy(), uv_s.copy()
    if both_bands:
        check_f[tip_rows], check_s[tip_rows] = front.tip_band_px, side.tip_band_px
    both = np.all(np.isfinite(check_f), -1) & np.all(np.isfinite(check_s), -1)
    points_w = np.full((uv_f.shape[0], 3), np.nan)
    jacobians = None
    if both.any():
        points_w[both] = rig.reconstruct(check_f[both], check_s[both])
        # One projection per view: the points, and (for the tip) three nudged copies of the
        # band centre that give the projection Jacobian there by finite differences.
        nudge_mm = 1e-3
        points = points_w[both]
        if both[0]:
            points = np.vstack([points, points_w[0] + nudge_mm * np.eye(3)])
        reprojected, jacobians = [], []
        for view in (rig.front, rig.side):
            uv = view.project(points)
            reprojected.append(uv[: both.sum()])
            if both[0]:
                jacobians.append((uv[-3:] - uv[0]).T / nudge_mm)
        residual = np.maximum(
            np.linalg.norm(reprojected[0] - check_f[both], axis=-1),
            np.linalg.norm(reprojected[1] - check_s[both], axis=-1),
        )
        spread = np.sqrt(
            np.trace(cov_f[both], axis1=-2, axis2=-1) + np.trace(cov_s[both], axis1=-2, axis2=-1)
        )
        spread = np.where(np.isfinite(spread), spread, 0.0)
        bad = residual > np.maximum(s.epipolar_gate_px, 4.0 * spread)
        rejected[np.flatnonzero(both)[bad]] = True
    refined = bool(
        both_bands
        and both[0]
        and not rejected[0]
        and np.isfinite(front.tip_extent_px * side.tip_extent_px)
        and np.isfinite(front.tube_radius_px * side.tube_radius_px)
    )
    if refined:
        half_band = 0.5 * s.band_length_mm
        tip_w, misfit = _tip_from_band(rig, front, side, points_w[0], jacobians, half_band)
        views = ((front, uv_f, cov_f, reprojected[0][0]), (side, uv_s, cov_s, reprojected[1][0]))
        for (seg, uv, cov, centre_px), J in zip(views, jacobians, strict=True):
            px_per_mm = float(np.linalg.norm(J, axis=-1).max())
            # The tangent's uncertainty, and what the two views disagree on (4 residuals for
            # 2 unknowns), as a variance of the tip in the image.
            extra = (half_band * px_per_mm * s.tip_direction_sigma_rad) ** 2 + 0.5 * misfit
            # Half a band from the centre: first order is exact to far below a pixel.
            uv[tip_rows] = centre_px + J @ (tip_w - points_w[0])
            cov[tip_rows] = seg.tip_band_cov + extra * np.eye(2)
    for uv, cov in ((uv_f, cov_f), (uv_s, cov_s)):
        uv[rejected] = np.nan
        cov[rejected] = np.nan
    return PairSegmentation(front, side, uv_f, uv_s, cov_f, cov_s, rejected, refined)


class PairSegmenter:
    """Segments synchronised pairs of one rig, catheter and registered base.

    Parameters
    ----------
    catheter : Catheter
    rig : BiplaneRig
        Pinhole rig of the cameras (e.g. :func:`models.rig_file.load_rig`).
    R_w_b, o_b_w_mm : arrays (3, 3), (3,)
        Registered base pose; its origin projected into each view picks the catheter and
        its base end.
    backgrounds : pair of uint8 arrays
        Prior images of the empty scene, one per view, of the rig's image sizes.
    settings : SegmentationSettings
    """

    def __init__(
        self,
        catheter: Catheter,
        rig: BiplaneRig,
        R_w_b: Array,
        o_b_w_mm: Array,
        backgrounds: tuple[Array, Array],
        settings: SegmentationSettings = SegmentationSettings(),
    ) -> None:
        if rig.kind != "pinhole":
            raise ValueError("PairSegmenter needs a pinhole rig (images are in pixels)")
        self.rig = rig
        self.segmenter = Segmenter(catheter, settings)
        self.backgrounds = tuple(
            check_image(bg, f"{name} background image", (v.image_size[1], v.image_size[0]))
            for bg, name, v in zip(backgrounds, ("front", "side"), (rig.front, rig.side),
                                   strict=True)
        )
        o = np.asarray(o_b_w_mm, float)
        self.base_px = (rig.front.project(o), rig.side.project(o))

    def segment(self, images: tuple[Array, Array]) -> PairSegmentation:
        return segment_pair(self.segmenter, images, self.backgrounds, self.base_px, self.rig)

    def frame(
        self,
        time_s: float,
        q: Array,
        images: tuple[Array, Array],
        q_dot: Array | None = None,
        delta_L_true_rad: float | None = None,
    ) -> Frame:
        """Segment a pair and return the pipeline Frame (images attached)."""
        return self.segment(images).frame(time_s, q, q_dot, images, delta_L_true_rad)
