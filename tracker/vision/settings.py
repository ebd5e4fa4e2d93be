"""Segmentation settings and image input (docs/design.md sections 4, 6).

:class:`SegmentationSettings` holds the thresholds of :mod:`tracker.vision.segmentation` and
:mod:`tracker.vision.pair`, read from the ``[segmentation]`` table of a TOML file
(docs/vision.md) and validated on load. :func:`read_grayscale` and :func:`check_image` turn
bad input into one clear ``OSError`` / ``ValueError``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from models.model_file import read_toml_file

Array = np.ndarray

SETTINGS_FORMAT = "cathtrack-segmentation"

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
    band_fit_steps : int
        Gauss-Newton steps of the fit that places the tip band and the markers' bands
        (:mod:`tracker.vision.band_fit`: a local tube-and-band model fitted to the contrast
        of every pixel near the band, about three times less scatter than the centroid at 8
        gray levels of noise); 0 keeps the contrast-weighted centroids.
    normalise : bool
        Fit each frame's tone curve (gain, offset, gamma) to its background before the
        subtraction (:mod:`tracker.vision.photometry`); off: the frame is taken to have the
        background's photometry.
    max_gain_change : float
        A frame whose gain relative to the background is outside ``[1 / this, this]``...
    max_clipped_fraction : float
        ...or with more than this fraction of its pixels black or saturated is flagged
        EXPOSURE and not segmented.
    camera_moved_px : float
        A frame shifted by more than this from its background is flagged CAMERA_MOVED (the
        background model is re-registered to it).
    max_shift_px : float
        Largest shift the background model is re-registered by; a frame that does not
        register within it is flagged BACKGROUND_LOST (take a new background).
    roi_pad_px : float
        Padding of the region searched around the catheter's predicted image, px (0: always
        search the whole image).
    freeze_background : bool
        Keep the background image as given (no update from the frames).
    background_rate : float
        Weight of a frame in the background's running average, per update of a pixel.
    background_stripes : int
        The rows of the image are updated in this many stripes, one at a time...
    background_every : int
        ...every this many frames (the cameras of a rig take turns): a pixel is updated every
        ``background_stripes x background_every`` frames.
    background_gate_sigma : float
        Pixels differing from the background by more than this many noise standard
        deviations are not averaged in (a catheter, a hand, anything new in the scene).
    catheter_clearance_px : float
        Nor are pixels within this distance of the segmented or predicted catheter, px.
    """

    threshold_sigma: float = 6.0
    min_threshold_gray: float = 12.0
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
    noise_stride_px: int = 12
    overlap_ratio: float = 1.45
    epipolar_gate_px: float = 3.0
    max_tip_width_ratio: float = 0.88
    tip_band: bool = True
    tip_direction_sigma_rad: float = 0.03
    band_fit_steps: int = 3
    normalise: bool = True
    max_gain_change: float = 2.0
    max_clipped_fraction: float = 0.5
    camera_moved_px: float = 1.0
    max_shift_px: float = 8.0
    roi_pad_px: float = 40.0
    freeze_background: bool = False
    background_rate: float = 0.1
    background_stripes: int = 8
    background_every: int = 2
    background_gate_sigma: float = 4.0
    catheter_clearance_px: float = 6.0

    def __post_init__(self) -> None:
        positive = (
            "threshold_sigma", "band_length_mm", "bin_px", "end_slab_px", "max_noise_gray",
            "base_search_px", "overlap_ratio", "epipolar_gate_px", "max_tip_width_ratio",
            "camera_moved_px", "max_shift_px", "background_gate_sigma",
        )
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and np.isfinite(value) and value > 0):
                raise ValueError(f"segmentation setting {name} must be positive, got {value!r}")
        non_negative = (
            "min_threshold_gray", "max_gap_px", "border_px", "sigma_floor_px",
            "tip_direction_sigma_rad", "roi_pad_px", "catheter_clearance_px",
        )
        for name in non_negative:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and np.isfinite(value) and value >= 0):
                raise ValueError(f"segmentation setting {name} must be >= 0, got {value!r}")
        if not (isinstance(self.band_fit_steps, int) and self.band_fit_steps >= 0):
            raise ValueError(
                f"segmentation setting band_fit_steps must be an int >= 0, got"
                f" {self.band_fit_steps!r}"
            )
        if not (isinstance(self.band_contrast, int | float) and 0 < self.band_contrast < 1):
            raise ValueError(
                "segmentation setting band_contrast must lie in (0, 1),"
                f" got {self.band_contrast!r}"
            )
        for name in ("min_area_px", "min_band_area_px", "closing_px", "noise_stride_px",
                     "background_stripes", "background_every"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ValueError(
                    f"segmentation setting {name} must be an integer >= 0, got {value!r}"
                )
        for name in ("tip_band", "normalise", "freeze_background"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(
                    f"segmentation setting {name} must be true or false,"
                    f" got {getattr(self, name)!r}"
                )
        for name in ("noise_stride_px", "background_stripes", "background_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"segmentation setting {name} must be >= 1")
        if not (isinstance(self.max_gain_change, int | float) and self.max_gain_change > 1):
            raise ValueError(
                f"segmentation setting max_gain_change must be > 1, got {self.max_gain_change!r}"
            )
        for name in ("max_clipped_fraction", "background_rate"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and 0 < value <= 1):
                raise ValueError(f"segmentation setting {name} must lie in (0, 1], got {value!r}")


DEFAULT_SETTINGS = SegmentationSettings()


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
    data = read_toml_file(path, ValueError, "settings")
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
