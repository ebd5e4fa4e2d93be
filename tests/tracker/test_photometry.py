"""The compiled photometric fit (tracker.vision.photometry_kernels.fit, behind
fit_photometry) against the implementation it replaced, kept here as a reference: the numpy
steps and Python floats of before, with numpy in place of the compiled sums it called.

On generated frames covering each branch: a tone curve of degree 0, 1 and 2 (the
background's gray levels spread below 3, between 3 and 12, above 12), a gamma and an
offset, noise, a known sub-pixel shift, a dark occluder (removed by the second fit),
saturated regions, too few unsaturated pixels (a black and a white frame), no
normalisation, no shift, a flat frame (no slope: no shift), another stride; and on rendered
frames of the catheter.

Tolerance: the float64 tone curve (and the float32 one to its rounding), shift, noise, gain
and black level within 1e-9 relative (or 1e-9 absolute, gray levels or px, for values near
zero); the pixels taken, the fraction clipped, the degree and ``fitted`` exactly the same
(a pixel more or less beyond the gate would move the noise by far more than the tolerance).
Only sums of non-integers over the 256 gray levels (the moments of a fit of degree 1 or 2,
the curve from its coefficients; numpy's were BLAS's) differ, in their last bits.
"""

import math

import cv2
import numpy as np
import pytest

from tests.tracker import segmentation_common
from tests.tracker.segmentation_common import Q_BENT
from tracker.vision import photometry_kernels
from tracker.vision.photometry import (
    LEVELS,
    Photometry,
    background_samples,
    fit_photometry,
    robust_sigma,
)

scene = segmentation_common.scene

RTOL = ATOL = 1e-9


# ---------------------------------------------------------------------------- reference
_X = LEVELS / 255.0 - 0.5
_POWERS = np.stack([_X**k for k in range(5)])
_LEVELS_SQUARED = LEVELS**2


def _solve_small(M, v):
    if len(v) == 2:
        (a, b), (_, d) = M
        p, q = v
        det = a * d - b * b
        if not (a > 1e-12 and det > 1e-12 * a):
            return [0.0, 0.0]
        return [(d * p - b * q) / det, (a * q - b * p) / det]
    (a, b, c), (_, d, e), (_, _, f) = M
    p, q, r = v
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A + b * B + c * C
    if not (a > 1e-12 and F > 1e-12 * a and det > 1e-12 * F):
        return [0.0, 0.0, 0.0]
    return [
        (A * p + B * q + C * r) / det,
        (B * p + D * q + E * r) / det,
        (C * p + E * q + F * r) / det,
    ]


def _tone_curve(counts, sums, degree):
    if degree == 0:
        scale = float(sums @ LEVELS) / max(float(counts @ _LEVELS_SQUARED), 1e-12)
        return scale * LEVELS
    n = degree + 1
    moments = (_POWERS[: 2 * n - 1] @ counts).tolist()
    M = [moments[i : i + n] for i in range(n)]
    coef = _solve_small(M, (_POWERS[:n] @ sums).tolist())
    return np.array(coef) @ _POWERS[:n]


def _tone_residuals(frame, level, lut, gate):
    residual = frame - lut[level]
    if math.isnan(gate):  # 4 robust standard deviations (the upper median), at least 2
        half = np.partition(np.abs(residual), residual.size // 2)[residual.size // 2]
        gate = max(4.0 * 1.4826 * half, 2.0)
    out = np.abs(residual) > gate
    counts_out = np.bincount(level[out], minlength=256).astype(float)
    sums_out = np.bincount(level[out], weights=frame[out], minlength=256)
    return residual, out, gate, counts_out, sums_out


def _reference_fit_photometry(
    image, background, stride=12, normalise=True, fit_shift=True, samples=None
):
    """fit_photometry as it was; returns the Photometry, the float64 tone curve, the degree
    (-1: none), whether the second fit ran and the pixels beyond the final gate."""
    if samples is None:
        samples = background_samples(background, stride)
    grid = image[samples.rows, samples.cols].ravel()
    usable = (grid > 0) & (grid < 255) & samples.usable
    frame, b_u8 = grid[usable].astype(float), samples.levels[usable]
    counts = np.bincount(b_u8, minlength=256).astype(float)
    sums = np.bincount(b_u8, weights=frame, minlength=256)
    n = frame.size
    size = samples.levels.size
    clipped = 1.0 - n / max(size, 1)
    if n < 50:
        sigma = robust_sigma(grid.astype(np.float64) - samples.levels)
        photometry = Photometry(LEVELS.astype(np.float32), np.zeros(2), sigma, 0.0, clipped, False)
        return photometry, LEVELS, -1, False, None
    mean_level = float(counts @ LEVELS) / n
    lut = LEVELS
    degree = -1
    if normalise:
        spread = math.sqrt(max(float(counts @ _LEVELS_SQUARED) / n - mean_level**2, 0.0))
        degree = 2 if spread >= 12.0 else (1 if spread >= 3.0 else 0)
        lut = _tone_curve(counts, sums, degree)
    residual, out, gate, counts_out, sums_out = _tone_residuals(frame, b_u8, lut, math.nan)
    second = bool(normalise and out.any())
    if second:
        lut = _tone_curve(counts - counts_out, sums - sums_out, degree)
        residual, out, _, _, _ = _tone_residuals(frame, b_u8, lut, gate)
    g, r = samples.gradient[:, usable], np.where(out, 0.0, residual)
    G = g @ g.T - g[:, out] @ g[:, out].T
    squares = float(r @ r)
    n_in = n - int(np.count_nonzero(out))
    sigma = math.sqrt(squares / n_in) if n_in > 10 else gate / 4.0
    level = min(max(round(mean_level), 1), 254)
    below, at, above = lut[level - 1 : level + 2].tolist()
    gain = 0.5 * (above - below)
    shift = [0.0, 0.0]
    if fit_shift and abs(gain) > 1e-6:
        G = [[G[0, 0], G[0, 1]], [G[0, 1], G[1, 1]]]
        shift = [-2.0 * d / gain for d in _solve_small(G, (g @ r).tolist())]
    bound = 0.25 * abs(at)
    dark = min(max(float(lut[0]), -bound), bound) if normalise else 0.0
    lut = np.maximum.accumulate(lut)
    photometry = Photometry(
        lut.astype(np.float32), np.array(shift), sigma, gain, clipped, True, dark
    )
    return photometry, lut, degree, second, out


# ------------------------------------------------------------------------------ frames
HEIGHT, WIDTH = 480, 640


def texture(rng, mean, amplitude, shape=(HEIGHT, WIDTH)):
    """A smooth random background (float), gray levels ``mean +- amplitude`` (1 sigma)."""
    noise = cv2.GaussianBlur(rng.standard_normal(shape), (0, 0), 4.0)
    return mean + amplitude * noise / noise.std()


def tone(background, gain=1.0, offset=0.0, gamma=1.0):
    return gain * 255.0 * (np.clip(background, 0, 255) / 255.0) ** gamma + offset


def u8(image):
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def shifted(background, dx, dy):
    """The background moved by (dx, dy) px: frame(p) = background(p - d)."""
    move = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]])
    return cv2.warpAffine(
        background,
        move,
        background.shape[::-1],
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REFLECT,
    )


def make_case(name, rng):
    """(image, background (uint8), keyword arguments of fit_photometry, expected (degree,
    second fit, fitted), None where any will do)."""
    noise = rng.standard_normal((HEIGHT, WIDTH))
    if name == "degree 0":
        bg = texture(rng, 120.0, 0.8)
        return u8(tone(bg, 1.07) + 1.5 * noise), u8(bg), {}, (0, None, True)
    if name == "degree 1, offset":
        bg = texture(rng, 120.0, 6.0)
        return u8(tone(bg, 0.95, 8.0) + 1.5 * noise), u8(bg), {}, (1, None, True)
    if name == "degree 2, gamma and offset":
        bg = texture(rng, 128.0, 40.0)
        return u8(tone(bg, 1.05, -6.0, 0.9) + 2.0 * noise), u8(bg), {}, (2, None, True)
    if name == "sub-pixel shift":
        bg = texture(rng, 128.0, 40.0)
        image = u8(tone(shifted(bg, 0.3, -0.4), 1.02, 3.0) + 1.0 * noise)
        return image, u8(bg), {}, (2, None, True)
    if name == "dark occluder":
        bg = texture(rng, 128.0, 30.0)
        image = tone(bg, 0.92, 5.0, 1.08) + 2.0 * noise
        image[100:220, 200:330] = 25.0 + 2.0 * noise[100:220, 200:330]
        return u8(image), u8(bg), {}, (2, True, True)
    if name == "saturated":
        bg = texture(rng, 150.0, 60.0)  # the background clipped at 0 and 255 in places
        bg[:60] = 255.0
        image = tone(bg, 1.3, 10.0) + 2.0 * noise  # and the frame, brighter, more so
        image[300:, :100] = 255.0
        return u8(image), u8(bg), {}, (2, None, True)
    if name == "black frame":
        bg = texture(rng, 128.0, 40.0)
        return np.zeros((HEIGHT, WIDTH), np.uint8), u8(bg), {}, (-1, False, False)
    if name == "white frame":
        bg = texture(rng, 128.0, 40.0)
        return np.full((HEIGHT, WIDTH), 255, np.uint8), u8(bg), {}, (-1, False, False)
    if name == "not normalised":
        bg = texture(rng, 128.0, 40.0)
        image = shifted(bg, -0.25, 0.15) + 2.0 * noise
        image[100:220, 200:330] = 25.0
        return u8(image), u8(bg), {"normalise": False}, (-1, False, True)
    if name == "no shift fitted":
        bg = texture(rng, 128.0, 40.0)
        image = u8(tone(shifted(bg, 0.3, 0.2), 1.05) + 2.0 * noise)
        return image, u8(bg), {"fit_shift": False}, (2, None, True)
    if name == "flat frame":  # no slope: no shift
        bg = texture(rng, 128.0, 40.0)
        return np.full((HEIGHT, WIDTH), 128, np.uint8), u8(bg), {}, (2, False, True)
    if name == "stride 7, samples kept":
        bg = u8(texture(rng, 110.0, 25.0, (240, 320)))
        image = u8(tone(bg, 0.9, 4.0, 1.05) + 2.0 * noise[:240, :320])
        return image, bg, {"stride": 7, "samples": background_samples(bg, 7)}, (2, None, True)
    raise ValueError(name)


CASES = [
    "degree 0",
    "degree 1, offset",
    "degree 2, gamma and offset",
    "sub-pixel shift",
    "dark occluder",
    "saturated",
    "black frame",
    "white frame",
    "not normalised",
    "no shift fitted",
    "flat frame",
    "stride 7, samples kept",
]


# ------------------------------------------------------------------------------- tests
def fit_and_kernel_result(monkeypatch, image, background, **kwargs):
    """fit_photometry's result, and what its kernel returned (the float64 tone curve, the
    degree)."""
    calls = []

    def record(*args):
        calls.append(kernel(*args))
        return calls[-1]

    kernel = photometry_kernels.fit
    monkeypatch.setattr(photometry_kernels, "fit", record)
    photometry = fit_photometry(image, background, **kwargs)
    assert len(calls) == 1
    return photometry, calls[0]


def assert_same_photometry(image, background, kwargs, monkeypatch):
    """The compiled fit against the reference; returns the reference's branches."""
    photometry, (n, lut, *_, degree) = fit_and_kernel_result(
        monkeypatch, image, background, **kwargs
    )
    expected, lut_ref, degree_ref, second, out = _reference_fit_photometry(
        image, background, **kwargs
    )
    assert photometry.fitted == expected.fitted
    assert photometry.clipped_fraction == expected.clipped_fraction
    close = {"rtol": RTOL, "atol": ATOL}
    if expected.fitted:
        assert degree == degree_ref
        np.testing.assert_allclose(lut, lut_ref, **close)
        assert np.all(np.diff(lut) >= 0)
        np.testing.assert_allclose(photometry.lut, lut_ref.astype(np.float32), rtol=1e-6)
    else:  # the kernel's early return: the identity, the noise from the images
        np.testing.assert_array_equal(photometry.lut, expected.lut)
    assert photometry.lut.dtype == np.float32 and photometry.lut.shape == (256,)
    np.testing.assert_allclose(photometry.shift_px, expected.shift_px, **close)
    for field in ("sigma_gray", "gain", "dark_gray"):
        np.testing.assert_allclose(
            getattr(photometry, field), getattr(expected, field), err_msg=field, **close
        )
    assert photometry.shift_cov_px2 is None
    if out is not None:  # the same pixels taken
        assert n == out.size
    return degree_ref, second, expected


@pytest.mark.parametrize("name", CASES)
def test_fit_photometry_matches_the_reference(name, monkeypatch):
    rng = np.random.default_rng(CASES.index(name))
    image, background, kwargs, (degree, second, fitted) = make_case(name, rng)
    degree_ref, second_ref, expected = assert_same_photometry(
        image, background, kwargs, monkeypatch
    )
    # The frames cover the branches they are meant to.
    assert (degree_ref, expected.fitted) == (degree, fitted)
    if second is not None:
        assert second_ref == second
    if name == "dark occluder":
        assert expected.sigma_gray < 3.0  # the occluder took no part in the noise
    if name == "saturated":
        assert expected.clipped_fraction > 0.15
    if name == "sub-pixel shift":
        np.testing.assert_allclose(expected.shift_px, [0.3, -0.4], atol=0.1)
    if name in ("no shift fitted", "flat frame"):
        assert not expected.shift_px.any()


def test_fit_photometry_matches_the_reference_on_rendered_frames(scene, monkeypatch):
    """Frames of the catheter as the live loop sees them, with and without normalisation."""
    _, _, renderer = scene
    frames = renderer.render(Q_BENT, 0.0, np.random.default_rng(7))
    for image, background in zip(frames.images, renderer.backgrounds, strict=True):
        for normalise in (True, False):
            _, _, expected = assert_same_photometry(
                image, background, {"normalise": normalise}, monkeypatch
            )
            assert expected.fitted
