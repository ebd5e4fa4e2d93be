"""Segmentation of a synchronised set of views of a rig (docs/design.md sections 4, 6).

Each view is segmented on its own (:class:`tracker.vision.segmentation.Segmenter`; over time,
:class:`tracker.vision.background.CameraSegmenter`, with a background that follows the scene
and a region of interest that follows the catheter); then, with the rig
(:func:`combine_views`, used by :func:`segment_pair` and :class:`PairSegmenter`): an epipolar
check of every point found in two or more views, and the tip placed in 3-D from the tip
band's centre (unbiased in every view however the tip points) and the catheter's tangent,
which removes the bias of a single view's far end when the tip points toward a camera. The
result maps onto the rows ``[tip, marker_0, ...]`` of each view of
:class:`tracker.types.Frame`, in the rig's view order (``rig.names``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from models.catheter import Catheter
from models.imaging import PinholeView, Rig
from tracker.types import Frame
from tracker.vision import kernels, pair_kernels
from tracker.vision.background import CameraSegmenter
from tracker.vision.segmentation import Segmenter, ViewSegmentation, frame_points
from tracker.vision.settings import DEFAULT_SETTINGS, SegmentationSettings, check_image

Array = np.ndarray


@dataclass(frozen=True)
class PairSegmentation:
    """Every view of a synchronised frame, and the rows of a pipeline Frame.

    Attributes
    ----------
    views : tuple of ViewSegmentation
        One per view, in the rig's order.
    uv : tuple of arrays (1 + n_markers, 2)
        Each view's rows ``[tip, marker_0, ...]``, px, NaN for points not found or rejected.
    cov : tuple of arrays (1 + n_markers, 2, 2)
        px^2, NaN where the point is missing.
    rejected : array (1 + n_markers,) of bool
        Rows found in two or more views whose rays do not meet (epipolar check): withheld in
        every view, since one of them has picked the wrong point (the catheter overlapping
        itself in that view).
    tip_refined : bool
        The tip was placed from the tip band of two or more views (see
        :func:`combine_views`).
    """

    views: tuple[ViewSegmentation, ...]
    uv: tuple[Array, ...]
    cov: tuple[Array, ...]
    rejected: Array
    tip_refined: bool = False

    def frame(
        self,
        time_s: float,
        q: Array,
        q_dot: Array | None = None,
        images: Sequence[Array] | None = None,
        delta_L_true_rad: float | None = None,
    ) -> Frame:
        """The pipeline frame of these views at the given time and joint values."""
        return Frame(
            time_s=float(time_s),
            q=np.asarray(q, float),
            q_dot=None if q_dot is None else np.asarray(q_dot, float),
            uv=self.uv,
            cov=self.cov,
            images=None if images is None else tuple(images),
            delta_L_true_rad=delta_L_true_rad,
        )


def _unit_sphere(n: int) -> Array:
    """n nearly uniform unit vectors (Fibonacci lattice), as the columns of a (3, n) array."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z**2)
    return np.array([r * np.cos(phi), r * np.sin(phi), z])


# Sets of directions are (3, n) arrays: numpy works along rows of n far faster than along
# rows of 3.
_COARSE = _unit_sphere(200)  # about 15 degrees apart
_CAP_RAD = np.radians(16.0)


def _cap(n: int, angle_rad: float) -> Array:
    """n nearly uniform unit vectors within ``angle_rad`` of +z, as the columns of (3, n)."""
    k = np.arange(n) + 0.5
    z = 1.0 - (1.0 - np.cos(angle_rad)) * k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z**2)
    return np.array([r * np.cos(phi), r * np.sin(phi), z])


_FINE = _cap(100, _CAP_RAD)  # about 3 degrees apart


def segment_pair(
    segmenter: Segmenter,
    images: Sequence[Array],
    backgrounds: Sequence[Array],
    base_px: Sequence[Array | None] | None = None,
    rig: Rig | None = None,
) -> PairSegmentation:
    """Segment one synchronised frame of every view into the fields of a pipeline Frame.

    Each image against its fixed background, searched whole (no state; see
    :class:`PairSegmenter` for backgrounds and regions of interest that follow).

    Parameters
    ----------
    segmenter : Segmenter
    images, backgrounds : sequences of uint8 arrays (h, w)
        One frame and its empty-scene prior per view, in the rig's order.
    base_px : sequence of arrays (2,) or None, optional
        The registered base projected into each view.
    rig : Rig, optional
        See :func:`combine_views`.
    """
    if base_px is None:
        base_px = (None,) * len(images)
    views = tuple(
        segmenter.segment(image, background, base)
        for image, background, base in zip(images, backgrounds, base_px, strict=True)
    )
    return combine_views(segmenter, views, rig)


_NUDGE_MM = 1e-3  # finite-difference step of the projection Jacobians at the tip band


@functools.lru_cache(maxsize=16)
def _cameras(rig: Rig) -> tuple[Array, ...]:
    """A pinhole rig's cameras stacked view by view, read-only, as
    :func:`pair_kernels.check_rows` takes them: R_cam_w (V, 3, 3), t_cam_w (V, 3), the
    rotations OpenCV projects with (V, 3, 3: of the Rodrigues vectors, as
    :meth:`PinholeView.project`), fx, fy, cx, cy (V, 4) and the distortion (V, 5)."""
    views = rig.views
    R_project = [cv2.Rodrigues(cv2.Rodrigues(np.array(v.R_cam_w))[0])[0] for v in views]
    arrays = (
        np.array([v.R_cam_w for v in views]),
        np.array([v.t_cam_w for v in views]),
        np.array(R_project),
        np.array([[v.K[0, 0], v.K[1, 1], v.K[0, 2], v.K[1, 2]] for v in views]),
        np.array([v.dist for v in views]),
    )
    for a in arrays:
        a.flags.writeable = False
    return arrays


def _stacked(views: tuple[ViewSegmentation, ...], tip_rows: Array) -> tuple[Array, ...]:
    """The views' points, covariances, markers found and tip bands in the arrays of
    :func:`pair_kernels.check_rows` (``uv``, ``cov``, ``found``, ``band``)."""
    V, R = len(views), tip_rows.shape[0]
    uv = np.empty((V, R, 2))
    cov = np.empty((V, R, 2, 2))
    found = np.empty((V + 1, R), bool)
    band = np.empty((V, pair_kernels.BAND_ROWS, 2))
    found[V] = tip_rows
    for k, view in enumerate(views):
        uv[k, 0] = view.tip_px
        uv[k, 1:] = view.markers_px
        cov[k, 0] = view.tip_cov
        cov[k, 1:] = view.markers_cov
        found[k, 1:] = view.markers_found
        b = band[k]
        b[pair_kernels.BAND_PX] = view.tip_band_px
        b[pair_kernels.BAND_DIRECTION] = view.tip_direction
        b[pair_kernels.BAND_EXTENT_RADIUS] = (view.tip_extent_px, view.tube_radius_px)
        b[pair_kernels.BAND_COV :] = view.tip_band_cov
    return uv, cov, found, band


def combine_views(
    segmenter: Segmenter, views: Sequence[ViewSegmentation], rig: Rig | None = None
) -> PairSegmentation:
    """The frame's rows from its views' segmentations, checked and refined with the rig.

    Parameters
    ----------
    segmenter : Segmenter
        The segmenter of the views (its settings and marker layout).
    views : sequence of ViewSegmentation
        One per view, in the rig's order.
    rig : Rig, optional
        The calibrated pinhole rig of the images. With it, two cross-view steps run: rows
        found in two or more views whose reprojections miss a view's point by more than the
        epipolar gate (or four times the points' spread) are withheld (``rejected``); and
        when two or more views see the tip band, the tip is placed in 3-D from the band's
        centre and the catheter's tangent and projected back into those views. This removes
        the bias of a single view's far end when the tip points toward the camera (the end
        disc of the tube sticks out past the end point).

    Notes
    -----
    The tip: the band's centroid is the projection of its centre in every view whatever the
    foreshortening, so the centre is triangulated from the centroids. The tangent t is the
    unit vector that best explains, in every view, where the image ends past the centroid:
    ``half_band t`` projects to an image vector p (short when t points at the camera), and
    the end disc of the tube sticks out past the tip by ``pi/4 R |sin a|`` (R the tube's
    image radius, a the angle between t and the image plane). Per view the residuals are
    p's offset across the measured direction and the measured extent minus
    ``p . direction + pi/4 R |sin a|``, px; their squares are summed over the views and
    minimised over the sphere of directions (:func:`tracker.vision.kernels.tip_tangent`: a
    coarse grid, then a fine cap around its best). A view where the tip points at the camera
    has a short p and an end that is a disc: its poorly defined direction then costs little,
    which is what makes this robust where intersecting the planes of the image directions
    is not.

    The arithmetic runs in two compiled calls (:mod:`tracker.vision.pair_kernels`) with the
    tangent's search between them.
    """
    s = segmenter.settings
    views = tuple(views)
    if rig is None:
        rows = [frame_points(view) for view in views]
        uv, cov = tuple(r[0] for r in rows), tuple(r[1] for r in rows)
        return PairSegmentation(views, uv, cov, np.zeros(uv[0].shape[0], bool))
    if rig.kind != "pinhole":
        raise ValueError("combine_views needs the pinhole rig the images were taken with")
    if len(views) != rig.n_views:
        raise ValueError(
            f"need one segmentation per view ({', '.join(rig.names)}), got {len(views)}"
        )
    uv, cov, found, band = _stacked(views, segmenter.frame_tip_rows)
    half_band = 0.5 * float(s.band_length_mm)
    status, rejected, refined, centre_w, geometry, linear, extent, cap_px = (
        pair_kernels.check_rows(
            uv, cov, found, band, *_cameras(rig), float(s.epipolar_gate_px), half_band,
            _NUDGE_MM,
        )
    )  # fmt: skip
    if status != pair_kernels.OK:
        raise ValueError(
            "cannot triangulate a row of the views' points: their viewing rays are parallel"
            " (a point on the line through the camera centres?)"
            if status == pair_kernels.PARALLEL_RAYS
            else "a row of the views' points triangulates at or behind a camera (a pinhole"
            " view needs depth > 0)"
        )
    if refined:
        tangent, misfit = kernels.tip_tangent(linear, extent, cap_px, _COARSE, _FINE)
        pair_kernels.place_tip(
            uv, cov, found, band, rejected, centre_w, geometry, tangent, misfit, half_band,
            float(s.tip_direction_sigma_rad),
        )  # fmt: skip
    return PairSegmentation(views, tuple(uv), tuple(cov), rejected, refined)


class PairSegmenter:
    """Segments synchronised frames of one rig, catheter and registered base, over time.

    One :class:`tracker.vision.background.CameraSegmenter` per view of the rig (its
    background model follows slow changes of the scene and re-registers a camera that moved;
    its region of interest follows the catheter), then the cross-view steps of
    :func:`combine_views`. Making it loads the compiled kernels of the segmentation and of
    the cross-view steps (or compiles them, a few seconds the first time on a machine;
    through its :class:`Segmenter`, :func:`tracker.vision.kernels.warm_up`, and
    :func:`tracker.vision.pair_kernels.warm_up`), so the first frame does not wait for
    them.

    Parameters
    ----------
    catheter : Catheter
    rig : Rig
        Pinhole rig of the cameras (e.g. :func:`models.rig_file.load_rig`).
    R_w_b, o_b_w_mm : arrays (3, 3), (3,)
        Registered base pose; its origin projected into each view picks the catheter and
        its base end.
    backgrounds : sequence of uint8 arrays
        Prior images of the empty scene, one per view in the rig's order, of the views'
        image sizes.
    settings : SegmentationSettings
    """

    def __init__(
        self,
        catheter: Catheter,
        rig: Rig,
        R_w_b: Array,
        o_b_w_mm: Array,
        backgrounds: Sequence[Array],
        settings: SegmentationSettings = DEFAULT_SETTINGS,
    ) -> None:
        if rig.kind != "pinhole":
            raise ValueError("PairSegmenter needs a pinhole rig (images are in pixels)")
        if len(backgrounds) != rig.n_views:
            raise ValueError(
                f"need one background image per view ({', '.join(rig.names)}),"
                f" got {len(backgrounds)}"
            )
        self.rig = rig
        self.segmenter = Segmenter(catheter, settings)
        pair_kernels.warm_up()
        o = np.asarray(o_b_w_mm, float)
        self.cameras = tuple(
            CameraSegmenter(self.segmenter, _sized(bg, view, name), view.project(o), name, k)
            for k, (bg, view, name) in enumerate(
                zip(backgrounds, rig.views, rig.names, strict=True)
            )
        )

    @property
    def backgrounds(self) -> tuple[Array, ...]:
        """Each camera's current background model (uint8), the last frame averaged in."""
        self.settle()
        return tuple(camera.background.image for camera in self.cameras)

    @property
    def base_px(self) -> tuple[Array, ...]:
        """The registered base projected into each camera, px."""
        return tuple(camera.base_px for camera in self.cameras)

    def reset(self) -> None:
        """Search the next frame's images whole (the backgrounds are kept)."""
        for camera in self.cameras:
            camera.reset()

    def segment(
        self,
        images: Sequence[Array],
        predicted_px: Sequence[Array | None] | None = None,
        *,
        settle: bool = True,
        meanwhile: Callable[[], None] | None = None,
    ) -> PairSegmentation:
        """Segment one synchronised frame (one image per view, in the rig's order).

        Parameters
        ----------
        images : sequence of uint8 arrays (h, w)
        predicted_px : sequence of arrays (n, 2) or None, optional
            Where the catheter's points are expected in each image (e.g. the last estimate's
            points reprojected), px; each camera searches around them first (see
            :meth:`CameraSegmenter.segment`).
        settle : bool
            Average the frame into the background models now; with False, at
            :meth:`settle` (see :meth:`CameraSegmenter.segment`).
        meanwhile : callable, optional
            Called once with no arguments before the views are combined: work of the
            caller's that can overlap a view segmented elsewhere (here it just runs).
        """
        if len(images) != len(self.cameras):
            raise ValueError(
                f"need one image per view ({', '.join(self.rig.names)}), got {len(images)}"
            )
        if predicted_px is None:
            predicted_px = (None,) * len(self.cameras)
        # Each camera's points moved out of its frame's shift (a vibration, a re-registered
        # move) into the pixels where the rig's calibration holds.
        views = tuple(
            camera.in_camera_frame(camera.segment(image, predicted, settle=settle))
            for camera, image, predicted in zip(self.cameras, images, predicted_px, strict=True)
        )
        if meanwhile is not None:
            meanwhile()
        return combine_views(self.segmenter, views, self.rig)

    def settle(self) -> None:
        """Average a frame segmented with ``settle=False`` into the background models."""
        for camera in self.cameras:
            camera.settle()

    def close(self) -> None:
        """Nothing to release (as :class:`tracker.vision.parallel.ParallelPairSegmenter`'s
        ``close``, which stops its worker process; either is a context manager)."""

    def __enter__(self) -> PairSegmenter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def rehearse(
        self,
        images: Sequence[Array],
        predicted_px: Sequence[Array | None] | None = None,
        abandon: Callable[[], bool] | None = None,
    ) -> bool:
        """:meth:`segment` without its result and without changing anything
        (:meth:`CameraSegmenter.rehearse`): the live loop warms the processor's caches with
        it just before a frame is due. ``abandon``: asked between the stages, True stops
        the rehearsal (the frame has come); False if it was stopped."""
        if predicted_px is None:
            predicted_px = (None,) * len(self.cameras)
        for camera, image, predicted in zip(self.cameras, images, predicted_px, strict=True):
            if not camera.rehearse(image, predicted, abandon):
                return False
        return True

    def frame(
        self,
        time_s: float,
        q: Array,
        images: Sequence[Array],
        q_dot: Array | None = None,
        delta_L_true_rad: float | None = None,
    ) -> Frame:
        """Segment a frame's images and return the pipeline Frame (images attached)."""
        return self.segment(images).frame(time_s, q, q_dot, images, delta_L_true_rad)


def _sized(background: Array, view: PinholeView, name: str) -> Array:
    """The background image, checked to be 8-bit of the camera's image size."""
    return check_image(
        background, f"{name} background image", (view.image_size[1], view.image_size[0])
    )
