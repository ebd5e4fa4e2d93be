"""The background's pixels that a frame's shift is fitted on (docs/vision.md section 4).

:func:`tracker.vision.photometry.fit_shift` registers every frame on the ``SHIFT_PIXELS``
pixels of its background of the strongest gradient (:class:`ShiftSamples`). Choosing them
takes the gradient of the whole image and a threshold on its magnitude: 1.3 ms for 640 x
480 (2 ms in numpy), which a background model that changes
(:mod:`tracker.vision.background`) would pay on one frame of every cycle of its stripes,
on the live loop's critical path. :class:`ShiftSampler` keeps them a stripe of rows at a
time instead: the pixels of a stripe are chosen again as soon as the stripe has been
averaged in, with the threshold of the cycle before, and the stripes' pixels are put
together when the cycle ends. :func:`shift_grid_mask` gives the cells around
the catheter that a frame's fit leaves out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tracker.vision import shift_kernels

Array = np.ndarray

SHIFT_PIXELS = 32768  # the background's pixels of the strongest gradient the shift is fitted on
SHIFT_CELL_PX = 4  # the cells in which the catheter's surroundings are left out of that fit
# The gradient of the background for the shift: a derivative of a Gaussian of 1 px (5 taps,
# as correlation kernels), which keeps the texture's gradient (its scale is many pixels)
# and takes out the quantisation's: the central differences of an 8-bit image carry
# enough of it to bias the shift 8 % toward zero (the errors in the variables of a least
# squares fit).
_TAPS = np.arange(-2.0, 3.0)
_SMOOTH = np.exp(-0.5 * _TAPS**2) / np.exp(-0.5 * _TAPS**2).sum()
_DERIVATIVE = _TAPS * _SMOOTH / float(_TAPS**2 @ _SMOOTH)
_SMOOTH, _DERIVATIVE = _SMOOTH.astype(np.float32), _DERIVATIVE.astype(np.float32)
_BORDER_PX = 3  # pixels this close to the border are not used (the gradient's 5 taps)
_THRESHOLD_STRIDE = 7  # the threshold from every 7th pixel's magnitude


@dataclass(frozen=True)
class ShiftSamples:
    """The background's pixels that :func:`tracker.vision.photometry.fit_shift` registers a
    frame on.

    The shift's information is the sum of the squared gradients: the ``SHIFT_PIXELS``
    pixels of the strongest gradient carry (for 640 x 480 and a smooth texture) as much as
    every other pixel of every other row, at less than half the cost.

    Attributes
    ----------
    index : array (n,), int32
        The pixels' flat indices in the image (row-major, increasing).
    levels : array (n,), uint8
        The background's gray levels there.
    gradient : array (2, n), float32
        Its gradient there (x, y), smoothed, gray levels per px, less the mean gradient of
        the pixels of the same gray level.
    cell : array (n,), int32
        Each pixel's cell of ``SHIFT_CELL_PX`` square in the grid of cells (row-major)...
    cells_shape : (int, int)
        ...of this shape (rows, columns): :func:`shift_grid_mask` leaves out cells.
    """

    index: Array
    levels: Array
    gradient: Array
    cell: Array
    cells_shape: tuple[int, int]


def _threshold_sq(sample: Array, size: int) -> float:
    """The squared magnitude above which ``SHIFT_PIXELS`` of an image's ``size`` pixels
    lie, (gray levels / px)^2, from every ``_THRESHOLD_STRIDE``-th pixel's, ``sample`` (a
    partition of them all costs ten times more; the count kept is then within a few
    percent of ``SHIFT_PIXELS``). ``sample`` is reordered."""
    rank = int((1.0 - min(SHIFT_PIXELS / size, 1.0)) * (sample.size - 1))
    return max(float(np.partition(sample, rank)[rank]), 0.0)


class ShiftSampler:
    """The :class:`ShiftSamples` of a background image that changes a stripe of rows at a
    time (:class:`tracker.vision.background.BackgroundModel`).

    :meth:`rebuild` chooses the pixels of the whole image at once (1.3 ms for 640 x 480:
    when the model is made or re-registered). :meth:`resample` chooses those of one
    stripe again (about 0.08 ms for an eighth of it) with the threshold of the last
    :meth:`combine`, which puts the stripes' pixels together and takes the threshold for
    the next stripes from the magnitudes seen in the last ones. A slow change of the scene
    moves the threshold by little from one cycle of stripes to the next, so the count kept
    stays within a few percent of ``SHIFT_PIXELS``; a sudden one is corrected a cycle
    later.

    Parameters
    ----------
    background : array (h, w), uint8
        The image to start from.
    stripes : int
        The stripes of rows (the background model's ``background_stripes``: stripe ``k``
        is rows ``k ceil(h / stripes)`` up to the next stripe's first).

    Attributes
    ----------
    samples : ShiftSamples
        The pixels as of the last :meth:`rebuild` or :meth:`combine`.
    """

    def __init__(self, background: Array, stripes: int) -> None:
        height, width = background.shape
        self._height = height
        self._size = height * width
        self._rows_per = -(-height // max(int(stripes), 1))
        self._stripes = -(-height // self._rows_per)
        self._cells_shape = (-(-height // SHIFT_CELL_PX), -(-width // SHIFT_CELL_PX))
        # Every _THRESHOLD_STRIDE-th pixel's squared magnitude, for the threshold.
        self._sample = np.zeros(-(-height * width // _THRESHOLD_STRIDE), np.float32)
        self._threshold_sq = math.inf
        self._blocks: list[tuple] = [()] * self._stripes
        self.samples = self.rebuild(background)

    @property
    def stripes(self) -> int:
        """The number of stripes (fewer than asked when the image has too few rows)."""
        return self._stripes

    def rebuild(self, background: Array) -> ShiftSamples:
        """Choose the pixels of the whole image (threshold included) and return them (also
        kept as :attr:`samples`)."""
        background = np.ascontiguousarray(background, np.uint8)
        # The magnitudes first (nothing is above an infinite threshold), for the threshold.
        self._select(background, 0, self._height, math.inf)
        self._threshold_sq = _threshold_sq(self._sample.copy(), self._size)
        for k in range(self._stripes):
            self.resample(background, k)
        return self.combine(new_threshold=False)

    def resample(self, background: Array, stripe: int) -> None:
        """Choose the pixels of one stripe of rows again, from ``background`` (uint8 (h, w),
        the whole image: the gradient reads two rows beyond the stripe)."""
        y0 = stripe * self._rows_per
        self._blocks[stripe] = self._select(
            background, y0, min(y0 + self._rows_per, self._height), self._threshold_sq
        )

    def combine(self, new_threshold: bool = True) -> ShiftSamples:
        """Put the stripes' pixels together (their gradients centred per gray level), keep
        them as :attr:`samples` and return them; with ``new_threshold``, the threshold of
        the next stripes from the magnitudes of the last ones."""
        index, levels, gradient, cell, counts, sums = zip(*self._blocks, strict=True)
        levels = np.concatenate(levels)
        # Each gradient less its mean over the pixels of the same gray level: the residual's
        # part that depends on the gray level alone (the error of the tone curve fitted on
        # the sparse grid) is then orthogonal to them, and does not leak into the shift
        # wherever the gradients at one gray level do not cancel (a scene brighter on one
        # side). The catheter's few pixels left out per frame hardly change the means.
        gradient = shift_kernels.centred_gradients(
            levels, np.concatenate(gradient, axis=1), sum(counts), sum(sums)
        )
        self.samples = ShiftSamples(np.concatenate(index), levels, gradient,
                                    np.concatenate(cell), self._cells_shape)
        if new_threshold:
            # A partition reorders its input: a copy (the sample is kept for the stripes).
            self._threshold_sq = _threshold_sq(self._sample.copy(), self._size)
        return self.samples

    def _select(self, background: Array, y0: int, y1: int, threshold_sq: float) -> tuple:
        return shift_kernels.select_pixels(
            background, y0, y1, _SMOOTH, _DERIVATIVE, _BORDER_PX, threshold_sq,
            SHIFT_CELL_PX, self._cells_shape[1], self._sample, _THRESHOLD_STRIDE,
        )


def shift_samples(background: Array) -> ShiftSamples:
    """:class:`ShiftSamples` of a background image (uint8 (h, w)) at once; 1.3 ms for
    640 x 480 (:class:`ShiftSampler` keeps those of a changing image)."""
    return ShiftSampler(background, 1).samples


def shift_grid_mask(samples: ShiftSamples, lines: list[tuple[Array, float]]) -> Array:
    """The cells of :func:`tracker.vision.photometry.fit_shift` within a distance of
    polylines.

    Parameters
    ----------
    samples : ShiftSamples
    lines : list of (points (n, 2), half width px)
        Polylines in the image (px; non-finite points left out) and how far from them the
        pixels are left out, px.

    Returns
    -------
    array ``samples.cells_shape``, uint8
        1 on the cells to leave out, 0 elsewhere: those whose centre is within the half
        width of a polyline, rounded up to half cells, plus a cell (every cell with a pixel
        within the half width, and a margin of about a cell).
    """
    mask = np.zeros(samples.cells_shape, np.uint8)
    for points, half_width_px in lines:
        # The band's width in whole cells, and a cell more on each side.
        reach_px = 0.5 * SHIFT_CELL_PX * (math.ceil(2.0 * half_width_px / SHIFT_CELL_PX) + 2)
        shift_kernels.mark_near_polyline(
            mask, np.ascontiguousarray(points, dtype=float).reshape(-1, 2), reach_px,
            float(SHIFT_CELL_PX),
        )  # fmt: skip
    return mask
