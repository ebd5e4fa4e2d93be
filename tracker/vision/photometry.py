"""Photometric normalisation of a frame to its background image (docs/vision.md section 4).

Between the capture of the background and a frame, a camera's automatic exposure, a lamp's
drift or a fluoroscope's automatic brightness control change the gain by 5-10 %, the dark
level moves, the response curve (gamma) may change, and the camera may be shifted. A fixed
prior subtracted as it is then finds the catheter everywhere or nowhere.

:func:`fit_photometry` fits, on a sparse grid of pixels, the frame's gray level as a smooth
tone curve of the background's (a polynomial of degree up to 2: a gain, an offset and a
curvature, enough for a gamma of 0.9 to 1.1) plus a shift of the whole image to first order
(the background's gradient times the shift). The fit is robust: a least-squares fit, then a
second one without the pixels beyond four robust standard deviations (the catheter, an
occluder); saturated pixels take no part. Its residual is the frame's noise estimate, and
``f(0)`` its black level (contrasts are fractions of the light above it, so an offset does
not change them).

:func:`fit_shift` refines the shift on the background's pixels of the strongest gradient
(:mod:`tracker.vision.shift_pixels`), to a few hundredths of a pixel (a camera that
vibrates is corrected frame by frame,
:meth:`tracker.vision.background.CameraSegmenter.in_camera_frame`), and
:func:`significant_shift` says whether it stands out of its own uncertainty.

Limits: one tone curve for the whole image (a gain that varies across the image and changes
from frame to frame is not followed, only a slow one through the background model's update,
:mod:`tracker.vision.background`); the shift is first order, exact to a fraction of a pixel
for shifts below about the texture's scale (see :func:`register_shift` for larger ones);
a background of a single gray level gives the gain only (no offset or curvature: with one
level they cannot be told apart, and do not need to be).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from tracker.vision import photometry_kernels, shift_kernels
from tracker.vision.shift_pixels import ShiftSamples

Array = np.ndarray

LEVELS = np.arange(256, dtype=np.float64)
_UNSATURATED = (LEVELS > 0) & (LEVELS < 255)  # per gray level: neither black nor saturated
_MIN_SAMPLES = 50


@dataclass(frozen=True)
class Photometry:
    """How a frame's gray levels relate to those of its background image.

    ``frame(p) = f(background(p - shift_px)) + noise`` away from the catheter.

    Attributes
    ----------
    lut : array (256,), float32
        ``f`` at every background gray level (non-decreasing), gray levels.
    shift_px : array (2,)
        Shift of the frame's content relative to the background (x, y), px, to first order.
    sigma_gray : float
        Robust standard deviation of the residual (sensor noise, quantisation, anything the
        fit does not explain), gray levels.
    gain : float
        Slope of ``f`` at the background's mean gray level (1: unchanged exposure).
    clipped_fraction : float
        Fraction of the grid's pixels saturated (0 or 255) in the frame.
    fitted : bool
        False when too few pixels could be used (a black or saturated frame).
    dark_gray : float
        The frame's gray level where the background's is 0: its black level (an offset the
        light does not scale), ``f(0)`` extrapolated, within a quarter of ``f`` at the
        background's mean level.
    shift_cov_px2 : array (2, 2), optional
        The covariance of ``shift_px`` when refined on a dense grid (:func:`fit_shift`),
        px^2; None for the first-order estimate alone.
    """

    lut: Array
    shift_px: Array
    sigma_gray: float
    gain: float = 1.0
    clipped_fraction: float = 0.0
    fitted: bool = True
    dark_gray: float = 0.0
    shift_cov_px2: Array | None = None

    @property
    def lut_u8(self) -> Array:
        """``f`` rounded to 8 bits, for :func:`cv2.LUT`."""
        return np.clip(np.rint(self.lut), 0, 255).astype(np.uint8)

    def inverse_lut(self) -> Array:
        """``f^-1`` at every frame gray level (float32, (256,)): the frame in the
        background's photometry."""
        # Strictly increasing for np.interp, by a ramp far below a gray level.
        ramp = np.asarray(self.lut, np.float64) + 1e-6 * LEVELS
        return np.interp(LEVELS, ramp, LEVELS).astype(np.float32)


def identity_photometry(sigma_gray: float = 0.0) -> Photometry:
    return Photometry(LEVELS.astype(np.float32), np.zeros(2), float(sigma_gray))


def robust_sigma(residual: Array) -> float:
    """1.4826 x the median absolute deviation from the median (the standard deviation for
    Gaussian residuals, whatever a few outliers do)."""
    r = np.asarray(residual, np.float64)
    if r.size == 0:
        return float("nan")
    return 1.4826 * float(np.median(np.abs(r - np.median(r))))


@dataclass(frozen=True)
class BackgroundSamples:
    """A background image on the fit's grid of pixels: what the fit needs of it.

    Attributes
    ----------
    rows, cols : slices
        The grid in the image.
    levels : array (n,), uint8
        The background's gray levels on the grid (raveled).
    gradient : array (2, n), float64
        Its central differences there (twice the gradient), x and y.
    usable : array (n,) of bool
        Not saturated (0 or 255) in the background.
    """

    rows: slice
    cols: slice
    levels: Array
    gradient: Array
    usable: Array


def background_samples(background: Array, stride: int) -> BackgroundSamples:
    """:class:`BackgroundSamples` of an image on a grid of ``stride`` px (away from the
    border by at least one pixel, for the differences)."""
    height, width = background.shape
    o = max(stride // 2, 1)
    r0, rm, rp = (slice(o, height - 1, stride), slice(o - 1, height - 2, stride),
                  slice(o + 1, height, stride))
    c0, cm, cp = (slice(o, width - 1, stride), slice(o - 1, width - 2, stride),
                  slice(o + 1, width, stride))
    levels = background[r0, c0].ravel()
    gradient = np.array([
        np.subtract(background[r0, cp], background[r0, cm], dtype=np.float64).ravel(),
        np.subtract(background[rp, c0], background[rm, c0], dtype=np.float64).ravel(),
    ])
    return BackgroundSamples(r0, c0, levels, gradient, _UNSATURATED.take(levels))


def fit_photometry(
    image: Array,
    background: Array,
    stride: int = 12,
    normalise: bool = True,
    fit_shift: bool = True,
    samples: BackgroundSamples | None = None,
) -> Photometry:
    """Fit the frame's tone curve and shift against its background on a grid of pixels.

    Parameters
    ----------
    image, background : arrays (h, w), uint8
    stride : int
        Spacing of the grid, px (stride 12 on 640 x 480: about 2 100 pixels).
    normalise : bool
        Fit the tone curve; otherwise ``f`` is the identity (the frame is taken to have the
        background's photometry) and only the noise (and the shift) is estimated.
    fit_shift : bool
        Also estimate the shift of the whole image.
    samples : BackgroundSamples, optional
        ``background_samples(background, stride)``, if kept from frame to frame.

    Returns
    -------
    Photometry
        ``fitted`` is False, and the noise the robust spread of ``image - background``, when
        fewer than 50 grid pixels are unsaturated (an all-black or all-white frame).

    Notes
    -----
    The tone curve is fitted twice, the second time without the pixels beyond four robust
    standard deviations (1.4826 x the median absolute residual) of the first: the catheter
    and occluders take no part. The noise is the root mean square of the second fit's
    residual within the same bound; the shift is the least-squares fit of that residual to
    the background's gradient, scaled by the tone curve's slope at the background's mean
    gray level (``gain``). All of it is one compiled kernel,
    :func:`tracker.vision.photometry_kernels.fit`.
    """
    if samples is None:
        samples = background_samples(background, stride)
    height, width = image.shape
    n, lut, shift_x, shift_y, sigma, gain, dark, _ = photometry_kernels.fit(
        np.ascontiguousarray(image), samples.rows.indices(height), samples.cols.indices(width),
        samples.levels, samples.usable, samples.gradient, bool(normalise), bool(fit_shift),
        _MIN_SAMPLES,
    )
    clipped = 1.0 - n / max(samples.levels.size, 1)
    if n < _MIN_SAMPLES:
        frame_u8 = image[samples.rows, samples.cols].ravel()
        sigma = robust_sigma(frame_u8.astype(np.float64) - samples.levels)
        return Photometry(LEVELS.astype(np.float32), np.zeros(2), sigma, 0.0, clipped, False)
    return Photometry(lut.astype(np.float32), np.array([shift_x, shift_y]), sigma, gain,
                      clipped, True, dark)


_SIGNIFICANT_CHI2 = 13.8  # chi-square of 2 dof beyond which a shift is applied (p = 0.001)


def fit_shift(
    image: Array,
    samples: ShiftSamples,
    photometry: Photometry,
    excluded: Array | None = None,
) -> Photometry:
    """The frame's shift relative to its background, to a few hundredths of a pixel.

    The photometric fit's shift (first order, on its sparse grid: a few tenths of a pixel
    at 8 gray levels of noise) is refined on the background's pixels of the strongest
    gradient (:class:`ShiftSamples`, some 33 000: fifteen times the pixels, far more than
    that of the information) with the background's smoothed gradient: the least-squares
    fit of ``frame(p) = f(background(p - shift))`` linearised at the background (the
    second-order term, of either sign from pixel to pixel, averages out over a textured
    scene), with gradients centred per gray level (the tone curve's own error, fitted on
    the sparse grid, would leak into the shift), on the pixels whose residual left by the
    first estimate is within four noise sigmas (the catheter and occluders take no part;
    the gate's centre needs no more precision than the first estimate's).

    Parameters
    ----------
    image : array (h, w), uint8
    samples : ShiftSamples
        The background's (:mod:`tracker.vision.shift_pixels`).
    photometry : Photometry
        The frame's fit (:func:`fit_photometry`): tone curve, gain, noise, first shift.
    excluded : array, uint8, optional
        The cells to leave out (not 0), :func:`tracker.vision.shift_pixels.shift_grid_mask`:
        the catheter and its surroundings, whose faint blurred edges pass any gate and
        would pull the shift by some hundredths of a pixel.

    Returns
    -------
    Photometry
        ``photometry`` with ``shift_px`` refined and ``shift_cov_px2``, its covariance
        (px^2, the residual's variance over the normal matrix), set; unchanged when it was
        not fitted or the background has no texture to register on.
    """
    if not photometry.fitted or abs(photometry.gain) < 1e-6:
        return photometry
    first_x, first_y = photometry.shift_px.tolist()
    if excluded is None:
        excluded = np.zeros(samples.cells_shape, np.uint8)
    n, squares, g00, g01, g11, b0, b1 = shift_kernels.shift_sums(
        np.ascontiguousarray(image).reshape(-1), samples.index, samples.levels,
        samples.gradient, samples.cell, excluded.reshape(-1), photometry.lut,
        float(photometry.gain), float(first_x), float(first_y),
        4.0 * max(photometry.sigma_gray, 0.5),
    )
    det = g00 * g11 - g01 * g01
    if n < _MIN_SAMPLES or not det > 1e-9 * g00 * g11 or not det > 0:
        return photometry
    shift = np.array([-(g11 * b0 - g01 * b1) / det, -(g00 * b1 - g01 * b0) / det])
    # The residual's variance over the normal matrix; the squares are those left by the
    # first estimate, within a few percent of the refined one's for the shifts the first
    # estimate is good for.
    cov = np.array([[g11, -g01], [-g01, g00]]) * (squares / n / det)
    return replace(photometry, shift_px=shift, shift_cov_px2=cov)


def significant_shift(photometry: Photometry) -> Array:
    """The frame's shift (x, y), px, where it stands out of its own uncertainty (chi-square
    of 2 degrees of freedom beyond the 0.999 quantile), zero elsewhere: a frame that has
    not moved is left exactly as it is, not moved by the noise of the estimate."""
    cov = photometry.shift_cov_px2
    if cov is None:
        return np.zeros(2)
    (a, b), (_, d) = cov.tolist()
    x, y = photometry.shift_px.tolist()
    det = a * d - b * b
    if not det > 0:
        return np.zeros(2)
    chi2 = (d * x * x - 2.0 * b * x * y + a * y * y) / det
    return np.array([x, y]) if chi2 > _SIGNIFICANT_CHI2 else np.zeros(2)


def register_shift(
    image: Array, background: Array, photometry: Photometry, max_shift_px: float
) -> Array | None:
    """The shift of the frame's content relative to the background, px, or None.

    Phase correlation of the frame with the background mapped to the frame's tone curve
    (both at half resolution, with a Hann window), for shifts beyond the first-order
    estimate's reach; None when the correlation peak is weak (the scene itself changed) or
    the shift is larger than ``max_shift_px``.
    """
    small_frame = cv2.pyrDown(image).astype(np.float32)
    small_bg = cv2.pyrDown(cv2.LUT(background, photometry.lut_u8)).astype(np.float32)
    window = cv2.createHanningWindow(small_frame.shape[::-1], cv2.CV_32F)
    (dx, dy), response = cv2.phaseCorrelate(small_bg, small_frame, window)
    shift = 2.0 * np.array([dx, dy])
    if response < 0.1 or np.hypot(*shift) > max_shift_px:
        return None
    return shift
