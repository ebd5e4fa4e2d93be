"""combine_views (tracker/vision/pair.py, compiled in tracker/vision/pair_kernels.py) against
the implementation it replaced, copied here as :func:`_reference_combine_views`: rows grouped
by the views that see them, :meth:`Rig.reconstruct` of each group, ``cv2.projectPoints`` per
view, residuals and variances in Python, the tip from the band with finite-difference
Jacobians.

The cases are real segmentations of rendered frames (two and three views, with and without
lens distortion) and the same segmentations changed: jittered, rows dropped in some views,
points moved 30 px (rejected) or moved with a wide covariance (kept by the 4 sigma spread),
the tip band missing in some or all views, non-finite tip extent or tube radius, a missing
covariance, a marker at the tip, other settings. Both must give the same PairSegmentation:
uv and cov within 1e-9 px / px^2 with NaN in the same places, the same ``rejected`` and
``tip_refined``; or both raise ValueError.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from models.catheter import default_catheter
from models.imaging import PinholeView, Rig, default_orthographic_rig
from replay.simulation.render import (
    DEFAULT_RENDER_DISTANCE_MM,
    DEFAULT_RENDER_FOCAL_PX,
    Renderer,
    default_render_rig,
)
from tests.fresh import last_value
from tests.tracker.segmentation_common import BASE_W
from tracker.vision import kernels
from tracker.vision.pair import _COARSE, _FINE, PairSegmentation, PairSegmenter, combine_views
from tracker.vision.segmentation import frame_points

TOLERANCE = 1e-9  # px for uv, px^2 for cov
MOVED_PX = 30.0


# ------------------------------------------------------------- the implementation replaced
def _tip_from_band(cameras, views, centre_w, jacobians, half_band_mm):
    n = len(views)
    linear = np.empty((4 * n, 3))
    JT = half_band_mm * np.array(jacobians)  # (views, 2, 3)
    linear[:n], linear[n : 2 * n] = JT[:, 0], JT[:, 1]
    directions = np.array([seg.tip_direction for seg in views])
    linear[2 * n : 3 * n] = (directions[:, None, :] @ JT)[:, 0]
    for k, camera in enumerate(cameras):
        x_cam = camera.R_cam_w @ centre_w + camera.t_cam_w
        linear[3 * n + k] = (x_cam / math.sqrt(x_cam @ x_cam)) @ camera.R_cam_w  # the ray
    extent = np.array([seg.tip_extent_px for seg in views])
    cap_px = np.array([0.25 * math.pi * seg.tube_radius_px for seg in views])
    tangent, misfit = kernels.tip_tangent(linear, extent, cap_px, _COARSE, _FINE)
    return centre_w + half_band_mm * tangent, misfit


_NUDGE_MM = 1e-3
_NUDGES = np.vstack([np.zeros(3), _NUDGE_MM * np.eye(3)])
_EYE2 = np.eye(2)


def _finite_point(p):
    return math.isfinite(p[0]) and math.isfinite(p[1])


def _reference_combine_views(segmenter, views, rig=None):
    s = segmenter.settings
    views = tuple(views)
    rows = [frame_points(view) for view in views]
    uv = [r[0] for r in rows]
    cov = [r[1] for r in rows]
    n_rows = uv[0].shape[0]
    if rig is None:
        return PairSegmentation(views, tuple(uv), tuple(cov), np.zeros(n_rows, bool))
    if rig.kind != "pinhole":
        raise ValueError("combine_views needs the pinhole rig the images were taken with")
    tip_rows = segmenter.frame_tip_rows
    banded = [k for k, view in enumerate(views) if _finite_point(view.tip_band_px)]
    check = uv
    if len(banded) >= 2:
        check = [u.copy() for u in uv]
        for k, view in enumerate(views):
            check[k][tip_rows] = view.tip_band_px if k in banded else np.nan
    listed = [c.tolist() for c in check]
    groups: dict[tuple[int, ...], list[int]] = {}
    for row in range(n_rows):
        seen = tuple(k for k, points in enumerate(listed) if _finite_point(points[row]))
        if len(seen) >= 2:
            groups.setdefault(seen, []).append(row)
    rejected = [False] * n_rows
    centre_w = None
    centre_px = {}
    for seen, members in groups.items():
        sub = rig.subset(seen)
        everyone = len(members) == n_rows
        points = sub.reconstruct(*(check[k] if everyone else check[k][members] for k in seen))
        m = len(members)
        if members[0] == 0:
            centre_w = points[0]
            points = np.vstack([points, centre_w + _NUDGES])
        residual = [0.0] * m
        variance = [0.0] * m
        for k, camera in zip(seen, sub.views, strict=True):
            projected = camera.project(points)
            if members[0] == 0:
                centre_px[k] = projected[m:]
            covariances = cov[k].tolist()
            for j, ((u, v), row) in enumerate(zip(projected[:m].tolist(), members, strict=True)):
                du, dv = u - listed[k][row][0], v - listed[k][row][1]
                residual[j] = max(residual[j], math.sqrt(du * du + dv * dv))
                variance[j] += covariances[row][0][0] + covariances[row][1][1]
        for j, row in enumerate(members):
            spread = math.sqrt(variance[j]) if math.isfinite(variance[j]) else 0.0
            rejected[row] = residual[j] > max(s.epipolar_gate_px, 4.0 * spread)
    refined = bool(
        len(banded) >= 2
        and not rejected[0]
        and all(math.isfinite(views[k].tip_extent_px * views[k].tube_radius_px) for k in banded)
    )
    if refined:
        half_band = 0.5 * s.band_length_mm
        jacobians = [(centre_px[k][1:] - centre_px[k][0]).T / _NUDGE_MM for k in banded]
        tip_w, misfit = _tip_from_band(
            [rig.views[k] for k in banded], [views[k] for k in banded], centre_w, jacobians,
            half_band,
        )  # fmt: skip
        offset = tip_w - centre_w
        for k, J in zip(banded, jacobians, strict=True):
            px_per_mm = math.sqrt(max(a * a + b * b + c * c for a, b, c in J.tolist()))
            extra = (half_band * px_per_mm * s.tip_direction_sigma_rad) ** 2 + 0.5 * misfit
            uv[k][tip_rows] = centre_px[k][0] + J @ offset
            cov[k][tip_rows] = views[k].tip_band_cov + extra * _EYE2
    if any(rejected):
        for u, c in zip(uv, cov, strict=True):
            u[rejected] = np.nan
            c[rejected] = np.nan
    return PairSegmentation(views, tuple(uv), tuple(cov), np.array(rejected), refined)


# ------------------------------------------------------------------------------ the cases
DISTORTION = (-0.6, 1.5, 2e-3, -1.5e-3, -4.0)  # k1, k2, p1, p2, k3: up to a few px here


def render_rig(n_views: int, distorted: bool) -> Rig:
    """The render rig's cameras (and, for three, one above), the first and last distorted."""
    d, f = DEFAULT_RENDER_DISTANCE_MM, DEFAULT_RENDER_FOCAL_PX
    places = [([0.0, -d, 0.0], [0.0, 0.0, 1.0]), ([d, 0.0, 0.0], [0.0, 0.0, 1.0])]
    places += [([0.0, 0.0, d], [0.0, 1.0, 0.0])] * (n_views == 3)
    views = [
        PinholeView.look_at(
            centre, np.zeros(3), up, f,
            dist=DISTORTION if distorted and k in (0, n_views - 1) else None,
        )
        for k, (centre, up) in enumerate(places)
    ]  # fmt: skip
    return Rig(*views, names=("front", "side", "top")[:n_views])


RIGS = {
    "two": lambda: default_render_rig(),
    "three": lambda: render_rig(3, False),
    "two distorted": lambda: render_rig(2, True),
    "three distorted": lambda: render_rig(3, True),
}
POSES = [  # joints (3,) and torsion, rad
    (np.array([0.8, 0.7, 0.5]), 0.0),
    (np.array([-1.2, 0.9, -0.6]), 0.4),
    (np.array([2.5, -0.5, 0.9]), -1.0),
    (np.array([0.3, 0.15, -0.2]), 2.0),
]


@dataclasses.dataclass
class Base:
    name: str
    rig: Rig
    segmenter: object  # the Segmenter of the frame
    views: tuple


@pytest.fixture(scope="module")
def bases() -> list[Base]:
    catheter = default_catheter()
    out = []
    for name, make in RIGS.items():
        rig = make()
        renderer = Renderer(catheter, rig, np.eye(3), BASE_W, seed=3)
        pair = PairSegmenter(catheter, rig, np.eye(3), BASE_W, renderer.backgrounds)
        rng = np.random.default_rng(4)
        for q, delta_L in POSES:
            images = renderer.render(q, delta_L, rng).images
            pair.reset()
            out.append(Base(name, rig, pair.segmenter, pair.segment(images).views))
    return out


def _moved(p, rng, distance_px):
    angle = rng.uniform(0.0, 2.0 * np.pi)
    return p + distance_px * np.array([np.cos(angle), np.sin(angle)])


def _with(views, k, **changes):
    views = list(views)
    views[k] = dataclasses.replace(views[k], **changes)
    return tuple(views)


def _jitter(views, rng, k):
    def shake(a):
        return a + rng.normal(0.0, 0.3, np.shape(a))

    return tuple(
        dataclasses.replace(
            v, tip_px=shake(v.tip_px), markers_px=shake(v.markers_px),
            tip_band_px=shake(v.tip_band_px),
        )
        for v in views
    )  # fmt: skip


def _drop_marker(views, rng, k):
    found = views[k].markers_found.copy()
    found[rng.integers(found.size)] = False
    return _with(views, k, markers_found=found)


def _drop_marker_nan(views, rng, k):
    j = rng.integers(views[k].markers_found.size)
    found, px = views[k].markers_found.copy(), views[k].markers_px.copy()
    found[j], px[j] = False, np.nan
    return _with(views, k, markers_found=found, markers_px=px)


def _drop_tip(views, rng, k):
    return _with(views, k, tip_px=np.full(2, np.nan))


def _move_marker(views, rng, k):
    px = views[k].markers_px.copy()
    j = rng.integers(px.shape[0])
    px[j] = _moved(px[j], rng, MOVED_PX)
    return _with(views, k, markers_px=px)


def _move_marker_wide(views, rng, k):
    """Moved, but with a covariance wide enough that 4 sigma covers it."""
    views = _move_marker(views, rng, k)
    return _with(views, k, markers_cov=views[k].markers_cov * 400.0 + 25.0 * np.eye(2))


def _move_tip(views, rng, k):
    return _with(views, k, tip_px=_moved(views[k].tip_px, rng, MOVED_PX))


def _move_tip_near_gate(views, rng, k):
    return _with(views, k, tip_px=_moved(views[k].tip_px, rng, rng.uniform(1.0, 5.0)))


def _move_band(views, rng, k):
    return _with(views, k, tip_band_px=_moved(views[k].tip_band_px, rng, MOVED_PX))


def _no_band(views, rng, k):
    return _with(views, k, tip_band_px=np.full(2, np.nan), tip_band_cov=np.full((2, 2), np.nan))


def _no_band_anywhere(views, rng, k):
    for j in range(len(views)):
        views = _no_band(views, rng, j)
    return views


def _nan_extent(views, rng, k):
    return _with(views, k, tip_extent_px=math.nan)


def _inf_extent(views, rng, k):
    return _with(views, k, tip_extent_px=math.inf)


def _nan_radius(views, rng, k):
    return _with(views, k, tube_radius_px=math.nan)


def _nan_tip_cov(views, rng, k):
    return _with(views, k, tip_cov=np.full((2, 2), np.nan))


def _only_one_view(views, rng, k):
    """Every row missing in all views but k (nothing to check)."""
    for j in range(len(views)):
        if j != k:
            views = _drop_tip(views, rng, j)
            views = _with(views, j, markers_found=np.zeros_like(views[j].markers_found))
    return views


CHANGES = [
    _jitter, _drop_marker, _drop_marker_nan, _drop_tip, _move_marker, _move_marker_wide,
    _move_tip, _move_tip_near_gate, _move_band, _no_band, _no_band_anywhere, _nan_extent,
    _inf_extent, _nan_radius, _nan_tip_cov, _only_one_view,
]  # fmt: skip


def _marker_at_tip(segmenter, views):
    """The same frame with one more marker, at the tip (a tip row besides row 0)."""
    tip_rows = np.append(segmenter.frame_tip_rows, True)
    views = tuple(
        dataclasses.replace(
            v,
            markers_px=np.vstack([v.markers_px, v.tip_px]),
            markers_cov=np.concatenate([v.markers_cov, v.tip_cov[None]]),
            markers_found=np.append(v.markers_found, v.tip_found),
        )
        for v in views
    )
    return SimpleNamespace(settings=segmenter.settings, frame_tip_rows=tip_rows), views


SETTINGS = [
    {},
    {"epipolar_gate_px": 1},  # an int, as a TOML file may give it
    {"epipolar_gate_px": 10.0, "band_length_mm": 2.0, "tip_direction_sigma_rad": 0.1},
]


def _cases(bases, seed=5):
    """(label, segmenter, views, rig): every base as segmented, with each change in each
    view, and random combinations of changes, markers at the tip and settings."""
    rng = np.random.default_rng(seed)
    for base in bases:
        V = len(base.views)
        yield base.name, base.segmenter, base.views, base.rig
        for change in CHANGES:
            for k in range(V):
                yield (
                    f"{base.name} {change.__name__}({k})",
                    base.segmenter,
                    change(base.views, rng, k),
                    base.rig,
                )
        for i in range(25):
            segmenter, views = base.segmenter, base.views
            if rng.random() < 0.3:
                segmenter, views = _marker_at_tip(segmenter, views)
            settings = SETTINGS[rng.integers(len(SETTINGS))]
            if settings:
                segmenter = SimpleNamespace(
                    settings=dataclasses.replace(segmenter.settings, **settings),
                    frame_tip_rows=segmenter.frame_tip_rows,
                )
            names = []
            for _ in range(rng.integers(1, 4)):
                change, k = CHANGES[rng.integers(len(CHANGES))], int(rng.integers(V))
                views = change(views, rng, k)
                names.append(f"{change.__name__}({k})")
            yield f"{base.name} random {i}: {' '.join(names)}", segmenter, views, base.rig


def _compare(segmenter, views, rig) -> tuple[PairSegmentation, float] | None:
    """Both implementations on one frame: the result and the largest difference, or None
    when both raise ValueError."""
    try:
        expected = _reference_combine_views(segmenter, views, rig)
    except ValueError:
        with pytest.raises(ValueError):
            combine_views(segmenter, views, rig)
        return None
    got = combine_views(segmenter, views, rig)
    assert len(got.views) == len(views) and all(
        a is b for a, b in zip(got.views, views, strict=True)
    )
    assert got.rejected.dtype == bool and got.rejected.shape == expected.rejected.shape
    assert np.array_equal(got.rejected, expected.rejected)
    assert got.tip_refined == expected.tip_refined and isinstance(got.tip_refined, bool)
    largest = 0.0
    for name in ("uv", "cov"):
        for a, b in zip(getattr(got, name), getattr(expected, name), strict=True):
            assert a.shape == b.shape and a.dtype == b.dtype
            assert np.array_equal(np.isnan(a), np.isnan(b)), name
            np.testing.assert_allclose(a, b, rtol=0.0, atol=TOLERANCE, err_msg=name)
            if np.isfinite(a).any():
                largest = max(largest, float(np.nanmax(np.abs(a - b))))
    return expected, largest


# ------------------------------------------------------------------------------- the tests
def frame_points_uv(views):
    return [frame_points(v)[0] for v in views]


def test_combine_views_matches_the_implementation_it_replaced(bases):
    counts: Counter = Counter()
    largest = 0.0
    for label, segmenter, views, rig in _cases(bases):
        try:
            compared = _compare(segmenter, views, rig)
        except AssertionError as error:
            raise AssertionError(f"case {label!r}: {error}") from error
        if compared is None:
            counts["error"] += 1
            continue
        result, difference = compared
        largest = max(largest, difference)
        counts["case"] += 1
        counts["views", len(views)] += 1
        counts["distorted"] += any(np.any(v.dist) for v in rig.views)
        counts["refined"] += result.tip_refined
        counts["rejected"] += bool(result.rejected.any())
        counts["tip rows"] += int(np.count_nonzero(segmenter.frame_tip_rows) > 1)
        # Rows seen (checked) by some views only, and rows seen by one view (not checked).
        seen = np.array([np.isfinite(u).all(axis=1) for u in frame_points_uv(views)])
        counts["partial"] += bool(((seen.sum(axis=0) >= 2) & ~seen.all(axis=0)).any())
        counts["unchecked"] += bool((seen.sum(axis=0) == 1).any())
        banded = sum(_finite_point(v.tip_band_px) for v in views)
        counts["band in < 2 views"] += banded < 2
        counts["non-finite extent"] += banded >= 2 and not all(
            math.isfinite(v.tip_extent_px * v.tube_radius_px) for v in views
        )
    # Every branch is exercised, many times.
    assert counts["case"] >= 1000, counts
    for key in ("refined", "rejected", "tip rows", "partial", "unchecked", "distorted",
                "band in < 2 views", "non-finite extent", ("views", 2), ("views", 3)):  # fmt: skip
        assert counts[key] >= 20, (key, counts)
    assert counts["case"] - counts["refined"] >= 100, counts
    assert largest <= TOLERANCE


def test_without_a_rig_and_with_an_orthographic_one(bases):
    base = bases[0]
    expected, largest = _compare(base.segmenter, base.views, None)
    assert largest == 0.0 and not expected.rejected.any() and not expected.tip_refined
    for rig in (default_orthographic_rig(), render_rig(3, False)):  # wrong kind, view count
        with pytest.raises(ValueError):
            combine_views(base.segmenter, base.views, rig)


def test_points_that_cannot_be_triangulated_raise_in_both(bases):
    """A point behind a camera (its mirror image projected), and rays along the baseline."""
    base = next(b for b in bases if b.name == "two")
    front, side = base.rig.views
    behind_w = front.center_w - 50.0 * front.R_cam_w[2]  # 50 mm behind the front camera
    x_cam = front.R_cam_w @ behind_w + front.t_cam_w
    mirror_px = front.K[:2, :2] @ (x_cam[:2] / x_cam[2]) + front.K[:2, 2]
    cases = [(mirror_px, side.project(behind_w))]
    # Each camera's centre seen from the other: both rays lie on the baseline.
    cases.append((front.project(side.center_w), side.project(front.center_w)))
    for px_front, px_side in cases:
        views = _with(base.views, 0, markers_px=px_front[None])
        views = _with(views, 1, markers_px=px_side[None])
        assert _compare(base.segmenter, views, base.rig) is None


def test_a_live_session_compiles_nothing():
    """Making a PairSegmenter compiles or loads the kernels of combine_views with the
    argument types it passes, whatever the rig (two or three views, distortion) and the
    settings' number types: segmenting then compiles nothing. In a fresh interpreter, as
    compiled versions only accumulate; every kernel is cached and free of the GIL."""
    script = """
import dataclasses, numba, numpy as np
from types import SimpleNamespace
from models.catheter import default_catheter
from replay.simulation.render import Renderer, default_render_rig
from tests.tracker.test_combine_views import render_rig
from tracker.vision import kernels, pair_kernels
from tracker.vision.pair import PairSegmenter, combine_views
def versions():
    out = {name: (len(f.signatures), f.targetoptions["nogil"], type(f._cache).__name__)
           for name, f in vars(pair_kernels).items()
           if isinstance(f, numba.core.registry.CPUDispatcher)}
    out["tip_tangent"] = (len(kernels.tip_tangent.signatures), True, "FunctionCache")
    return out
catheter, rig, base = default_catheter(), default_render_rig(), np.array([0.0, 0.0, -15.0])
renderer = Renderer(catheter, rig, np.eye(3), base, seed=1)
segmenter = PairSegmenter(catheter, rig, np.eye(3), base, renderer.backgrounds)
before = versions()
pair = renderer.render(np.array([0.8, 0.7, 0.5]), 0.0, np.random.default_rng(0))
result = segmenter.segment(pair.images)
segmenter.segment(pair.images, pair.points_px)
three = render_rig(3, True)
inner = SimpleNamespace(frame_tip_rows=segmenter.segmenter.frame_tip_rows,
    settings=dataclasses.replace(segmenter.segmenter.settings, epipolar_gate_px=2))
combine_views(inner, result.views + result.views[:1], three)
print(repr((before, versions(), result.tip_refined)))
"""
    before, after, refined = last_value(script)
    assert refined
    assert after == before
    for name, (count, nogil, cache) in before.items():  # helpers are inlined: no version
        assert nogil and cache == "FunctionCache" and count == int(name[0] != "_"), name


@pytest.mark.parametrize(
    "dist",
    [
        np.zeros(5),
        np.array([-0.21, 0.08, 0.0012, -0.0009, -0.015]),
        np.array([0.12, -0.3, -0.002, 0.0015, 0.4]),
    ],
)
def test_the_written_out_camera_model_is_opencvs(dist):
    """pair_kernels' projection and undistortion against cv2.projectPoints and
    cv2.undistortPoints (PinholeView's criteria) on 2000 points spread over the image."""
    from tracker.vision import pair_kernels

    view = PinholeView.look_at(
        np.array([30.0, -380.0, 60.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]), 2500.0,
        dist=dist,
    )  # fmt: skip
    rng = np.random.default_rng(11)
    points = rng.uniform(-60.0, 60.0, (2000, 3))
    R = cv2.Rodrigues(cv2.Rodrigues(np.array(view.R_cam_w))[0])[0]
    K = np.array(view.K)
    intrinsics = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    k = np.asarray(view.dist, float)
    ours = np.array([pair_kernels._project(R, view.t_cam_w, intrinsics, k, *p) for p in points])
    np.testing.assert_allclose(ours, view.project(points), rtol=0.0, atol=1e-9)
    pixels = view.project(points)
    ideal = np.array([pair_kernels._undistort(u, v, intrinsics, k) for u, v in pixels])
    np.testing.assert_allclose(ideal, view.undistort(pixels), rtol=0.0, atol=1e-9)
    if dist.any():  # the test sees the distortion
        assert np.abs(ideal - pixels).max() > 1.0
