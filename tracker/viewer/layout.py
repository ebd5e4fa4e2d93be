"""Where everything goes in the rerun viewer: entity paths, colours, the default blueprint and
the geometry drawn (the bending-plane fan, the dial, marker rings). :mod:`tracker.viewer.sink`
logs to these paths.

- ``world/...`` -- the 3-D scene in {W}, mm: the catheter model at the estimated bending plane
  (with the plane as a surface) and, where known, at the true one; the reconstructed markers;
  the tip's +/-2 sigma arc of uncertainty about the base axis and the +/-2 sigma fan of the
  bending plane; the cameras (pinhole views; left out of the default 3-D view, which is
  framed on the catheter);
- ``world/cameras/<view>/...`` -- each camera's image, the segmented markers (rings) and the
  markers reprojected from the estimate (dots, pinhole rigs); ``views/<view>/...`` the same
  points in mm for the paper's orthographic planes, which have no camera;
- ``dial/...`` -- the bending plane delta_1 = q_r + delta_L of each method and of the truth as
  needles on a dial, looking down the base axis (the wrapped angle, where it is natural);
- ``series/...`` -- time series: delta_L of every method, unwrapped (deg), with the truth and
  the +/-2 sigma band; the bending-plane error with its +/-2 sigma band (deg); NIS per degree
  of freedom with the chi-square 95% band; the joint values (``cathtrack view``); in live runs
  also the latency from the image time stamp to the estimate (ms) and the dropped and
  predict-only frames.

One colour per method everywhere (:func:`method_color`): the catheter, the fan, the reprojected
markers, the dial and every series of a method share it; the truth is green.

Time is the ``time`` timeline (s since the start of the session) and the ``frame`` sequence.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from models.pose import Pose

Array = np.ndarray
Color = tuple[int, int, int]

VIEWS = ("front", "side")  # the view names of a rig that does not name its views
TIMELINE = "time"
FRAME_SEQUENCE = "frame"

# Entity paths, in one place.
WORLD = "world"
CAMERAS = "world/cameras"
CATHETER_ESTIMATE = "world/catheter/estimate"
CATHETER_TRUTH = "world/catheter/truth"
PLANE_FAN = "world/catheter/plane_fan"
BENDING_PLANE = "world/catheter/bending_plane"
MARKERS_3D = "world/markers"
DIAL = "dial"
DIAL_FRAME = "dial/frame"
DIAL_TRUTH = "dial/truth"
SERIES_DELTA_L = "series/delta_L"
# Series are drawn (and listed in the legend) in the order of their paths: "_truth" first,
# under the methods, so that an estimate on the truth stays visible.
DELTA_L_TRUTH = f"{SERIES_DELTA_L}/_truth"
SERIES_ERROR = "series/error"
SERIES_NIS = "series/nis"
SERIES_JOINTS = "series/joints"
SERIES_LATENCY = "series/latency_ms"
SERIES_FRAMES = "series/frames"
LATENCY_ESTIMATE = f"{SERIES_LATENCY}/estimate"
FRAMES_DROPPED = f"{SERIES_FRAMES}/dropped"
FRAMES_PREDICT_ONLY = f"{SERIES_FRAMES}/predict_only"
SIDES = ("plus", "minus")


def camera_path(view: str) -> str:
    return f"{CAMERAS}/{view}"


def image_path(view: str) -> str:
    return f"{CAMERAS}/{view}/image"


def view_path(view: str, pinhole: bool) -> str:
    """Where a view's 2-D points go: under its camera, or on its own for a plane (mm)."""
    return camera_path(view) if pinhole else f"views/{view}"


def delta_L_path(method: str) -> str:
    return f"{SERIES_DELTA_L}/{method}"


def band_path(method: str, side: str) -> str:
    """One side ("plus" or "minus") of a method's +/-2 sigma band about its delta_L."""
    return f"{SERIES_DELTA_L}/{method}_{side}2sigma"


def error_path(method: str) -> str:
    return f"{SERIES_ERROR}/{method}"


def error_band_path(method: str, side: str) -> str:
    """One side of a method's +/-2 sigma about zero error."""
    return f"{SERIES_ERROR}/{method}_{side}2sigma"


def nis_path(method: str) -> str:
    return f"{SERIES_NIS}/{method}"


def nis_band_path(method: str, side: str) -> str:
    """One side ("low" or "high") of the chi-square 95% band of a method's NIS per dof."""
    return f"{SERIES_NIS}/{method}_chi2_{side}"


def dial_path(method: str) -> str:
    return f"{DIAL}/{method}"


def joint_path(joint: str) -> str:
    return f"{SERIES_JOINTS}/{joint}"


# ------------------------------------------------------------------------------ colours
# Chosen to read on rerun's dark theme and on a light one. The truth is the only green.
TRUTH_COLOR: Color = (60, 220, 100)
METHOD_COLORS: dict[str, Color] = {
    "ukf": (255, 127, 14),
    "ukf-position": (255, 190, 110),
    "tip-position": (70, 150, 255),
    "tip-position-lsq": (150, 200, 255),
    "body-positions": (180, 120, 240),
    "body-positions-lsq": (215, 180, 250),
    "tip-velocity": (235, 70, 80),
    "tip-velocity-lsq": (250, 150, 150),
}
OTHER_COLORS: tuple[Color, ...] = (  # for names not above, picked by a hash of the name
    (230, 200, 40),
    (240, 110, 200),
    (40, 200, 210),
    (170, 170, 170),
    (200, 140, 80),
)
RECORDED_PREFIX = "recorded-"
SEGMENTED_COLOR: Color = (255, 230, 0)  # rings around the segmented markers
REFERENCE_COLOR: Color = (150, 150, 150)  # chi-square band, the dial's frame
FAN_ALPHA = 90  # the +/-2 sigma fan
PLANE_ALPHA = 60  # the bending plane
LATENCY_COLOR: Color = (70, 150, 255)
DROPPED_COLOR: Color = (235, 70, 80)
PREDICT_ONLY_COLOR: Color = (150, 150, 150)
JOINT_COLORS: dict[str, Color] = {
    "q_r_deg": (255, 160, 60),
    "q_p_mm": (90, 170, 255),
    "q_d_mm": (200, 130, 240),
}


def method_color(method: str) -> Color:
    """The one colour of a method, the same in every view and every recording.

    A recorded estimate (``recorded-<method>``, ``cathtrack view``) is its method's colour
    darkened, so that it stays apart from the same method run again.
    """
    if method.startswith(RECORDED_PREFIX):
        base = method_color(method[len(RECORDED_PREFIX) :])
        return tuple(int(0.6 * c) for c in base)  # type: ignore[return-value]
    if method in METHOD_COLORS:
        return METHOD_COLORS[method]
    return OTHER_COLORS[zlib.crc32(method.encode()) % len(OTHER_COLORS)]


# ------------------------------------------------------------------------------ blueprint
def scene_eye(scene, distance_lengths: float = 1.25) -> rrb.EyeControls3D:
    """A 3-D eye framed on the catheter: it looks at the middle of the catheter's reach from
    between the front and side directions, a little above, ``distance_lengths`` catheter
    lengths away, with the base axis up.

    Parameters
    ----------
    scene : anything with catheter, R_w_b, o_b_w_mm
    """
    pose = Pose(scene.R_w_b, scene.o_b_w_mm)
    length_mm = float(scene.catheter.length_mm)
    target_b = np.array([0.0, 0.0, 0.4 * length_mm])
    direction_b = np.array([1.0, -1.0, 0.6])
    direction_b /= np.linalg.norm(direction_b)
    position_b = target_b + distance_lengths * length_mm * direction_b
    target_w, position_w = pose.world_from_base(np.vstack([target_b, position_b]))
    return rrb.EyeControls3D(
        position=position_w,
        look_target=target_w,
        eye_up=np.asarray(pose.R_w_b, dtype=float)[:, 2],
    )


def base_grid(scene, spacing_mm: float = 5.0) -> rrb.LineGrid3D:
    """A grid in the base plane (through the base origin, across the base axis), mm."""
    normal_w = np.asarray(scene.R_w_b, dtype=float)[:, 2]
    distance = float(normal_w @ np.asarray(scene.o_b_w_mm, dtype=float))
    return rrb.LineGrid3D(
        visible=True, spacing=spacing_mm, plane=rr.encodings.Plane3D(normal_w, distance)
    )


def view_bounds(scene, view, margin: float = 0.08) -> rrb.VisualBounds2D | None:
    """The part of a view where the catheter can be: the projection of a box about the base
    axis, 1.5 catheter lengths wide and one tall, with a margin (None if it cannot be
    projected)."""
    length_mm = float(scene.catheter.length_mm)
    corners = np.array(
        [[x, y, z] for x in (-0.75, 0.75) for y in (-0.75, 0.75) for z in (0.0, 1.0)]
    )
    points_w = Pose(scene.R_w_b, scene.o_b_w_mm).world_from_base(length_mm * corners)
    try:
        uv = np.asarray(view.project(points_w), dtype=float)
    except ValueError:  # behind a camera
        return None
    low, high = uv.min(axis=0), uv.max(axis=0)
    pad = margin * (high - low)
    low, high = low - pad, high + pad
    size = getattr(view, "image_size", None)
    if size is not None:  # stay on the image
        low = np.maximum(low, 0.0)
        high = np.minimum(high, np.asarray(size, dtype=float))
    if not np.all(high > low):
        return None
    return rrb.VisualBounds2D(x_range=[low[0], high[0]], y_range=[low[1], high[1]])


def _scene_view_name(primary: str | None, pinhole: bool) -> str:
    shown = f"{primary} estimate" if primary else "estimate"
    return f"3-D: {shown} and bending plane, +/-2 sigma fan, truth (green dots)" + (
        "" if pinhole else ", orthographic planes"
    )


def default_blueprint(
    methods: Sequence[str] = (),
    pinhole: bool = True,
    live: bool = False,
    *,
    scene=None,
    primary: str | None = None,
    joints: bool = False,
) -> rrb.Blueprint:
    """The 3-D scene above the views and the dial on the left; delta_L, error and NIS over
    time on the right.

    Parameters
    ----------
    methods : sequence of str
        The methods logged; the first is the one drawn in 3-D unless ``primary`` says.
    pinhole : bool
        Cameras (the views under ``world/cameras``) or orthographic planes (``views``).
        A ``scene`` decides instead.
    live : bool
        Add the loop's latency and its dropped and predict-only frames.
    scene : anything with catheter, rig, R_w_b, o_b_w_mm, optional
        Frames the 3-D view on the catheter (:func:`scene_eye`) and names the views after
        ``scene.rig.names``; without it the 3-D view frames everything.
    joints : bool
        Add the joint values (``cathtrack view``), in a tab next to the NIS.
    """
    named_views = [(name, None) for name in VIEWS]
    eye = grid = None
    if scene is not None:
        pinhole = scene.rig.kind == "pinhole"
        named_views = [
            (name, view_bounds(scene, view))
            for name, view in zip(scene.rig.names, scene.rig.views, strict=True)
        ]
        eye, grid = scene_eye(scene), base_grid(scene)
    primary = primary or (methods[0] if methods else None)
    views = [
        rrb.Spatial2DView(
            origin=view_path(name, pinhole),
            name=f"{name}: o segmented, * {primary or 'estimate'}",
            visual_bounds=bounds,
        )
        for name, bounds in named_views
    ]
    dial = rrb.Spatial2DView(
        origin=DIAL,
        name="bending plane delta_1 (deg)",
        visual_bounds=rrb.VisualBounds2D(x_range=[-1.45, 1.45], y_range=[-1.35, 1.35]),
    )
    scene_view = rrb.Spatial3DView(
        origin=WORLD,
        # The cameras are 400 mm away from a 29 mm catheter: left out of the 3-D view (their
        # images are in the 2-D views).
        contents=["+ $origin/**", f"- {CAMERAS}/**"],
        name=_scene_view_name(primary, pinhole),
        eye_controls=eye,
        line_grid=grid,
    )
    nis = rrb.TimeSeriesView(
        origin=SERIES_NIS,
        name="NIS / dof, chi-square 95% band (axis clipped at 5)",
        axis_y=rrb.ScalarAxis(range=(0.0, 5.0)),
        plot_legend=rrb.PlotLegend(corner="RightTop"),
    )
    series = [
        rrb.TimeSeriesView(
            origin=SERIES_DELTA_L,
            name="delta_L unwrapped, +/-2 sigma (deg)",
            plot_legend=rrb.PlotLegend(corner="LeftTop"),
        ),
        rrb.TimeSeriesView(
            origin=SERIES_ERROR,
            name="bending-plane error and +/-2 sigma (deg)",
            plot_legend=rrb.PlotLegend(corner="LeftTop"),
        ),
        rrb.Tabs(nis, rrb.TimeSeriesView(origin=SERIES_JOINTS, name="joints (deg, mm)"))
        if joints
        else nis,
    ]
    if live:
        series.append(
            rrb.Horizontal(
                rrb.TimeSeriesView(origin=SERIES_LATENCY, name="latency image -> estimate (ms)"),
                rrb.TimeSeriesView(origin=SERIES_FRAMES, name="dropped / predict-only frames"),
            )
        )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                scene_view,
                rrb.Horizontal(*views, dial),
                row_shares=[3, 2],
            ),
            rrb.Vertical(*series),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


# ------------------------------------------------------------------------------ geometry
def plane_fan_w(
    catheter,
    q: Array,
    delta_L_rad: float,
    std_rad: float,
    R_w_b: Array,
    o_b_w_mm: Array,
    segments: int = 24,
    min_radius_fraction: float = 0.25,
) -> tuple[Array, Array]:
    """The +/-2 sigma fan of the bending plane: a triangle fan in {W}, mm.

    The apex is the base origin; the rim is an arc about the base axis at the tip's height,
    from 2 sigma before to 2 sigma after the tip's direction (the whole turn when 2 sigma
    exceeds pi or is not finite). Every half-plane through the base axis and a rim point is a
    bending plane within +/-2 sigma of the estimate. The rim radius is the tip's distance
    from the base axis, but at least ``min_radius_fraction`` of the catheter's length so that
    the fan stays visible when the catheter is nearly straight.

    Parameters
    ----------
    catheter : Catheter
    q : array, shape (3,)
        Joint values (q_r [rad], q_p [mm], q_d [mm]).
    delta_L_rad, std_rad : float
        Estimate and its standard deviation, rad.
    R_w_b, o_b_w_mm : arrays (3, 3), (3,)
        Registered base pose in {W}.
    segments : int
        Triangles of the fan.

    Returns
    -------
    vertices_w : array, shape (segments + 2, 3)
        The apex, then the rim from -2 sigma to +2 sigma, mm.
    triangles : array, shape (segments, 3)
        Vertex indices.
    """
    q = np.asarray(q, dtype=float)
    tip_b = np.asarray(catheter.tip(q, float(delta_L_rad)), dtype=float)
    lateral_mm = float(np.hypot(tip_b[0], tip_b[1]))
    # The tip's direction about the base axis; delta_1 = q_r + delta_L when it is on the axis.
    centre = (
        float(np.arctan2(tip_b[1], tip_b[0])) if lateral_mm > 1e-9 else float(q[0] + delta_L_rad)
    )
    spread = 2.0 * float(std_rad)
    spread = min(spread, np.pi) if np.isfinite(spread) else np.pi
    radius = max(lateral_mm, min_radius_fraction * catheter.length_mm)
    phi = centre + np.linspace(-spread, spread, int(segments) + 1)
    rim_b = np.column_stack(
        [radius * np.cos(phi), radius * np.sin(phi), np.full(phi.size, tip_b[2])]
    )
    vertices_b = np.vstack([np.zeros(3), rim_b])
    k = np.arange(1, int(segments) + 1)
    triangles = np.column_stack([np.zeros_like(k), k, k + 1]).astype(np.uint32)
    return Pose(R_w_b, o_b_w_mm).world_from_base(vertices_b), triangles


def bending_plane_w(backbone_b: Array, pose: Pose) -> tuple[Array, Array]:
    """The bending plane as a surface in {W}: the strip between the catheter's backbone and
    its projection on the base axis (each of its segments lies in the plane through the axis
    and that backbone point: one plane for a planar catheter, two when delta_2 != 0).

    Parameters
    ----------
    backbone_b : array, shape (n, 3)
        Backbone points in {B}, mm, base to tip.
    pose : models.pose.Pose
        Registered base pose.

    Returns
    -------
    vertices_w : array, shape (2 n, 3)
        Backbone point k at ``2 k``, its foot on the axis at ``2 k + 1``, mm.
    triangles : array, shape (2 (n - 1), 3)
    """
    backbone_b = np.asarray(backbone_b, dtype=float)
    n = backbone_b.shape[0]
    feet_b = np.zeros_like(backbone_b)
    feet_b[:, 2] = backbone_b[:, 2]
    vertices_b = np.empty((2 * n, 3))
    vertices_b[0::2], vertices_b[1::2] = backbone_b, feet_b
    k = 2 * np.arange(n - 1)
    triangles = np.concatenate(
        [np.column_stack([k, k + 1, k + 2]), np.column_stack([k + 1, k + 3, k + 2])]
    ).astype(np.uint32)
    return pose.world_from_base(vertices_b), triangles


def dial_points(angle_rad, radius) -> Array:
    """Points of the dial at angles delta_1 (rad) and radii, shape (..., 2).

    The dial looks down the base axis: x_b to the right, y_b up (the 2-D view's y axis points
    down, hence the minus sign), angles counter-clockwise.
    """
    angle = np.asarray(angle_rad, dtype=float)
    radius = np.asarray(radius, dtype=float)
    return np.stack([radius * np.cos(angle), -radius * np.sin(angle)], axis=-1)


def dial_needle(delta_1_rad: float, std_rad: float, radius: float) -> list[Array]:
    """A needle from the centre to ``radius`` at delta_1, and the +/-2 sigma arc at its end
    (no arc when 2 sigma is not finite or covers the whole turn)."""
    strips = [dial_points([delta_1_rad, delta_1_rad], [0.0, radius])]
    spread = 2.0 * float(std_rad)
    if np.isfinite(spread) and spread < np.pi:
        arc = delta_1_rad + np.linspace(-spread, spread, 17)
        strips.append(dial_points(arc, np.full(arc.size, radius)))
    return strips


def rings_2d(uv: Array, radius: float, segments: int = 20) -> Array:
    """Circles of ``radius`` about points, shape (n, segments + 1, 2) (closed polylines)."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    phi = np.linspace(0.0, 2.0 * np.pi, int(segments) + 1)
    circle = radius * np.column_stack([np.cos(phi), np.sin(phi)])
    return uv[:, None, :] + circle[None, :, :]
