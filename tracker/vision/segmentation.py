"""Marker segmentation of one view: image -> the 2-D points the estimators consume
(docs/design.md sections 4, 6).

The paper's approach, per view (:class:`Segmenter`):

1. background subtraction against a prior image of the empty scene (the catheter is darker
   than the scene: ``diff = f(background) - image``), after a photometric normalisation: the
   tone curve ``f`` (gain, offset, gamma) of the frame relative to the background, fitted
   robustly on a grid of pixels (:mod:`tracker.vision.photometry`), whose residual is the
   per-frame noise estimate; optionally only in a region around the catheter's predicted
   image (with a search of the whole image when it is not found there);
2. a threshold at a multiple of that noise on both images smoothed, at half resolution over
   the whole image then at full resolution in the region found
   (:mod:`tracker.vision.detection`), mask clean-up (closing, small blobs removed), and the
   catheter chosen as the blob nearest the registered base;
3. the centreline: mask pixels ordered by their geodesic distance from the base along the
   mask (a shortest-path sweep over the mask's 8-neighbour grid,
   :mod:`tracker.vision.pixel_graph`; pieces of a catheter split by an occluder
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

Then per synchronised frame of the rig's views (:mod:`tracker.vision.pair`): an epipolar
check and the tip placed in 3-D from the tip band. Over time, per camera
(:mod:`tracker.vision.background`): a background that follows the scene and a region of
interest that follows the catheter.

Every point comes with a covariance propagated from the per-frame noise estimate through the
centroid / end formulas (plus a small floor), and a flag saying what went wrong when a point
is missing. Bad input is either a flagged result (no catheter, the tip out of the image, a
hidden marker, a view where the catheter overlaps itself) or one ``ValueError`` / ``OSError``
(an image of the wrong size or type, an unreadable file), never a silent wrong point.

The steps over the catheter's pixels are compiled kernels (:mod:`tracker.vision.kernels`).

Points are in px (distorted pixels of the camera, as :class:`models.imaging.PinholeView`
expects them); :func:`frame_points` maps them onto the rows ``[tip, marker_0, ...]`` of
:class:`tracker.types.Frame`. Thresholds are
:class:`tracker.vision.settings.SegmentationSettings`.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import NamedTuple

import cv2
import numpy as np

from models.catheter import Catheter
from tracker.vision import band_fit, kernels, pixel_graph
from tracker.vision.detection import (
    coarse_region,
    detection_backgrounds,
    find_in_box,
    foreground,
    search_box,
)
from tracker.vision.photometry import BackgroundSamples, Photometry, fit_photometry
from tracker.vision.settings import DEFAULT_SETTINGS, SegmentationSettings, check_image

Array = np.ndarray


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
    EXPOSURE = enum.auto()  # the frame is black, saturated or far from the background's gain
    CAMERA_MOVED = enum.auto()  # the frame is shifted from the background (re-registered)
    BACKGROUND_LOST = enum.auto()  # the background no longer registers: take a new one


# The flags under which nothing is segmented (combined once: an enum operation costs about
# a microsecond).
NOT_SEGMENTED = SegmentationFlag.EXPOSURE | SegmentationFlag.BACKGROUND_LOST


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
    photometry : Photometry, optional
        The frame's tone curve and shift relative to its background.
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
    photometry: Photometry | None = None

    @property
    def tip_found(self) -> bool:
        return math.isfinite(self.tip_px[0]) and math.isfinite(self.tip_px[1])


def shifted_back(
    seg: ViewSegmentation, shift_px: Array, shift_cov_px2: Array | None = None
) -> ViewSegmentation:
    """The segmentation of a frame whose whole image was shifted by ``shift_px`` (x, y),
    px, with every point moved back by it (into the pixels of the unshifted image).

    ``shift_cov_px2`` (2, 2), the shift's covariance if it was measured, is added to every
    point's (the points share the shift's error).
    """
    shift = np.asarray(shift_px, float)
    extra = np.zeros((2, 2)) if shift_cov_px2 is None else np.asarray(shift_cov_px2, float)
    return replace(
        seg,
        base_px=seg.base_px - shift,
        base_cov=seg.base_cov + extra,
        tip_px=seg.tip_px - shift,
        tip_cov=seg.tip_cov + extra,
        markers_px=seg.markers_px - shift,
        markers_cov=seg.markers_cov + extra,
        centreline_px=seg.centreline_px - shift,
        bands_px=seg.bands_px - shift,
        tip_band_px=seg.tip_band_px - shift,
        tip_band_cov=seg.tip_band_cov + extra,
    )


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
    uv = np.concatenate([seg.tip_px[None], seg.markers_px])
    cov = np.concatenate([seg.tip_cov[None], seg.markers_cov])
    found = [seg.tip_found, *seg.markers_found.tolist()]
    if not all(found):
        missing = np.logical_not(found)
        uv[missing] = np.nan
        cov[missing] = np.nan
    return uv, cov, np.array(found)


# ---------------------------------------------------------------------------- the segmenter
# The catheter's pixels are held as flat arrays, one value per pixel, and their coordinates
# as the rows of a (2, n) array: numpy works along a (n, 2) array two numbers at a time,
# several times slower, and picks columns with take / compress several times faster than
# with fancy indexing. Scalars and 2-vectors are Python floats: a numpy call on a few
# numbers costs far more than the arithmetic.


class _Band(NamedTuple):
    """One radio-opaque band: its contrast-weighted centroid c (2,) and covariance (2, 2), px,
    image; its distance from the base along the catheter (contrast-weighted mean, least and
    greatest), px; ``label``: its pixels are those the labels of :func:`kernels.bands`
    give this number."""

    c: Array
    cov: Array
    d: float
    d_min: float
    d_max: float
    label: int


# Read-only arrays of NaN: copied for a result's missing points (a copy costs less than
# np.full).
_NAN2, _NAN22 = np.full(2, np.nan), np.full((2, 2), np.nan)
for _array in (_NAN2, _NAN22):
    _array.flags.writeable = False
_TIP_WITHHELD = SegmentationFlag.OVERLAP | SegmentationFlag.TIP_AT_BORDER
# A band fit that moves the centre farther than this from the centroid is dropped, px.
_MAX_FIT_MOVE_PX = 2.0


def _median(values: Array) -> float:
    """The median of a non-empty 1-D array, which it reorders (np.median costs far more for a
    few values)."""
    n = values.size
    values.partition([(n - 1) // 2, n // 2])
    return 0.5 * float(values[(n - 1) // 2] + values[n // 2])


def _finite_point(p: Array) -> bool:
    """Whether both coordinates of a point (2,) are finite (np.isfinite costs more for two
    numbers)."""
    return math.isfinite(p[0]) and math.isfinite(p[1])


class Segmenter:
    """Segments one view of one catheter model.

    Parameters
    ----------
    catheter : Catheter
        Gives the markers (their arclengths, in order) and the length: every marker is a
        band centred on its arclength (a marker at the tip arclength, if a model has one, is
        the tip point). The base and the tip carry bands too.
    settings : SegmentationSettings

    Keeps nothing from image to image: one segmenter may serve several threads at once. Its
    compiled kernels are loaded (or compiled, the first time on a machine) when it is made,
    not on the first image (:func:`tracker.vision.kernels.warm_up`).
    """

    def __init__(self, catheter: Catheter, settings: SegmentationSettings = DEFAULT_SETTINGS):
        self.catheter = catheter
        self.settings = settings
        L = catheter.length_mm
        b = settings.band_length_mm
        markers = np.asarray(catheter.marker_arclengths_mm, float)
        self.n_markers = markers.size
        self.marker_is_tip = np.abs(markers - L) < 1e-6
        # The rows of a Frame's view that are the tip: row 0, and a marker at the tip.
        self.frame_tip_rows = np.concatenate([[True], self.marker_is_tip])
        self.has_tip_band = bool(settings.tip_band)
        interior = np.flatnonzero(~self.marker_is_tip)
        self.interior_markers = interior
        # Expected band centres as fractions of the length: used only when bands are missing.
        centres = np.clip(markers[interior], b / 2, L - b / 2)
        self.interior_fractions = centres / L
        k = max(int(settings.closing_px), 1)
        self._kernel = np.ones((k, k), np.uint8) if k > 1 else None
        self._floor = settings.sigma_floor_px**2 * np.eye(2)
        # The markers' points and covariances with none found, copied for every result.
        n = self.n_markers
        self._no_markers = np.full((n, 2), np.nan), np.full((n, 2, 2), np.nan)
        kernels.warm_up()
        band_fit.warm_up()

    # ---------------------------------------------------------------- public
    def segment(
        self,
        image: Array,
        background: Array,
        base_px: Array | None = None,
        *,
        photometry: Photometry | None = None,
        search_px: Array | None = None,
        prepared: tuple[Array, Array] | None = None,
        abandon: Callable[[], bool] | None = None,
    ) -> ViewSegmentation | None:
        """Segment one image against the prior image of the empty scene.

        Parameters
        ----------
        image, background : arrays (h, w), uint8
            The frame and the empty scene (same camera, same size).
        base_px : array (2,), optional
            The registered base projected into this view, px; it picks the catheter among
            the blobs and says which end is the base. Without it the base is the thicker end
            (the proximal segment is wider).
        photometry : Photometry, optional
            The frame's tone curve relative to the background, if already fitted
            (:meth:`photometry`); fitted here otherwise.
        search_px : array (n, 2), optional
            Where the catheter is expected in the image (the last estimate's points
            reprojected, or the last frame's centreline, with the base), px: only the region
            around them, padded by ``roi_pad_px``, is searched, and the whole image when
            the catheter is not found there or runs out of it.
        prepared : pair of uint8 arrays, optional
            ``detection_backgrounds(background)``, if kept from frame to frame.
        abandon : callable, optional
            Asked between the stages; once it says True the segmentation stops and returns
            None (a rehearsal that a frame has come to replace).

        Notes
        -----
        The whole image is searched at half resolution (both images averaged over 2 x 2
        pixels and smoothed: white noise drops to 0.19 of itself, the tube keeps most of its
        contrast); the foreground at full resolution is then found in the region of the
        blobs found there, with a margin. A region around ``search_px`` is searched at full
        resolution directly, and the whole image as above when the catheter is not found in
        it or runs out of it.
        """
        s = self.settings
        background = check_image(background, "background image")
        image = check_image(image, "image", background.shape)
        if photometry is None:
            photometry = self.photometry(image, background)
        flags = self.photometry_flags(photometry)
        if flags & NOT_SEGMENTED:
            return self.empty_result(flags, photometry)
        smoothed, coarse = detection_backgrounds(background) if prepared is None else prepared
        found = None
        if search_px is not None:
            box = search_box(search_px, s.roi_pad_px, image.shape)
            found = find_in_box(image, smoothed, photometry, box, base_px, s)
        if found is None:
            region = coarse_region(image, coarse, photometry, base_px, s)
            if region is not None:
                box, base_ok = region
                found = box, foreground(image, smoothed, photometry, box, s), base_ok
        if found is None:
            return self.empty_result(flags | SegmentationFlag.NO_CATHETER, photometry)
        roi, mask, base_ok = found
        if not base_ok:
            flags |= SegmentationFlag.BASE_NOT_FOUND
        if abandon is not None and abandon():
            return None
        return self._segment_roi(
            image, background, photometry, mask, roi, base_px if base_ok else None, flags,
            abandon,
        )

    def photometry(
        self, image: Array, background: Array, samples: BackgroundSamples | None = None
    ) -> Photometry:
        """The frame's tone curve, shift and noise relative to the background (normalised
        only if the settings say so); ``samples``: the background's on the grid, if kept."""
        s = self.settings
        return fit_photometry(
            image, background, s.noise_stride_px, s.normalise, samples=samples
        )

    def photometry_flags(self, photometry: Photometry) -> SegmentationFlag:
        """NOISY, EXPOSURE and CAMERA_MOVED as the settings judge the frame's photometry."""
        s = self.settings
        flags = SegmentationFlag.NONE
        if not photometry.sigma_gray <= s.max_noise_gray:
            flags |= SegmentationFlag.NOISY
        if (
            not photometry.fitted
            or photometry.clipped_fraction > s.max_clipped_fraction
            or not 1.0 / s.max_gain_change <= photometry.gain <= s.max_gain_change
        ):
            flags |= SegmentationFlag.EXPOSURE
        if math.hypot(*photometry.shift_px.tolist()) > s.camera_moved_px:
            flags |= SegmentationFlag.CAMERA_MOVED
        return flags

    # ---------------------------------------------------------------- steps
    def empty_result(self, flags: SegmentationFlag, photometry: Photometry) -> ViewSegmentation:
        """A result with every point missing (NaN) and these flags."""
        markers, markers_cov = self._no_markers
        return ViewSegmentation(
            flags=flags,
            noise_sigma_gray=photometry.sigma_gray,
            base_px=_NAN2.copy(),
            base_cov=_NAN22.copy(),
            tip_px=_NAN2.copy(),
            tip_cov=_NAN22.copy(),
            markers_px=markers.copy(),
            markers_cov=markers_cov.copy(),
            markers_found=np.zeros(self.n_markers, bool),
            centreline_px=np.zeros((0, 2)),
            bands_px=np.zeros((0, 2)),
            tip_band_px=_NAN2.copy(),
            tip_band_cov=_NAN22.copy(),
            tip_direction=_NAN2.copy(),
            photometry=photometry,
        )

    def _catheter_pixels(self, mask: Array) -> tuple[Array, Array, Array] | None:
        """The rows and columns (intp, row-major order) of the mask's pixels in blobs of at
        least ``min_area_px``, and the mask of those blobs; None if there are none."""
        # cv2.findNonZero: the pixels as np.nonzero gives them, for a fraction of its cost;
        # the blobs' areas only when there are several (connectedComponentsWithStats costs
        # several times more than the labels and a bincount).
        n_labels, labels = cv2.connectedComponents(mask, connectivity=8)
        if n_labels < 2:
            return None
        points = cv2.findNonZero(mask).reshape(-1, 2)
        if n_labels == 2:
            if points.shape[0] < self.settings.min_area_px:
                return None
        else:
            label = labels[points[:, 1], points[:, 0]]
            big = np.bincount(label) >= self.settings.min_area_px
            big[0] = False
            if not big.any():
                return None
            # Usually every blob in the region is large: keep the mask as it is.
            if not big[1:].all():
                mask = big[labels].view(np.uint8)
                points = points[big[label]]
        xs, ys = np.array(points.T, np.intp, order="C")
        return ys, xs, mask

    def _segment_roi(self, image, background, photometry, m, roi, base_px, flags, abandon=None):
        s = self.settings
        sigma = photometry.sigma_gray
        x0, y0 = roi[0], roi[1]
        height, width = image.shape
        if self._kernel is not None:
            m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, self._kernel)
        pixels = self._catheter_pixels(m)
        if pixels is None:
            return self.empty_result(flags | SegmentationFlag.NO_CATHETER, photometry)
        ys, xs, keep = pixels
        # The contrast: the fraction of the light the catheter blocks (the background as the
        # frame would show it, above the black level). The kernels take C-ordered arrays and
        # ints and floats only: anything else would compile another version on the spot.
        w, var_w, xy = kernels.contrast(
            np.ascontiguousarray(image), np.ascontiguousarray(background), photometry.lut,
            float(photometry.dark_gray), float(sigma), ys, xs, int(x0), int(y0),
        )
        # ---- geodesic distances from the base along the mask (8-neighbours)
        index = pixel_graph.pixel_index(ys, xs, *m.shape)
        max_gap = float(s.max_gap_px)
        no_bridges = pixel_graph.NO_BRIDGES

        def sweep(seed, bridges, max_gap_px=max_gap):
            """Distances from the seed, the bridges after it and whether it added one."""
            dist, *after = pixel_graph.geodesic_sweep(
                index, ys, xs, xy, seed, max_gap_px, *bridges
            )
            return dist, after, after[1].size > bridges[1].size

        if base_px is not None:
            seed = pixel_graph.nearest(xy, float(base_px[0]), float(base_px[1]))
            dist, _, joined = sweep(seed, no_bridges)
        else:
            # Double sweep: the farthest pixel from anywhere is an end; the thicker end is the base.
            d0, bridges, joined = sweep(0, no_bridges)
            end_a = int(np.argmax(np.where(np.isfinite(d0), d0, -1)))
            dist, bridges, j2 = sweep(end_a, bridges)
            joined = joined or j2
            reach = np.isfinite(dist)
            D = dist[reach].max()
            span = 4.0 * s.bin_px
            area_a = np.count_nonzero(reach & (dist <= span))
            area_b = np.count_nonzero(reach & (dist >= D - span))
            if area_b > area_a:
                end_b = int(np.argmax(np.where(reach, dist, -1)))
                dist, _, _ = sweep(end_b, bridges, 0.0)
        if joined:
            flags |= SegmentationFlag.FRAGMENTED
        D = float(dist.max())
        if not math.isfinite(D):
            reach = np.isfinite(dist)
            xs, ys, xy, w, var_w, dist = (
                xs[reach], ys[reach], xy.compress(reach, axis=1), w[reach], var_w[reach],
                dist[reach],
            )
            index = pixel_graph.pixel_index(ys, xs, *m.shape)
            D = float(dist.max())

        def thickness_of() -> Array:
            radius = cv2.distanceTransform(keep, cv2.DIST_L2, cv2.DIST_MASK_5)
            return radius[ys, xs]

        if abandon is not None and abandon():
            return None

        # ---- centreline samples: x, y and distance from the base
        bins, line = kernels.centreline(dist, xy, w, float(s.bin_px))
        centreline = line[:2].T.copy()
        # ---- bands along the catheter, and checks that the view is not self-overlapping
        bands, label, band_arrays = self._bands(index, ys, xs, w, var_w, dist, roi)
        overlap = self._overlapping(bins, D, thickness_of, bands, band_arrays[2])
        tol = max(3.0, 2.0 * s.bin_px)
        base_band = tip_band = None
        if bands and bands[0].d_min <= tol:
            base_band = bands.pop(0)
        if self.has_tip_band and bands and bands[-1].d_max >= D - tol:
            tip_band = bands.pop(-1)
        # ---- ends: the end band's centroid (or the centreline) plus the mass beyond it
        ends = kernels.ends(
            xy, w, var_w, dist, line, label, *band_arrays,
            -1 if base_band is None else base_band.label,
            -1 if tip_band is None else tip_band.label,
            D, float(s.bin_px), float(s.end_slab_px), float(s.tip_direction_sigma_rad),
        )
        base, base_cov, base_mass = ends[0, :2], ends[0, 2:6].reshape(2, 2), float(ends[0, 10])
        tip, tip_cov, tip_direction = ends[1, :2], ends[1, 2:6].reshape(2, 2), ends[1, 6:8]
        tip_extent, tube_radius, tip_mass = ends[1, 8:].tolist()
        # Both end bands block the same fraction of light, so the ratio of their contrast
        # per unit length is the ratio of the tube widths there, whatever the blur: the
        # distal tube is thinner. A far end as wide as the base is the catheter folded back
        # onto itself in this view (its bending plane seen edge-on), with another band there.
        lo_x, lo_y, hi_x, hi_y = kernels.extent_beyond(xy, dist, float(D - tol))
        at_border = (
            lo_x < s.border_px
            or lo_y < s.border_px
            or hi_x > width - 1 - s.border_px
            or hi_y > height - 1 - s.border_px
        )
        width_ratio = tip_mass / base_mass if base_band is not None else float("nan")
        folded = bool(
            tip_band is not None and not at_border and width_ratio > s.max_tip_width_ratio
        )
        nan2 = _NAN2.copy()
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
        elif self.has_tip_band and tip_band is None and not overlap and not folded:
            # The far end carries no band: the tip is hidden, or the distal segment curls back
            # over itself in this view and its band may have merged with another. Either way
            # the bands cannot be told apart safely.
            flags |= SegmentationFlag.TIP_NOT_FOUND
            tip = tip_direction = nan2
            bands = []
        if abandon is not None and abandon():
            return None
        fit = None
        if s.band_fit_steps:
            fit = (np.ascontiguousarray(image), np.ascontiguousarray(background), photometry,
                   tube_radius)
        if fit is not None and tip_band is not None:
            tip_band, tip_direction, tip_extent = self._fitted_tip_band(
                fit, tip_band, tip_direction, tip_extent
            )
        tip_found = _finite_point(tip)
        if not tip_found and not flags & _TIP_WITHHELD:
            flags |= SegmentationFlag.TIP_NOT_FOUND  # too short a centreline for an end
        # ---- markers
        n_mk = self.n_markers
        markers, markers_cov = (a.copy() for a in self._no_markers)
        found = np.zeros(n_mk, bool)
        if tip_found:
            markers[self.marker_is_tip] = tip
            markers_cov[self.marker_is_tip] = tip_cov
            found[self.marker_is_tip] = True
        interior = self.interior_markers
        if interior.size:
            assigned, extra = self._assign(bands, base_band, tip_band, D)
            if fit is not None:
                assigned = [None if band is None else self._fitted_band(fit, band, line)
                            for band in assigned]
            if extra:
                flags |= SegmentationFlag.EXTRA_BANDS
            missing = False
            for k, band in zip(interior.tolist(), assigned, strict=True):
                if band is None:
                    missing = True
                else:
                    markers[k], markers_cov[k], found[k] = band.c, band.cov, True
            if missing:
                flags |= SegmentationFlag.MARKER_MISSING
        floor = self._floor
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
            bands_px=np.array([b.c for b in all_bands]).reshape(-1, 2),
            tip_band_px=nan2 if tip_band is None else tip_band.c,
            tip_band_cov=_NAN22.copy() if tip_band is None else tip_band.cov + floor,
            tip_direction=tip_direction if tip_band is not None else nan2,
            tip_extent_px=float(tip_extent) if tip_band is not None else float("nan"),
            tube_radius_px=float(tube_radius),
            tip_width_ratio=float(width_ratio),
            photometry=photometry,
        )

    def _fit(self, fit, band: _Band, direction, at_tip: bool) -> Array | None:
        """:func:`band_fit.fit_band` from a band's centroid and the catheter's direction
        there; its row, or None when the fit was dropped (the centroid stays)."""
        image, background, photometry, tube_radius = fit
        dx, dy = direction
        if not (math.isfinite(tube_radius) and math.isfinite(dx) and math.isfinite(dy)):
            return None
        # The band's pixel centres span its length less about a pixel.
        half_length = max(0.5 * (band.d_max - band.d_min) + 0.5, 1.0)
        row = band_fit.fit_band(
            image, background, photometry.lut, float(photometry.dark_gray),
            float(photometry.sigma_gray), float(band.c[0]), float(band.c[1]), float(dx),
            float(dy), float(half_length), float(tube_radius), at_tip,
            int(self.settings.band_fit_steps), _MAX_FIT_MOVE_PX,
        )
        return row if row[0] else None

    @staticmethod
    def _fitted(band: _Band, row: Array) -> _Band:
        cov = np.array([[row[5], row[6]], [row[6], row[7]]])
        return band._replace(c=row[1:3].copy(), cov=cov)

    def _fitted_band(self, fit, band: _Band, line: Array) -> _Band:
        """A marker's band placed by the fit (the centreline's direction across it to start)."""
        step = float(self.settings.bin_px)
        d = np.array([band.d - step, band.d + step])
        dx = float(np.interp(d[1], line[2], line[0]) - np.interp(d[0], line[2], line[0]))
        dy = float(np.interp(d[1], line[2], line[1]) - np.interp(d[0], line[2], line[1]))
        norm = math.hypot(dx, dy)
        if not norm > 0:
            return band
        row = self._fit(fit, band, (dx / norm, dy / norm), False)
        return band if row is None else self._fitted(band, row)

    def _fitted_tip_band(self, fit, band: _Band, direction: Array, extent: float):
        """The tip band placed by the fit, the catheter's direction from its centre to the
        band's end (the fit's chord), and the extent of the far end past the band's
        *centroid* along that direction.

        The extent stays measured from the centroid: the far end is the centroid plus the
        mass beyond it (:func:`kernels.ends`), and the centroid's offset along the catheter
        (the band's threshold cuts its blurred edge toward the tip, not the one toward the
        tube) is in the end as well, so it cancels in their difference. Measured from the
        fitted centre, which does not share it, the extent would carry that offset, which
        changes with the view's foreshortening: the pair's tangent, and its tip, would move
        with the configuration (0.07 -> 0.12 px along the catheter without noise)."""
        row = self._fit(fit, band, (float(direction[0]), float(direction[1])), True)
        if row is None:
            return band, direction, extent
        new_direction = row[3:5].copy()
        new_extent = extent * (direction[0] * new_direction[0] + direction[1] * new_direction[1])
        return self._fitted(band, row), new_direction, float(new_extent)

    def _overlapping(self, bins, D, thickness_of, bands: list[_Band], along: Array) -> bool:
        """Whether the catheter touches, crosses or folds onto itself in this view.

        Two signs. A stretch of the centreline where the mask has many more pixels per
        sample than usual and is also much thicker than the typical tube (largest inscribed
        disc, from the distance transform; side by side, or a crossing); either alone is not
        enough, since the inscribed disc is coarse at a few pixels and tight projected bends
        fan the samples out. And a "band" much longer than a band can look (the tube folded
        onto itself is as dark as a band).

        ``bins`` are the pixels' centreline samples, ``D`` the largest distance from the
        base; ``thickness_of()`` returns each pixel's inscribed radius; it is only called
        when the counts are suspicious. ``bands`` and ``along`` as :meth:`_bands` gives them.
        """
        s = self.settings
        n_bins = int(D / s.bin_px) + 1  # bins.max() + 1
        # Samples of a band (a band seen end-on is a disc wider than the tube) and of the
        # ends count 0 (kernels.sample_counts).
        count, typical_n = kernels.sample_counts(bins, n_bins, along, float(s.bin_px))
        if not typical_n > 0:  # fewer than 3 samples to judge by
            return False
        wide = count > 1.1 * s.overlap_ratio * typical_n  # (typical_n > 0: only counted ones)
        if wide.any():
            ok = count > 0
            thickness = np.zeros(n_bins)
            np.maximum.at(thickness, bins, thickness_of())
            typical_r = _median(thickness[ok])
            if np.any(thickness[wide] > s.overlap_ratio * typical_r):
                return True
        longest = 1.6 * typical_n / s.bin_px + 2.0 * s.bin_px
        return any(b.d_max - b.d_min > longest for b in bands)

    def _bands(self, index, ys, xs, w, var_w, dist, roi) -> tuple[list[_Band], Array, tuple]:
        """The radio-opaque bands (:func:`kernels.bands`: connected groups of band pixels,
        8-neighbours), ordered along the catheter; each pixel's band number (-1: none); and
        the bands as arrays (centres, covariances and distances from the base: mean, least,
        greatest). ``index``: :func:`pixel_graph.pixel_index` of the pixels ``ys``, ``xs``
        in the region ``roi``."""
        s = self.settings
        label, centres, covs, along = kernels.bands(
            index, ys, xs, w, var_w, dist, float(s.band_contrast), int(s.min_band_area_px),
            int(roi[0]), int(roi[1]),
        )
        bands = [_Band(c, cov, d, d_lo, d_hi, k)
                 for k, (c, cov, (d, d_lo, d_hi)) in enumerate(
                     zip(centres, covs, along.tolist(), strict=True))]
        return bands, label, (centres, covs, along)

    def _assign(self, bands, base_band, tip_band, D):
        """Interior bands -> interior markers: in order when the count matches, else by position."""
        n = self.interior_markers.size
        if len(bands) == n:
            return list(bands), False
        if not bands:
            return [None] * n, False
        start = base_band.d if base_band is not None else 0.0
        end = tip_band.d if tip_band is not None else D
        span = max(end - start, 1e-9)
        frac = np.array([(b.d - start) / span for b in bands])
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
