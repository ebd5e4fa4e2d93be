"""The frame's shift from its background (a camera that vibrates): measured to a few
hundredths of a pixel, taken out of the points, and frames that did not move left alone."""

import cv2
import numpy as np
import pytest

from models.catheter import default_catheter
from replay.simulation.render import (
    ImagingChange,
    ImagingNuisance,
    Renderer,
    RenderSettings,
    catheter_points_w,
    default_render_rig,
    render_view,
)
from tracker.vision import shift_kernels, shift_pixels
from tracker.vision.background import BackgroundModel
from tracker.vision.pair import PairSegmenter
from tracker.vision.photometry import fit_photometry, fit_shift, significant_shift
from tracker.vision.settings import DEFAULT_SETTINGS
from tracker.vision.shift_pixels import ShiftSampler, shift_grid_mask, shift_samples

BASE_W = np.array([0.0, 0.0, -15.0])
Q_BENT = np.array([0.8, 0.7, 0.5])
N_FRAMES = 40


@pytest.mark.parametrize("noise_gray, se_px", [(2.0, 0.015), (8.0, 0.05)])
def test_shift_is_measured_to_hundredths_of_a_pixel(noise_gray, se_px):
    """40 frames shifted by 0.5 px standard deviation per axis: the shift within its own
    standard error (RMS error at most 1.3 times it, mean at most 0.01 px or 3 standard
    errors of the mean), that standard error at most ``se_px``, no bias of scale beyond 3 %; the shift
    is then applied to every frame (significant), and to none of 40 frames not shifted
    but one at most."""
    catheter, rig = default_catheter(), default_render_rig()
    settings = RenderSettings(noise_sigma_gray=noise_gray)
    renderer = Renderer(catheter, rig, np.eye(3), BASE_W, settings, seed=3)
    view, background = rig.views[0], renderer.backgrounds[0]
    samples = shift_samples(background)
    rng = np.random.default_rng(7)
    truth, found, se, applied = [], [], [], []
    for k in range(2 * N_FRAMES):
        shift = 0.5 * rng.standard_normal(2) if k < N_FRAMES else np.zeros(2)
        q = Q_BENT + 0.1 * rng.standard_normal(3)
        pose = renderer.pose(q, 0.3)
        image = render_view(view, catheter, pose, renderer.background_float[0], rng, settings,
                            change=ImagingChange(shift_px=tuple(shift)))
        # The catheter's surroundings left out, as CameraSegmenter does with its centreline.
        backbone = view.project(catheter_points_w(catheter, pose, np.linspace(0, 29.0, 30)))
        excluded = shift_grid_mask(samples, [(backbone + shift, 10.0)])
        photometry = fit_shift(image, samples, fit_photometry(image, background), excluded)
        truth.append(shift)
        found.append(photometry.shift_px)
        se.append(np.sqrt(np.diag(photometry.shift_cov_px2)))
        applied.append(bool(significant_shift(photometry).any()))
    truth, found, se = np.array(truth), np.array(found), np.array(se)
    error = found - truth
    assert se.mean() <= se_px
    assert np.sqrt((error**2).mean(axis=0)).max() <= 1.3 * se.mean()
    bound = max(0.01, 3.0 * se.mean() / np.sqrt(error.shape[0]))
    assert np.abs(error.mean(axis=0)).max() <= bound
    shifted = slice(0, N_FRAMES)
    slope = np.polyfit(truth[shifted].ravel(), found[shifted].ravel(), 1)[0]
    assert slope == pytest.approx(1.0, abs=0.03)
    if noise_gray <= 2.0:  # at 8 gray levels a shift below 0.2 px may not stand out
        assert all(applied[:N_FRAMES])
    assert sum(applied[N_FRAMES:]) <= 1


def test_a_vibrating_camera_gives_the_points_of_a_still_one():
    """The same frames with and without a shift of the whole image of 0.5 px standard
    deviation per axis (the sensor noise the same), against the points the calibrated
    cameras see: the RMS error of the shifted frames' points at most 1.2 times the still
    ones' (uncorrected, 0.5 px would add in quadrature), and the camera not re-registered
    as if it had moved."""
    catheter, rig = default_catheter(), default_render_rig()
    errors, shifts, cameras = {}, [], {}
    for vibration in (0.0, 0.5):
        renderer = Renderer(catheter, rig, np.eye(3), BASE_W, seed=5,
                            nuisance=ImagingNuisance(vibration_px=vibration), nuisance_seed=9)
        segmenter = PairSegmenter(catheter, rig, np.eye(3), BASE_W, renderer.backgrounds)
        rng = np.random.default_rng(8)
        rows = []
        for k in range(N_FRAMES):
            pair = renderer.render(Q_BENT + [0.01 * k, 0.005 * k, 0.0], 0.3, rng)
            uv = segmenter.segment(pair.images).uv
            rows.append([u - view.project(pair.points_w) for u, view in zip(uv, rig.views,
                                                                           strict=True)])
            shifts += [change.shift_px for change in pair.changes]
        errors[vibration] = np.array(rows).reshape(-1, 2)
        cameras[vibration] = segmenter.cameras
    assert np.sqrt((np.array(shifts) ** 2).sum(axis=-1)).max() > 1.0  # beyond camera_moved_px
    rms = {}
    for vibration, e in errors.items():
        found = np.isfinite(e).all(axis=-1)
        assert found.mean() > 0.9
        rms[vibration] = np.sqrt((e[found] ** 2).sum(axis=-1).mean())
    assert rms[0.5] <= 1.2 * rms[0.0], rms
    assert all(not camera.shift_px.any() for camera in cameras[0.5])


def assert_same_samples(a, b):
    for name in ("index", "levels", "gradient", "cell"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.cells_shape == b.cells_shape


def test_pixels_chosen_a_stripe_at_a_time_are_those_of_the_whole_image():
    """Re-chosen stripe by stripe (with the threshold of the cycle before), the shift's
    pixels of an image are, from the second cycle on the image, exactly those chosen from
    the whole image at once; the first cycle keeps the old threshold, hence a few percent
    more or fewer pixels, but each one's gradient is the new image's."""
    renderer = Renderer(default_catheter(), default_render_rig(), np.eye(3), BASE_W, seed=3)
    first, second = renderer.backgrounds
    sampler = ShiftSampler(first, 8)
    assert_same_samples(sampler.samples, shift_samples(first))
    for _ in range(2):
        for stripe in range(sampler.stripes):
            sampler.resample(second, stripe)
        once = sampler.combine()
        if _ == 0:
            whole = shift_samples(second)
            assert abs(once.index.size / whole.index.size - 1.0) < 0.1
            common, in_once, in_whole = np.intersect1d(once.index, whole.index,
                                                       return_indices=True)
            assert common.size > 0.9 * whole.index.size
            # Centred over different sets of pixels: equal up to each level's mean, so the
            # difference is one constant per gray level (to float32 rounding).
            levels = once.levels[in_once]
            np.testing.assert_array_equal(levels, whole.levels[in_whole])
            difference = once.gradient[:, in_once] - whole.gradient[:, in_whole]
            for level in np.unique(levels):
                at = difference[:, levels == level]
                constant = np.repeat(at[:, :1], at.shape[1], axis=1)
                np.testing.assert_allclose(at, constant, atol=1e-5, err_msg=f"level {level}")
    assert_same_samples(once, shift_samples(second))


def test_the_background_models_pixels_follow_its_stripes():
    """A model that averages in frames of a brighter scene (its stripes one at a time, on
    its turns): the shift's pixels of each stripe are chosen again with its update and put
    together once per cycle, on the frame after the cycle's last stripe, with the gray
    levels the model then has and the gradient of its image (but on the two rows at the
    end of each stripe, read before the next stripe's update)."""
    renderer = Renderer(default_catheter(), default_render_rig(), np.eye(3), BASE_W, seed=3)
    background = renderer.backgrounds[0]
    model = BackgroundModel(background, DEFAULT_SETTINGS)
    assert_same_samples(model.shift_samples, shift_samples(background))
    rng = np.random.default_rng(2)
    cycle = DEFAULT_SETTINGS.background_stripes * DEFAULT_SETTINGS.background_every
    changed_at = []
    for frame in range(2 * cycle):
        image = np.clip(background + 10.0 + 2.0 * rng.standard_normal(background.shape),
                        0, 255).astype(np.uint8)
        photometry = fit_photometry(image, model.image, normalise=False)
        before = model.shift_samples
        model.update(image, photometry, [])
        if model.shift_samples is not before:
            changed_at.append(frame)
            samples = model.shift_samples
            np.testing.assert_array_equal(samples.levels, model.image.ravel()[samples.index])
    # The frame after the last stripe's turn: the cycle's last.
    assert changed_at == [cycle - 1, 2 * cycle - 1]
    samples, whole = model.shift_samples, shift_samples(model.image)
    assert abs(samples.index.size / whole.index.size - 1.0) < 0.05
    rows_per = -(-background.shape[0] // DEFAULT_SETTINGS.background_stripes)
    common, mine, theirs = np.intersect1d(samples.index, whole.index, return_indices=True)
    inside = (common // background.shape[1]) % rows_per < rows_per - 2
    assert common.size > 0.95 * whole.index.size
    # Centred over slightly different sets of pixels: equal but for each level's mean.
    difference = samples.gradient[:, mine[inside]] - whole.gradient[:, theirs[inside]]
    levels = samples.levels[mine[inside]]
    count = np.maximum(np.bincount(levels, minlength=256), 1)
    for d in difference:
        per_level = np.bincount(levels, d, minlength=256) / count
        assert np.abs(d - per_level[levels]).max() < 1e-3
    assert model.image.mean() > background.mean() + 1.0  # the model did change


def test_compiled_choice_and_sums_match_numpy():
    """The compiled kernels against what they replace: the pixels chosen are those whose
    gradient (OpenCV's separable filter, edges replicated) exceeds the threshold away from
    the border, with that gradient; the shift's sums are numpy's over the pixels kept."""
    renderer = Renderer(default_catheter(), default_render_rig(), np.eye(3), BASE_W, seed=3)
    background = renderer.backgrounds[1]
    level = background.astype(np.float32)
    gx = cv2.sepFilter2D(level, cv2.CV_32F, shift_pixels._DERIVATIVE, shift_pixels._SMOOTH,
                         borderType=cv2.BORDER_REPLICATE)
    gy = cv2.sepFilter2D(level, cv2.CV_32F, shift_pixels._SMOOTH, shift_pixels._DERIVATIVE,
                         borderType=cv2.BORDER_REPLICATE)
    squared = gx * gx + gy * gy
    b = shift_pixels._BORDER_PX
    squared[:b] = squared[-b:] = squared[:, :b] = squared[:, -b:] = 0.0
    threshold = float(np.quantile(squared, 0.9))
    sample = np.zeros(-(-background.size // 7), np.float32)
    index, levels, gradient, cell, counts, sums = shift_kernels.select_pixels(
        background, 30, 200, shift_pixels._SMOOTH, shift_pixels._DERIVATIVE, b, threshold,
        4, 160, sample, 7)
    rows = slice(30, 200)
    near = np.isclose(squared[rows], threshold, rtol=1e-5)  # rounding may tip these
    chosen = np.zeros(background.shape, bool).ravel()
    chosen[index] = True
    chosen = chosen.reshape(background.shape)[rows]
    assert np.array_equal(chosen[~near], (squared[rows] > threshold)[~near])
    np.testing.assert_allclose(gradient, [gx.ravel()[index], gy.ravel()[index]], atol=1e-4)
    np.testing.assert_array_equal(levels, background.ravel()[index])
    np.testing.assert_array_equal(cell, (index // 640 // 4) * 160 + (index % 640) // 4)
    np.testing.assert_array_equal(counts, np.bincount(levels, minlength=256))
    np.testing.assert_allclose(sums[0], np.bincount(levels, gradient[0], minlength=256),
                               rtol=1e-9, atol=1e-6)
    flat = np.arange(30 * 640, 200 * 640)
    np.testing.assert_allclose(sample[flat[flat % 7 == 0] // 7],
                               squared.ravel()[flat[flat % 7 == 0]], rtol=1e-4, atol=1e-4)

    rng = np.random.default_rng(1)
    image = np.clip(background + 3.0 * rng.standard_normal(background.shape), 0, 255)
    image = image.astype(np.uint8).ravel()
    excluded = (rng.random(160 * 120) < 0.2).astype(np.uint8)
    lut = (1.05 * np.arange(256) - 2.0).astype(np.float32)
    gain, sx, sy, gate = 1.05, 0.3, -0.2, 12.0
    found = shift_kernels.shift_sums(image, index, levels, gradient, cell, excluded, lut,
                                     gain, sx, sy, gate)
    f = image[index].astype(np.float64)
    g = gain * gradient.astype(np.float64)
    residual = f - lut[levels]
    left = residual + g[0] * sx + g[1] * sy
    keep = ((excluded[cell] == 0) & (f > 0) & (f < 255) & (levels > 0) & (levels < 255)
            & (np.abs(left) <= gate))
    assert 0 < keep.sum() < keep.size
    g, residual, left = g[:, keep], residual[keep], left[keep]
    expected = (keep.sum(), left @ left, g[0] @ g[0], g[0] @ g[1], g[1] @ g[1],
                g[0] @ residual, g[1] @ residual)
    assert found[0] == expected[0]
    np.testing.assert_allclose(found[1:], expected[1:], rtol=1e-10)


def _distance_to_polyline(x, y, points):
    """Distance (px) of the points (x, y) (any shape) to the polyline through ``points``."""
    best = np.full(np.shape(x), np.inf)
    pairs = zip(points[:-1], points[1:], strict=True) if len(points) > 1 else [(points[0],) * 2]
    for a, b in pairs:
        d = b - a
        length2 = d @ d
        t = 0.0 if length2 == 0 else np.clip(((x - a[0]) * d[0] + (y - a[1]) * d[1]) / length2, 0, 1)
        best = np.minimum(best, np.hypot(x - a[0] - t * d[0], y - a[1] - t * d[1]))
    return best


def test_the_cells_left_out_are_those_near_the_polylines():
    """shift_grid_mask against the distance of every cell's centre to the polylines (their
    finite points; a single point is a disc), and every pixel within a half width of a
    polyline lies in a cell left out."""

    class Cells:
        cells_shape = (30, 40)  # a 160 x 120 image in cells of SHIFT_CELL_PX = 4

    rng = np.random.default_rng(11)
    cell = 4
    rows, columns = np.indices(Cells.cells_shape)
    centre_x, centre_y = (columns + 0.5) * cell - 0.5, (rows + 0.5) * cell - 0.5
    pixel_y, pixel_x = np.indices((120, 160))
    for trial in range(20):
        lines = []
        for _ in range(1 + trial % 2):
            n = 1 if trial % 5 == 0 else int(rng.integers(2, 12))
            points = np.cumsum(rng.normal(0.0, 12.0, (n, 2)), axis=0) + rng.uniform(-10, 170, 2)
            if n > 3:
                points[rng.integers(1, n - 1)] = np.nan  # not found: left out
            lines.append((points, float(rng.uniform(1.0, 14.0))))
        mask = shift_grid_mask(Cells, lines)
        expected = np.zeros(Cells.cells_shape, bool)
        covered = np.ones((120, 160), bool)
        for points, half_width in lines:
            finite = points[np.isfinite(points).all(axis=1)]
            reach = 0.5 * cell * (np.ceil(2.0 * half_width / cell) + 2)
            expected |= _distance_to_polyline(centre_x, centre_y, finite) <= reach
            near = _distance_to_polyline(pixel_x, pixel_y, finite) <= half_width
            covered &= ~near | mask.repeat(cell, 0).repeat(cell, 1).astype(bool)
        np.testing.assert_array_equal(mask.astype(bool), expected)
        assert covered.all()
