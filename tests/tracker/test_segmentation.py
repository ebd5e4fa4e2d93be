"""Segmentation of rendered bi-plane images: accuracy against the truth and the bound, bad input."""

import dataclasses

import numpy as np
import pytest

from models.bounds import crb_tip
from models.catheter import default_catheter
from models.imaging import BiplaneRig
from models.rig_file import orthographic_rig, plane_from_pixels
from models.rotations import wrap_angle
from replay.simulation.render import Renderer, default_render_rig, far_view, render_view
from tracker.estimators import make_estimator
from tracker.reconstruction import Reconstructor
from tracker.vision.segmentation import (
    PairSegmenter,
    SegmentationFlag,
    SegmentationSettings,
    Segmenter,
    check_image,
    frame_points,
    load_segmentation_settings,
    read_grayscale,
)

BASE_W = np.array([0.0, 0.0, -15.0])
N_CONFIGS = 20
DELTA_2 = [0.0, np.pi / 2]


def catheter_with(delta_2):
    return dataclasses.replace(default_catheter(), delta_2_rad=delta_2)


def bent_configurations(n, seed):
    """Joints and torsion of bent catheters (|q_p| >= 0.4 mm: delta_L observable)."""
    rng = np.random.default_rng(seed)
    q_p = rng.uniform(0.4, 1.0, n) * rng.choice([-1.0, 1.0], n)
    q = np.column_stack([rng.uniform(-np.pi, np.pi, n), q_p, rng.uniform(-1.0, 1.0, n)])
    return q, rng.uniform(-np.pi, np.pi, n)


@dataclasses.dataclass
class Session:
    catheter: object
    rig: BiplaneRig
    renderer: Renderer
    segmenter: PairSegmenter
    q: np.ndarray
    delta_L: np.ndarray
    truth: list
    results: list


def run_session(catheter, rig, seed, n=N_CONFIGS):
    renderer = Renderer(catheter, rig, np.eye(3), BASE_W, seed=seed)
    segmenter = PairSegmenter(catheter, rig, np.eye(3), BASE_W, renderer.backgrounds)
    q, delta_L = bent_configurations(n, seed)
    rng = np.random.default_rng(seed + 1)
    truth, results = [], []
    for qi, di in zip(q, delta_L, strict=True):
        pair = renderer.render(qi, di, rng)
        truth.append(pair)
        results.append(segmenter.segment(pair.images))
    return Session(catheter, rig, renderer, segmenter, q, delta_L, truth, results)


@pytest.fixture(scope="module", params=DELTA_2, ids=["delta_2=0", "delta_2=pi/2"])
def session(request):
    return run_session(catheter_with(request.param), default_render_rig(), seed=11)


def tip_errors_px(session):
    """Per view, the segmented minus the true tip, px, for frames with a tip in both views."""
    rows = []
    for pair, result in zip(session.truth, session.results, strict=True):
        if np.all(np.isfinite(result.uv_front[0])) and np.all(np.isfinite(result.uv_side[0])):
            rows.append(
                (result.uv_front[0] - pair.points_px[0][0], result.uv_side[0] - pair.points_px[1][0])
            )
    return np.array(rows)  # (n, 2 views, 2)


def test_most_bent_frames_give_a_tip_in_both_views(session):
    assert len(tip_errors_px(session)) >= 0.8 * N_CONFIGS


def test_reconstructed_tip_error_below_0_3_mm_rms(session):
    errors = []
    for pair, result in zip(session.truth, session.results, strict=True):
        if np.all(np.isfinite(result.uv_front[0])) and np.all(np.isfinite(result.uv_side[0])):
            tip_w = session.rig.reconstruct(result.uv_front[0], result.uv_side[0])
            errors.append(np.linalg.norm(tip_w - pair.points_w[0]))
    errors = np.array(errors)
    assert np.sqrt(np.mean(errors**2)) < 0.3
    assert errors.max() < 0.6


def test_markers_are_sub_pixel(session):
    errors = []
    for pair, result in zip(session.truth, session.results, strict=True):
        for uv, truth in ((result.uv_front, pair.points_px[0]), (result.uv_side, pair.points_px[1])):
            found = np.all(np.isfinite(uv), axis=1)
            errors.append(np.linalg.norm(uv[found] - truth[found], axis=1))
    errors = np.concatenate(errors)
    assert np.sqrt(np.mean(errors**2)) < 0.5
    assert errors.max() < 2.0  # no point silently wrong


def test_tip_position_errors_within_1_5_bound_from_measured_noise(session):
    """Closed-form Tip Position on the segmented frames against the Cramer-Rao bound.

    The bound uses the segmentation noise measured on these very frames (the covariance of
    the tip's pixel errors in each view), propagated through the reconstruction.
    """
    errors_px = tip_errors_px(session)
    cov_f = np.cov(errors_px[:, 0].T, bias=True) + np.outer(*[errors_px[:, 0].mean(0)] * 2)
    cov_s = np.cov(errors_px[:, 1].T, bias=True) + np.outer(*[errors_px[:, 1].mean(0)] * 2)
    reconstructor = Reconstructor(session.catheter, session.rig, np.eye(3), BASE_W)
    estimator = make_estimator("tip-position", session.catheter)
    normalised = []
    for q, delta_L, pair, result in zip(
        session.q, session.delta_L, session.truth, session.results, strict=True
    ):
        reconstructor.reset()
        observation = reconstructor.observe(result.frame(0.0, q))
        if not observation.has_tip():
            continue
        estimate = estimator.step(observation)
        cov_w = session.rig.reconstruction_covariance(pair.points_w[0], cov_f, cov_s)
        bound = float(crb_tip(session.catheter, q, delta_L, cov_w))
        normalised.append(wrap_angle(estimate.delta_L_rad - delta_L) / bound)
    normalised = np.array(normalised)
    assert len(normalised) >= 0.8 * N_CONFIGS
    assert np.sqrt(np.mean(normalised**2)) <= 1.5


def test_reported_covariance_is_honest(session):
    """Mean squared Mahalanobis error of the tip against its reported covariance (2 dof)."""
    nees = []
    for pair, result in zip(session.truth, session.results, strict=True):
        for uv, cov, truth in (
            (result.uv_front, result.cov_front, pair.points_px[0]),
            (result.uv_side, result.cov_side, pair.points_px[1]),
        ):
            if np.all(np.isfinite(uv[0])):
                e = uv[0] - truth[0]
                nees.append(e @ np.linalg.solve(cov[0], e))
    assert 0.3 < np.mean(nees) < 6.0


def test_noise_estimate_matches_the_sensor_noise(session):
    sigma = session.renderer.settings.noise_sigma_gray
    for result in session.results:
        for view in (result.front, result.side):
            assert view.noise_sigma_gray == pytest.approx(np.hypot(sigma, 0.4), rel=0.15)


def test_far_views_agree_with_the_orthographic_model():
    """Near-orthographic views: pixels -> plane mm -> the paper's reconstruction (eq. estDK)."""
    near = default_render_rig()
    rig = BiplaneRig(far_view(near.front, 20.0), far_view(near.side, 20.0))
    session = run_session(catheter_with(0.0), rig, seed=5, n=8)
    planes = orthographic_rig(rig)
    errors, gaps = [], []
    for pair, result in zip(session.truth, session.results, strict=True):
        if not (np.all(np.isfinite(result.uv_front[0])) and np.all(np.isfinite(result.uv_side[0]))):
            continue
        mm_f = plane_from_pixels(rig.front, result.uv_front[0])
        mm_s = plane_from_pixels(rig.side, result.uv_side[0])
        tip_ortho = planes.reconstruct(mm_f, mm_s)
        tip_pinhole = rig.reconstruct(result.uv_front[0], result.uv_side[0])
        errors.append(np.linalg.norm(tip_ortho - pair.points_w[0]))
        gaps.append(np.linalg.norm(tip_ortho - tip_pinhole))
    assert len(errors) >= 6
    assert np.sqrt(np.mean(np.square(errors))) < 0.3
    assert max(gaps) < 0.1


def test_without_the_registered_base_the_thicker_end_is_the_base(session):
    segmenter = session.segmenter.segmenter
    pair = session.truth[0]
    with_hint = segmenter.segment(pair.images[0], pair.backgrounds[0], pair.base_px[0])
    without = segmenter.segment(pair.images[0], pair.backgrounds[0], None)
    assert np.linalg.norm(without.base_px - pair.base_px[0]) < 1.0
    assert np.allclose(without.markers_px, with_hint.markers_px, atol=0.5, equal_nan=True)


# ----------------------------------------------------------------------------- bad input
@pytest.fixture(scope="module")
def scene():
    catheter = default_catheter()
    rig = default_render_rig()
    renderer = Renderer(catheter, rig, np.eye(3), BASE_W, seed=2)
    return catheter, rig, renderer


Q_BENT = np.array([0.8, 0.7, 0.5])


def assert_within_covariance(uv, cov, truth, n_sigma=3.0):
    """Every point that was reported lies within n_sigma of the truth by its own covariance."""
    for point, c, true in zip(uv, cov, truth, strict=True):
        if np.all(np.isfinite(point)):
            e = point - true
            assert e @ np.linalg.solve(c, e) < n_sigma**2
            assert np.linalg.norm(e) < 3.0


def test_no_catheter_in_view_is_a_flagged_empty_frame(scene):
    catheter, rig, renderer = scene
    rng = np.random.default_rng(0)
    empty = tuple(
        render_view(v, catheter, None, bg, rng)
        for v, bg in zip((rig.front, rig.side), renderer.background_float, strict=True)
    )
    segmenter = PairSegmenter(catheter, rig, np.eye(3), BASE_W, renderer.backgrounds)
    result = segmenter.segment(empty)
    assert result.front.flags & SegmentationFlag.NO_CATHETER
    assert result.side.flags & SegmentationFlag.NO_CATHETER
    assert np.all(np.isnan(result.uv_front)) and np.all(np.isnan(result.cov_side))
    observation = Reconstructor(catheter, rig, np.eye(3), BASE_W).observe(
        result.frame(0.0, Q_BENT)
    )
    assert not observation.has_tip()


def test_tip_leaving_the_image_is_flagged_not_guessed(scene):
    catheter, rig, _ = scene
    base = np.array([44.0, 0.0, -15.0])  # near the right edge of the front image
    renderer = Renderer(catheter, rig, np.eye(3), base, seed=2)
    pair = renderer.render(np.array([0.5, 0.7, 0.5]), 0.0, np.random.default_rng(0))
    assert pair.points_px[0][0, 0] > rig.front.image_size[0]  # the tip is out of the image
    segmenter = PairSegmenter(catheter, rig, np.eye(3), base, renderer.backgrounds)
    result = segmenter.segment(pair.images)
    assert result.front.flags & SegmentationFlag.TIP_AT_BORDER
    assert np.all(np.isnan(result.uv_front[0]))
    # The side view alone: its tip is the far end, whose covariance includes the end disc.
    assert np.all(np.isfinite(result.uv_side))
    assert_within_covariance(result.uv_side, result.cov_side, pair.points_px[1])


@pytest.mark.parametrize("what", ["marker", "tip"])
def test_occluded_point_is_missing_and_the_rest_right(scene, what):
    catheter, rig, renderer = scene
    rng = np.random.default_rng(3)
    clean = renderer.render(Q_BENT, 0.0, rng)
    row = 1 if what == "marker" else 0
    u, v = clean.points_px[0][row].astype(int)
    occluder = [(u - 7, v - 7, 14, 14)]
    pair = renderer.render(Q_BENT, 0.0, rng, occluders=(occluder, []))
    segmenter = PairSegmenter(catheter, rig, np.eye(3), BASE_W, renderer.backgrounds)
    result = segmenter.segment(pair.images)
    expected = SegmentationFlag.MARKER_MISSING if what == "marker" else SegmentationFlag.TIP_NOT_FOUND
    assert result.front.flags & expected
    assert np.all(np.isnan(result.uv_front[row]))
    assert_within_covariance(result.uv_front, result.cov_front, pair.points_px[0])
    assert_within_covariance(result.uv_side, result.cov_side, pair.points_px[1])
    if what == "marker":
        assert np.all(np.isfinite(result.uv_front[0]))  # the catheter is joined across the gap


def test_catheter_folded_onto_itself_in_one_view_is_withheld(scene):
    """Bending plane seen edge-on by the side camera: the distal segment folds back."""
    catheter, rig, renderer = scene
    pair = renderer.render(np.array([0.0, 0.7, 0.5]), 0.0, np.random.default_rng(0))
    result = PairSegmenter(catheter, rig, np.eye(3), BASE_W, renderer.backgrounds).segment(
        pair.images
    )
    assert result.side.flags & SegmentationFlag.OVERLAP
    assert np.all(np.isnan(result.uv_side))
    assert np.all(np.isfinite(result.uv_front[0]))
    assert_within_covariance(result.uv_front, result.cov_front, pair.points_px[0])


def test_wrong_image_size_or_type_is_one_clear_error(scene):
    catheter, rig, renderer = scene
    segmenter = Segmenter(catheter)
    background = renderer.backgrounds[0]
    with pytest.raises(ValueError, match="expected 640x480"):
        segmenter.segment(np.zeros((240, 320), np.uint8), background)
    with pytest.raises(ValueError, match="uint8"):
        segmenter.segment(background.astype(np.float32), background)
    with pytest.raises(ValueError, match="single-channel"):
        segmenter.segment(np.stack([background] * 3, axis=-1), background)
    with pytest.raises(ValueError, match="numpy array"):
        check_image([[1, 2]])
    with pytest.raises(ValueError, match="background"):
        PairSegmenter(catheter, rig, np.eye(3), BASE_W, (background[:100], background))


def test_unreadable_image_file_is_one_clear_error(tmp_path):
    bad = tmp_path / "frame.png"
    bad.write_bytes(b"not a png")
    with pytest.raises(OSError, match="cannot read image"):
        read_grayscale(bad)
    with pytest.raises(OSError, match="no such file"):
        read_grayscale(tmp_path / "missing.png")


def test_frame_points_follow_the_marker_order(scene):
    catheter, rig, renderer = scene
    pair = renderer.render(Q_BENT, 0.0, np.random.default_rng(1))
    seg = Segmenter(catheter).segment(pair.images[0], pair.backgrounds[0], pair.base_px[0])
    uv, cov, found = frame_points(seg)
    n = 1 + len(catheter.marker_arclengths_mm)
    assert uv.shape == (n, 2) and cov.shape == (n, 2, 2) and found.all()
    assert np.abs(uv[1:] - pair.points_px[0][1:]).max() < 0.5
    assert np.all(np.linalg.eigvalsh(cov) > 0)


# ------------------------------------------------------------------------------ settings
def test_settings_file_overrides_defaults_and_rejects_unknown_keys(tmp_path):
    good = tmp_path / "settings.toml"
    good.write_text('format = "cathtrack-segmentation"\n[segmentation]\nband_contrast = 0.7\n')
    settings = load_segmentation_settings(good)
    assert settings.band_contrast == 0.7
    assert settings.threshold_sigma == SegmentationSettings().threshold_sigma
    unknown = tmp_path / "unknown.toml"
    unknown.write_text("[segmentation]\nband_contrst = 0.7\n")
    with pytest.raises(ValueError, match="band_contrst"):
        load_segmentation_settings(unknown)
    bad = tmp_path / "bad.toml"
    bad.write_text("[segmentation]\nband_contrast = 1.5\n")
    with pytest.raises(ValueError, match="band_contrast"):
        load_segmentation_settings(bad)
    with pytest.raises(ValueError, match="cannot read"):
        load_segmentation_settings(tmp_path / "missing.toml")
