"""One camera's segmentation over time: a background that follows the scene, and a region of
interest that follows the catheter (docs/vision.md section 4).

:class:`BackgroundModel` is the empty scene of one camera, in the photometry of the image it
started from. Each frame updates a stripe of its rows (a running average of the frame mapped
back through the frame's tone curve, :mod:`tracker.vision.photometry`), leaving out the pixels
near the segmented catheter and those that differ from the model by more than
``background_gate_sigma`` noise standard deviations (the catheter even when it was not
segmented, a hand, anything new). Slow changes of the scene (a lamp drifting across it, a
warming sensor) are followed; the catheter, present from the first frame, is not burnt in.
``freeze_background`` keeps the image as given.

Every frame's shift from the model is measured to a few hundredths of a pixel
(:func:`tracker.vision.photometry.fit_shift`): a camera that vibrates gives points that
:meth:`CameraSegmenter.in_camera_frame` moves back into the background's pixels, where the
rig's calibration holds. When the shift persists (the camera moved: an average of the
frames' shifts above ``camera_moved_px``, or one frame's above three times that), the model
is re-registered by that shift if it is at most ``max_shift_px`` and the frame then fits it;
the frames are flagged CAMERA_MOVED from then on (the rig's calibration of that camera may
no longer hold).
Otherwise the frame is flagged BACKGROUND_LOST and not segmented: take a new background.

:class:`CameraSegmenter` wires one camera: the per-view :class:`Segmenter`, its background
model, the registered base in its image, and the region searched (around the points the
caller predicts, e.g. the last estimate reprojected, or else around the catheter of the last
frame; the whole image at the start and whenever the catheter is not found there).
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from tracker.vision.detection import detection_backgrounds
from tracker.vision.photometry import (
    Photometry,
    background_samples,
    fit_shift,
    register_shift,
    significant_shift,
)
from tracker.vision.segmentation import (
    NOT_SEGMENTED,
    SegmentationFlag,
    Segmenter,
    ViewSegmentation,
    shifted_back,
)
from tracker.vision.settings import SegmentationSettings, check_image
from tracker.vision.shift_pixels import ShiftSampler, shift_grid_mask

Array = np.ndarray

_REGISTRATION_STEPS = 4
# The part of the frames' shift that persists (a camera that moved, not one that vibrates):
# an exponential average of the shifts with this weight per frame. A vibration of 0.5 px
# standard deviation per axis averages to 0.21 px, so it never reaches camera_moved_px
# (1 px); a move of 3.4 px or more does on its first frame, a move of 1.5 px on its third.
_DRIFT_WEIGHT = 0.3


class BackgroundModel:
    """The empty scene of one camera, updated from the frames.

    Parameters
    ----------
    background : array (h, w), uint8
        The image of the empty scene (or of the scene with the catheter parked out of view).
    settings : SegmentationSettings
        ``freeze_background``, ``background_rate``, ``background_stripes``,
        ``background_every``, ``background_gate_sigma``, ``catheter_clearance_px``.
    phase : int
        This camera's turn among the rig's (it updates on the frames where
        ``(frame + phase) % background_every == 0``).

    Attributes
    ----------
    image : array (h, w), uint8
        The current model, as the segmentation uses it...
    prepared : pair of arrays, uint8
        ...as its detection step does (:func:`detection_backgrounds`)...
    samples : BackgroundSamples
        ...and as the photometric fit does; these are recomputed after every cycle of
        stripes (they do not need the last gray level of a slow change).
    shift_samples : ShiftSamples
        The model's pixels that the fit of each frame's shift runs over. A stripe's are
        chosen again right after the stripe's update, and all stripes' are put together on
        the camera's next frame after the cycle's last
        (:class:`tracker.vision.shift_pixels.ShiftSampler`: chosen from the whole image at
        once they cost 2 ms on one frame in sixteen).
    shift_px : array (2,)
        Total shift the model has been re-registered by since the start, px.
    """

    def __init__(self, background: Array, settings: SegmentationSettings, phase: int = 0) -> None:
        self.settings = settings
        self._frame = int(phase)
        self.image = np.array(background, np.uint8, copy=True)
        self._level = self.image.astype(np.float32)
        self._refresh()
        self._sampler = ShiftSampler(self.image, settings.background_stripes)
        self.shift_samples = self._sampler.samples
        self._stripe = 0
        self._combine = False  # every stripe's shift pixels chosen again, not yet together
        self.shift_px = np.zeros(2)

    def shifted(self, shift_px: Array) -> Array:
        """The model's gray levels (float32) with its content moved by ``shift_px`` (x, y),
        px, edges replicated; the model itself is unchanged."""
        dx, dy = (float(v) for v in shift_px)
        move = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]], np.float32)
        height, width = self.image.shape
        level = cv2.warpAffine(self._level, move, (width, height), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REPLICATE)
        return level

    def shift(self, shift_px: Array) -> None:
        """Move the model's content by ``shift_px`` (x, y), px (re-registration)."""
        self._level = self.shifted(shift_px)
        self.image = _to_u8(self._level)
        self._refresh()
        # Rare (a camera that moved) and the whole image changed: all at once.
        self.shift_samples = self._sampler.rebuild(self.image)
        self._combine = False
        self.shift_px = self.shift_px + np.asarray(shift_px, float)

    def update(
        self, image: Array, photometry: Photometry, catheter_px: list[tuple[Array, float]]
    ) -> None:
        """Average the next stripe of rows of a frame into the model (on this camera's turn).

        Parameters
        ----------
        image : array (h, w), uint8
        photometry : Photometry
            The frame's tone curve relative to this model (the frame is mapped back by its
            inverse) and noise (for the gate).
        catheter_px : list of (points (n, 2), half width px)
            Polylines along the catheter (segmented or predicted) whose neighbourhood, half
            width plus ``catheter_clearance_px``, is left out.
        """
        s = self.settings
        self._frame += 1
        if self._combine:
            # After the frame that averaged in the cycle's last stripe, which also
            # recomputed the detection's and the photometric fit's copies (_refresh): the
            # two do not fall on one frame.
            self.shift_samples = self._sampler.combine()
            self._combine = False
        if (
            s.freeze_background
            or not photometry.fitted
            or (self._frame - 1) % s.background_every
        ):
            return
        height = self.image.shape[0]
        rows_per = -(-height // s.background_stripes)
        y0 = self._stripe * rows_per
        y1 = min(y0 + rows_per, height)
        self._stripe = (self._stripe + 1) % s.background_stripes
        if y1 <= y0:
            return
        # The frame in the model's photometry, and the pixels within the gate of the model.
        in_photometry = cv2.LUT(image[y0:y1], photometry.inverse_lut())
        dx, dy = significant_shift(photometry).tolist()
        if dx or dy:
            # A frame shifted from the model (a vibration) is moved back before it is
            # averaged in: averaging shifted frames would blur the model.
            top, bottom = max(y0 - _MARGIN_ROWS, 0), min(y1 + _MARGIN_ROWS, height)
            move = np.array([[1.0, 0.0, -dx], [0.0, 1.0, top - y0 - dy]], np.float32)
            in_photometry = cv2.warpAffine(
                cv2.LUT(image[top:bottom], photometry.inverse_lut()), move,
                (in_photometry.shape[1], y1 - y0), flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
        level = self._level[y0:y1]
        gate = s.background_gate_sigma * max(photometry.sigma_gray, 1.0) / max(photometry.gain, 0.1)
        mask = cv2.compare(cv2.absdiff(in_photometry, level), gate, cv2.CMP_LE)
        one = 1 << _SHIFT
        for points, half_width_px in catheter_px:
            points = np.asarray(points, float).reshape(-1, 2)
            if not np.isfinite(points).all():
                points = points[np.isfinite(points).all(axis=1)]
            thickness = math.ceil(2.0 * (half_width_px + s.catheter_clearance_px))
            if points.size == 0:
                continue
            rows = points[:, 1]
            if not (rows.min() - thickness < y1 and rows.max() + thickness > y0):
                continue
            # Fixed point in the stripe: y0 is whole, so shifting after rounding is exact.
            fixed = np.rint(points * one).astype(np.int32)
            fixed[:, 1] -= y0 * one
            cv2.polylines(mask, [fixed], False, 0, thickness, cv2.LINE_8, _SHIFT)
            for x, y in (fixed[0].tolist(), fixed[-1].tolist()):
                cv2.circle(mask, (x, y), (thickness * one) // 2, 0, -1, cv2.LINE_8, _SHIFT)
        cv2.accumulateWeighted(in_photometry, level, s.background_rate, mask)
        self.image[y0:y1] = _to_u8(level)
        # The shift's pixels of the stripe, chosen again now that its rows are in the cache
        # (on the camera's next frame the pair's median was 0.1 ms longer); all stripes'
        # put together on that next frame after the last one.
        stripe = y0 // rows_per
        self._sampler.resample(self.image, stripe)
        self._combine = stripe == self._sampler.stripes - 1
        if self._stripe == 0:
            self._refresh()

    def _refresh(self) -> None:
        """Recompute what the detection and the photometric fit keep of the model."""
        self.prepared = detection_backgrounds(self.image)
        self.samples = background_samples(self.image, self.settings.noise_stride_px)


_SHIFT = 2  # fractional bits of the polyline coordinates given to OpenCV
_MARGIN_ROWS = 4  # rows around a stripe read to move it back by a frame's shift


def _to_u8(level: Array) -> Array:
    """Gray levels (float32, >= 0) rounded to 8 bits, saturated."""
    return cv2.convertScaleAbs(level)


class CameraSegmenter:
    """Segments the frames of one camera.

    Parameters
    ----------
    segmenter : Segmenter
        The per-view segmentation of the catheter (its settings apply here too).
    background : array (h, w), uint8
        The camera's image of the empty scene.
    base_px : array (2,), optional
        The registered base projected into this camera, px.
    name : str
        The camera's name in error messages.
    index : int
        The camera's place in the rig (the cameras take turns to update their backgrounds).
    """

    def __init__(
        self,
        segmenter: Segmenter,
        background: Array,
        base_px: Array | None = None,
        name: str = "camera",
        index: int = 0,
    ) -> None:
        self.segmenter = segmenter
        self.settings = segmenter.settings
        self.name = name
        background = check_image(background, f"{name} background image")
        self.background = BackgroundModel(background, self.settings, index)
        self.base_px = None if base_px is None else np.asarray(base_px, float).reshape(2)
        self.last: ViewSegmentation | None = None
        self.noise_gray: float | None = None  # running estimate of the sensor noise
        self._drift_px = np.zeros(2)  # the persistent part of the frames' shift (x, y), px
        self._pending: tuple | None = None  # a frame's background update not yet made

    @property
    def shift_px(self) -> Array:
        """How far the camera's image has moved since its background was captured, px."""
        return self.background.shift_px

    def reset(self) -> None:
        """Forget the last frame (the next one is searched whole); the background stays."""
        self.last = None

    def _moved(self, photometry: Photometry, flags: SegmentationFlag) -> bool:
        """Whether the camera has moved from its background model: the persistent part of
        the frames' shift (an exponential average) beyond ``camera_moved_px``, or this
        frame's beyond three times that. A camera that vibrates is not re-registered on
        every frame: each frame's shift is taken out of its points instead
        (:meth:`in_camera_frame`)."""
        if flags & SegmentationFlag.EXPOSURE or not photometry.fitted:
            return False
        shift = photometry.shift_px
        self._drift_px = (1.0 - _DRIFT_WEIGHT) * self._drift_px + _DRIFT_WEIGHT * shift
        limit = self.settings.camera_moved_px
        return (
            math.hypot(*self._drift_px.tolist()) > limit
            or math.hypot(*shift.tolist()) > 3.0 * limit
        )

    def segment(
        self, image: Array, predicted_px: Array | None = None, *, settle: bool = True
    ) -> ViewSegmentation:
        """Segment one frame, then update the background and the region of interest.

        Parameters
        ----------
        image : array (h, w), uint8
        predicted_px : array (n, 2), optional
            Where the catheter's points are expected in this image (e.g. the last estimate's
            points reprojected), px: the search starts in the region around them and the
            base. Without them, the region around the last frame's catheter.
        settle : bool
            Average the frame into the background model now. With False the update waits
            for :meth:`settle` (the live loop calls it once the estimate has left, so that
            it is off the critical path), or for the next frame at the latest; the results
            are the same either way. ``image`` must not be changed meanwhile.

        Returns
        -------
        ViewSegmentation
            In the frame's pixels; its ``photometry.shift_px`` is the frame's shift from the
            background model, refined on a dense grid (:func:`fit_shift`), and
            :meth:`in_camera_frame` moves the points into the pixels of the camera's
            background image as it was given.
        """
        image = check_image(image, f"{self.name} image", self.background.image.shape)
        self.settle()
        s = self.settings
        segmenter = self.segmenter
        model = self.background
        photometry = segmenter.photometry(image, model.image, model.samples)
        flags = segmenter.photometry_flags(photometry)
        extra = SegmentationFlag.NONE
        if self._moved(photometry, flags):
            photometry, extra = self._reregister(image, photometry)
            self._drift_px = np.zeros(2)
        if math.hypot(*model.shift_px.tolist()) > s.camera_moved_px:
            extra |= SegmentationFlag.CAMERA_MOVED
        if extra & SegmentationFlag.BACKGROUND_LOST:
            seg = segmenter.empty_result(flags | extra, photometry)
        else:
            seg = segmenter.segment(
                image, model.image, self.base_px, photometry=photometry,
                search_px=self._search_points(predicted_px),
                prepared=model.prepared,
            )
        lines = self._catheter_lines(seg)
        if photometry.fitted and not seg.flags & NOT_SEGMENTED:
            # The frame's shift to a few hundredths of a pixel, on the background around
            # the catheter: what in_camera_frame takes out of the points.
            clearance = s.catheter_clearance_px
            photometry = fit_shift(
                image, model.shift_samples, photometry,
                shift_grid_mask(model.shift_samples, [(p, w + clearance) for p, w in lines]),
            )
            seg = dataclasses.replace(seg, flags=seg.flags | extra, photometry=photometry)
            self.noise_gray = (
                photometry.sigma_gray if self.noise_gray is None
                else 0.9 * self.noise_gray + 0.1 * photometry.sigma_gray
            )
            self._pending = (image, photometry, lines)
            if settle:
                self.settle()
        elif extra:
            seg = dataclasses.replace(seg, flags=seg.flags | extra)
        if seg.centreline_px.shape[0] >= 2:
            self.last = seg
        elif seg.flags & SegmentationFlag.NO_CATHETER:
            self.last = None
        return seg

    def settle(self) -> None:
        """Average the last frame segmented with ``settle=False`` into the background model
        (nothing when there is none pending)."""
        pending, self._pending = self._pending, None
        if pending is not None:
            self.background.update(*pending)

    def rehearse(
        self, image: Array, predicted_px: Array | None = None, abandon=None
    ) -> bool:
        """Segment ``image`` as :meth:`segment` would, and change nothing: no background
        update, no shift, no region kept (``LiveTracker.prime`` runs it on the last frame
        just before the next one is due, so that the segmentation's code and data are back
        in the processor's caches when it comes). ``abandon``: asked between the stages,
        True stops the rehearsal (the frame has come). False if it was stopped."""
        self.settle()
        model = self.background
        photometry = self.segmenter.photometry(image, model.image, model.samples)
        if self.segmenter.photometry_flags(photometry) & NOT_SEGMENTED:
            return True
        if abandon is not None and abandon():
            return False
        seg = self.segmenter.segment(
            image, model.image, self.base_px, photometry=photometry,
            search_px=self._search_points(predicted_px), prepared=model.prepared,
            abandon=abandon,
        )  # fmt: skip
        return seg is not None  # None only when abandoned

    def in_camera_frame(self, seg: ViewSegmentation) -> ViewSegmentation:
        """A segmentation of this camera moved from the frame's pixels into those of the
        background image it was given (where the rig's calibration holds).

        The frame's shift is the background model's re-registration (``shift_px``) plus
        the frame's own shift from the model (a vibration) where it stands out of its
        uncertainty (:func:`tracker.vision.photometry.significant_shift`), whose covariance
        is then added to the points'. A shift of the whole image is a small rotation of the
        camera about its centre: to first order the points are then where the calibrated
        camera sees the catheter.
        """
        photometry = seg.photometry
        own = np.zeros(2) if photometry is None else significant_shift(photometry)
        total = self.background.shift_px + own
        if not (total.any()):
            return seg
        cov = photometry.shift_cov_px2 if own.any() else None
        return shifted_back(seg, total, cov)

    # ------------------------------------------------------------------ steps
    def _search_points(self, predicted_px: Array | None) -> Array | None:
        if self.settings.roi_pad_px <= 0:
            return None
        if predicted_px is not None:
            points = [np.asarray(predicted_px, float).reshape(-1, 2)]
        elif self.last is not None:
            points = [self.last.centreline_px, self.last.tip_px[None]]
        else:
            return None
        if self.base_px is not None:
            points.append(self.base_px[None])
        return np.concatenate(points)

    def _catheter_lines(self, seg: ViewSegmentation) -> list[tuple[Array, float]]:
        """The catheter's centreline of this frame, or of the last frame if none was found."""
        source = seg if seg.centreline_px.shape[0] >= 2 else self.last
        if source is None:
            return []
        radius = source.tube_radius_px if math.isfinite(source.tube_radius_px) else 4.0
        # The proximal tube is wider than the distal radius measured at the tip: 1.2 / 0.89.
        return [(source.centreline_px, 1.5 * radius)]

    def _reregister(self, image: Array, photometry: Photometry):
        """Shift the model onto a frame that moved; (photometry, flags) of the outcome."""
        s = self.settings
        segmenter = self.segmenter
        shift = np.asarray(photometry.shift_px, float)
        if np.hypot(*shift) > 0.5 * s.max_shift_px:
            # Beyond the first-order estimate's reach: phase correlation first.
            coarse = register_shift(image, self.background.image, photometry, s.max_shift_px)
            if coarse is None:
                return photometry, SegmentationFlag.BACKGROUND_LOST
            shift = coarse
        total = np.zeros(2)
        for _ in range(_REGISTRATION_STEPS):
            total = total + shift
            if np.hypot(*total) > s.max_shift_px:
                return photometry, SegmentationFlag.BACKGROUND_LOST
            moved = _to_u8(self.background.shifted(total))
            photometry = segmenter.photometry(image, moved)
            shift = np.asarray(photometry.shift_px, float)
            if np.hypot(*shift) < 0.1 * s.camera_moved_px:
                break
        expected = self.noise_gray if self.noise_gray is not None else photometry.sigma_gray
        registered = (
            np.hypot(*shift) <= 0.5 * s.camera_moved_px
            and photometry.sigma_gray <= 1.5 * expected + 1.0
        )
        if not registered:
            return photometry, SegmentationFlag.BACKGROUND_LOST
        self.background.shift(total)
        return photometry, SegmentationFlag.CAMERA_MOVED
