"""Every rerun call of the project: entity paths, the default blueprint, the logging sinks and
the rerun outputs (file, viewer, server) of the command line.

The live loop and the offline replay share :class:`RerunSink`, which logs to an explicit
:class:`rerun.RecordingStream` (never the global one):

- ``world/...`` -- the 3-D scene in {W}, mm: the catheter model at the estimated bending plane
  and, where known, at the true one; the reconstructed markers; the tip's +/-2 sigma arc of
  uncertainty about the base axis and the +/-2 sigma fan of the bending plane; the cameras
  (pinhole views) with their images;
- ``world/cameras/<view>/...`` -- each camera's image, the segmented markers and the markers
  reprojected from the estimate (pinhole rigs); ``views/<view>/...`` the same points in mm
  for the paper's orthographic planes, which have no camera;
- ``series/...`` -- time series in degrees: delta_L of every method with the truth and the
  +/-2 sigma band, the bending-plane error, and the NIS; in live runs also the latency from
  the image time stamp to the estimate (ms) and the dropped and predict-only frames.

Time is the ``time`` timeline (s since the start of the session) and the ``frame`` sequence.

:class:`LiveViewerSink` is the live loop's rerun sink (:mod:`tracker.live.loop`);
:func:`add_rerun_args` and :func:`open_rerun_output` turn the usual rerun flags into the
outputs of a command: an ``.rrd`` file, a viewer (connected to or spawned), a gRPC server for
web viewers, or several at once.
"""

from __future__ import annotations

import dataclasses
import socket
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from models.imaging import PinholeView
from models.rotations import wrap_angle
from tracker.types import Estimate, Frame, Observation

Array = np.ndarray

VIEWS = ("front", "side")
TIMELINE = "time"
FRAME_SEQUENCE = "frame"

# Entity paths, in one place.
WORLD = "world"
CATHETER_ESTIMATE = "world/catheter/estimate"
CATHETER_TRUTH = "world/catheter/truth"
TIP_UNCERTAINTY = "world/catheter/uncertainty"
PLANE_FAN = "world/catheter/plane_fan"
MARKERS_3D = "world/markers"
SERIES_DELTA_L = "series/delta_L"
SERIES_ERROR = "series/error"
SERIES_NIS = "series/nis"
SERIES_LATENCY = "series/latency_ms"
SERIES_FRAMES = "series/frames"
LATENCY_ESTIMATE = f"{SERIES_LATENCY}/estimate"
FRAMES_DROPPED = f"{SERIES_FRAMES}/dropped"
FRAMES_PREDICT_ONLY = f"{SERIES_FRAMES}/predict_only"

DEFAULT_VIEWER_PORT = 9876
DEFAULT_VIEWER_URL = f"rerun+http://127.0.0.1:{DEFAULT_VIEWER_PORT}/proxy"
LOOPBACK = "127.0.0.1"


def camera_path(view: str) -> str:
    return f"world/cameras/{view}"


def image_path(view: str) -> str:
    return f"world/cameras/{view}/image"


def view_path(view: str, pinhole: bool) -> str:
    """Where a view's 2-D points go: under its camera, or on its own for a plane (mm)."""
    return camera_path(view) if pinhole else f"views/{view}"


def delta_L_path(method: str) -> str:
    return f"{SERIES_DELTA_L}/{method}"


def band_path(method: str, side: str) -> str:
    return f"{SERIES_DELTA_L}/{method}_{side}2sigma"


def error_path(method: str) -> str:
    return f"{SERIES_ERROR}/{method}"


def nis_path(method: str) -> str:
    return f"{SERIES_NIS}/{method}"


_PALETTE = [
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
]
TRUTH_COLOR = (20, 20, 20)
ESTIMATE_COLOR = (255, 127, 14)
FAN_COLOR = (255, 127, 14, 70)  # translucent
SEGMENTED_COLOR = (0, 200, 255)
REPROJECTED_COLOR = (255, 60, 60)
LATENCY_COLOR = (31, 119, 180)
DROPPED_COLOR = (214, 39, 40)
PREDICT_ONLY_COLOR = (127, 127, 127)


def default_blueprint(
    methods: Sequence[str] = (), pinhole: bool = True, live: bool = False
) -> rrb.Blueprint:
    """3-D scene and both views on the left; delta_L, error and NIS over time on the right.

    ``live`` adds the loop's latency and its dropped and predict-only frames below them.
    """
    views = [rrb.Spatial2DView(origin=view_path(v, pinhole), name=f"{v} view") for v in VIEWS]
    series = [
        rrb.TimeSeriesView(origin=SERIES_DELTA_L, name="delta_L +/-2 sigma (deg)"),
        rrb.TimeSeriesView(origin=SERIES_ERROR, name="bending-plane error (deg)"),
        rrb.TimeSeriesView(origin=SERIES_NIS, name="NIS"),
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
                rrb.Spatial3DView(origin=WORLD, name="3-D scene"),
                rrb.Horizontal(*views),
                row_shares=[3, 2],
            ),
            rrb.Vertical(*series),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


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
        float(np.arctan2(tip_b[1], tip_b[0]))
        if lateral_mm > 1e-9
        else float(q[0] + delta_L_rad)
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
    R_w_b = np.asarray(R_w_b, dtype=float)
    return vertices_b @ R_w_b.T + np.asarray(o_b_w_mm, dtype=float), triangles


class RerunSink:
    """Logs frames and estimates to one rerun recording stream.

    Parameters
    ----------
    stream : rerun.RecordingStream
        Explicit stream (a file sink from ``stream.save(path)``, a viewer, a server...).
    primary : str, optional
        The method whose estimate draws the catheter in 3-D and the reprojected markers
        (default: the first method logged).
    backbone_points : int
        Points along the drawn catheter.
    jpeg_quality : int, optional
        Log the images JPEG-compressed at this quality (1-100): about 25 kB instead of
        300 kB per 640x480 image, for long live sessions. None logs them raw.
    time_origin_s : float or None
        Subtracted from every time stamp on the ``time`` timeline; None takes the first time
        logged (live sources stamp with the monotonic clock).
    """

    def __init__(
        self,
        stream: rr.RecordingStream,
        primary: str | None = None,
        backbone_points: int = 40,
        jpeg_quality: int | None = None,
        time_origin_s: float | None = 0.0,
    ) -> None:
        if jpeg_quality is not None and not 1 <= int(jpeg_quality) <= 100:
            raise ValueError(f"jpeg_quality must lie in 1..100, got {jpeg_quality}")
        self.stream = stream
        self.primary = primary
        self.jpeg_quality = None if jpeg_quality is None else int(jpeg_quality)
        self.time_origin_s = time_origin_s
        self._s = None
        self._backbone_points = int(backbone_points)
        self._scene_id: int | None = None
        self._methods: list[str] = []
        self._frame_index = 0
        self._truth_logged = False
        self._truth_time_s: float | None = None
        self._live_styled = False
        self._closed = False

    # ---------------------------------------------------------------- static
    def _method_color(self, method: str) -> tuple[int, int, int]:
        if method not in self._methods:
            self._methods.append(method)
        return _PALETTE[self._methods.index(method) % len(_PALETTE)]

    def _log_scene(self, scene) -> None:
        """Cameras (pose and intrinsics) once per scene."""
        if self._scene_id == id(scene):
            return
        self._scene_id = id(scene)
        self._s = np.linspace(0.0, scene.catheter.length_mm, self._backbone_points)
        self.stream.log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for name, view in zip(VIEWS, (scene.rig.front, scene.rig.side), strict=True):
            if isinstance(view, PinholeView):
                self.stream.log(
                    camera_path(name),
                    rr.Transform3D(translation=view.center_w, mat3x3=np.asarray(view.R_cam_w).T),
                    rr.Pinhole(
                        image_from_camera=np.asarray(view.K),
                        resolution=list(view.image_size),
                        image_plane_distance=50.0,
                    ),
                    static=True,
                )
        self.stream.log(
            f"{SERIES_DELTA_L}/truth",
            rr.SeriesLines(colors=[TRUTH_COLOR], names=["truth"], widths=[2.0]),
            static=True,
        )

    def _style_method(self, method: str) -> None:
        if method in self._methods:
            return
        color = self._method_color(method)
        self.stream.log(
            delta_L_path(method), rr.SeriesLines(colors=[color], names=[method]), static=True
        )
        for side in ("plus", "minus"):
            self.stream.log(
                band_path(method, side),
                rr.SeriesLines(colors=[color], names=[f"{method} {side} 2 sigma"], widths=[0.5]),
                static=True,
            )
        self.stream.log(
            error_path(method), rr.SeriesLines(colors=[color], names=[method]), static=True
        )
        self.stream.log(
            nis_path(method), rr.SeriesPoints(colors=[color], names=[method]), static=True
        )

    def _style_live(self) -> None:
        if self._live_styled:
            return
        self._live_styled = True
        for path, color, name in (
            (LATENCY_ESTIMATE, LATENCY_COLOR, "image -> estimate"),
            (FRAMES_DROPPED, DROPPED_COLOR, "dropped (cumulative)"),
            (FRAMES_PREDICT_ONLY, PREDICT_ONLY_COLOR, "predict only, no joints (cumulative)"),
        ):
            self.stream.log(path, rr.SeriesLines(colors=[color], names=[name]), static=True)

    def _session_time(self, time_s) -> float | Array:
        if self.time_origin_s is None:
            self.time_origin_s = float(np.min(time_s)) if np.size(time_s) else 0.0
        return time_s - self.time_origin_s

    def set_time(self, time_s: float) -> None:
        self.stream.set_time(TIMELINE, duration=float(self._session_time(float(time_s))))

    # ---------------------------------------------------------------- per frame
    def _image(self, image: Array):
        logged = rr.Image(image)
        if self.jpeg_quality is not None:
            logged = logged.compress(jpeg_quality=self.jpeg_quality)
        return logged

    def _clear_estimate(self, pinhole: bool) -> None:
        """No valid estimate: nothing drawn from it (rather than the last one, stale)."""
        for path in (CATHETER_ESTIMATE, TIP_UNCERTAINTY, PLANE_FAN):
            self.stream.log(path, rr.Clear(recursive=False))
        for name in VIEWS:
            self.stream.log(f"{view_path(name, pinhole)}/reprojected", rr.Clear(recursive=False))

    def log_frame(
        self,
        frame: Frame,
        observation: Observation | None,
        estimates: Mapping[str, Estimate],
        scene,
        images: bool = True,
    ) -> None:
        """One frame: images and segmented markers, the 3-D scene at the primary estimate.

        Parameters
        ----------
        frame : Frame
        observation : Observation, optional
            Its reconstruction (markers relative to the base, {B}).
        estimates : mapping of method name to Estimate
            This frame's estimates; the primary method's draws the catheter.
        scene : replay.simulation.simulator.Scene or anything with catheter, rig, R_w_b, o_b_w_mm
        images : bool
            Log the images (False: markers only, a lighter recording).
        """
        self._log_scene(scene)
        self.stream.set_time(FRAME_SEQUENCE, sequence=self._frame_index)
        self._frame_index += 1
        self.set_time(frame.time_s)
        pinhole = scene.rig.kind == "pinhole"
        R_w_b, o_b_w = np.asarray(scene.R_w_b), np.asarray(scene.o_b_w_mm)
        for k, name in enumerate(VIEWS):
            path = view_path(name, pinhole)
            if images and frame.images is not None and pinhole:
                self.stream.log(image_path(name), self._image(frame.images[k]))
            uv = np.asarray(frame.uv_front if k == 0 else frame.uv_side, dtype=float)
            found = np.all(np.isfinite(uv), axis=-1)
            self.stream.log(
                f"{path}/segmented",
                rr.Points2D(uv[found], colors=[SEGMENTED_COLOR], radii=[3.0 if pinhole else 0.3]),
            )
        if observation is not None and observation.markers_b_mm is not None:
            points_b = np.vstack([observation.tip_b_mm, observation.markers_b_mm])
            points_b = points_b[np.all(np.isfinite(points_b), axis=-1)]
            self.stream.log(
                MARKERS_3D,
                rr.Points3D(points_b @ R_w_b.T + o_b_w, colors=[SEGMENTED_COLOR], radii=[0.4]),
            )
        q = np.asarray(frame.q, dtype=float)
        catheter = scene.catheter
        if frame.delta_L_true_rad is not None and np.isfinite(frame.delta_L_true_rad):
            truth_w = catheter.backbone(q, frame.delta_L_true_rad, self._s) @ R_w_b.T + o_b_w
            self.stream.log(
                CATHETER_TRUTH, rr.LineStrips3D([truth_w], colors=[TRUTH_COLOR], radii=[0.15])
            )
        primary = self.primary or next(iter(estimates), None)
        estimate = estimates.get(primary) if primary is not None else None
        if estimate is None or not estimate.valid:
            self._clear_estimate(pinhole)
            return
        backbone_w = catheter.backbone(q, estimate.delta_L_rad, self._s) @ R_w_b.T + o_b_w
        self.stream.log(
            CATHETER_ESTIMATE,
            rr.LineStrips3D([backbone_w], colors=[ESTIMATE_COLOR], radii=[0.3]),
        )
        # Where the tip would be for delta_L within +/-2 sigma: an arc about the base axis.
        spread = min(2.0 * estimate.std_rad, np.pi)
        arc = estimate.delta_L_rad + np.linspace(-spread, spread, 25)
        tip_b = catheter.tip(np.broadcast_to(q, (arc.size, 3)), arc)
        self.stream.log(
            TIP_UNCERTAINTY,
            rr.LineStrips3D([tip_b @ R_w_b.T + o_b_w], colors=[ESTIMATE_COLOR], radii=[0.1]),
        )
        vertices_w, triangles = plane_fan_w(
            catheter, q, estimate.delta_L_rad, estimate.std_rad, R_w_b, o_b_w
        )
        self.stream.log(
            PLANE_FAN,
            rr.Mesh3D(
                vertex_positions=vertices_w, triangle_indices=triangles, albedo_factor=FAN_COLOR
            ),
        )
        arclengths = np.array((catheter.length_mm, *catheter.marker_arclengths_mm))
        points_w = catheter.backbone(q, estimate.delta_L_rad, arclengths) @ R_w_b.T + o_b_w
        for name, view in zip(VIEWS, (scene.rig.front, scene.rig.side), strict=True):
            try:
                uv = view.project(points_w)
            except ValueError:  # a point behind a camera: nothing to draw
                continue
            self.stream.log(
                f"{view_path(name, pinhole)}/reprojected",
                rr.Points2D(uv, colors=[REPROJECTED_COLOR], radii=[2.0 if pinhole else 0.2]),
            )

    def log_estimate(self, name: str, estimate: Estimate, truth_rad: float | None = None) -> None:
        """One method's estimate as time series (degrees): delta_L, +/-2 sigma, error, NIS."""
        self._style_method(name)
        self.set_time(estimate.time_s)
        if not estimate.valid:
            return
        value = np.degrees(estimate.delta_L_rad)
        self.stream.log(delta_L_path(name), rr.Scalars(value))
        if np.isfinite(estimate.std_rad) and estimate.std_rad < np.pi:
            two_sigma = 2 * np.degrees(estimate.std_rad)
            self.stream.log(band_path(name, "plus"), rr.Scalars(value + two_sigma))
            self.stream.log(band_path(name, "minus"), rr.Scalars(value - two_sigma))
        if truth_rad is not None and np.isfinite(truth_rad):
            if self._truth_time_s != estimate.time_s:  # once per frame, whatever the methods
                self._truth_time_s = estimate.time_s
                self.stream.log(f"{SERIES_DELTA_L}/truth", rr.Scalars(np.degrees(truth_rad)))
            error = np.degrees(wrap_angle(estimate.delta_L_rad - truth_rad))
            self.stream.log(error_path(name), rr.Scalars(error))
        if estimate.nis is not None and np.isfinite(estimate.nis):
            self.stream.log(nis_path(name), rr.Scalars(estimate.nis))

    def log_live(
        self,
        time_s: float,
        latency_s: float,
        frames_dropped: int | None = None,
        frames_predict_only: int | None = None,
    ) -> None:
        """The live loop's health at one frame: latency (ms) and cumulative frame counts.

        Parameters
        ----------
        time_s : float
            The frame's image time stamp, s.
        latency_s : float
            Image time stamp (or arrival) -> estimate ready, s.
        frames_dropped, frames_predict_only : int, optional
            Frames dropped so far (out of order, duplicate, unusable) and frames tracked
            without joint values so far (the estimator only predicted).
        """
        self._style_live()
        self.set_time(time_s)
        self.stream.log(LATENCY_ESTIMATE, rr.Scalars(1e3 * float(latency_s)))
        if frames_dropped is not None:
            self.stream.log(FRAMES_DROPPED, rr.Scalars(float(frames_dropped)))
        if frames_predict_only is not None:
            self.stream.log(FRAMES_PREDICT_ONLY, rr.Scalars(float(frames_predict_only)))

    def log_series(
        self,
        name: str,
        estimates: Sequence[Estimate],
        truth_rad: Array | None = None,
    ) -> None:
        """A whole replay of one method at once (columns; the same series as log_estimate)."""
        self._style_method(name)
        t = np.array([e.time_s for e in estimates], dtype=float)
        value = np.degrees(np.array([e.delta_L_rad for e in estimates], dtype=float))
        std = np.degrees(np.array([e.std_rad for e in estimates], dtype=float))
        valid = np.isfinite(value) & np.isfinite(std)
        self._columns(delta_L_path(name), t[valid], value[valid])
        banded = valid & (std < 180.0)
        self._columns(band_path(name, "plus"), t[banded], value[banded] + 2 * std[banded])
        self._columns(band_path(name, "minus"), t[banded], value[banded] - 2 * std[banded])
        if truth_rad is not None:
            truth = np.asarray(truth_rad, dtype=float)
            known = valid & np.isfinite(truth)
            error = np.degrees(wrap_angle(np.radians(value[known]) - truth[known]))
            self._columns(error_path(name), t[known], error)
            if not self._truth_logged:
                self._truth_logged = True
                have = np.isfinite(truth)
                self._columns(f"{SERIES_DELTA_L}/truth", t[have], np.degrees(truth[have]))
        nis = np.array([np.nan if e.nis is None else e.nis for e in estimates], dtype=float)
        has_nis = np.isfinite(nis)
        if has_nis.any():
            self._columns(nis_path(name), t[has_nis], nis[has_nis])

    def _columns(self, path: str, t: Array, values: Array) -> None:
        if t.size == 0:
            return
        self.stream.send_columns(
            path,
            indexes=[rr.TimeColumn(TIMELINE, duration=self._session_time(t))],
            columns=rr.Scalars.columns(scalars=values),
        )

    # ---------------------------------------------------------------- end
    def close(self, timeout_s: float = 5.0) -> bool:
        """Flush everything logged and close the stream's outputs (an ``.rrd`` gets its
        footer and is complete; viewer connections and servers are closed).

        Returns False when not everything reached the outputs within ``timeout_s`` (a viewer
        that went away). Closing twice does nothing.
        """
        if self._closed:
            return True
        self._closed = True
        delivered = True
        try:
            self.stream.flush(timeout_sec=float(timeout_s))
        except RuntimeError:  # "Flush timed out - not all log messages were sent"
            delivered = False
        self.stream.disconnect()
        return delivered


# ------------------------------------------------------------------------------ live loop
def _report_stderr(message: str) -> None:
    print(f"cathtrack: {message}", file=sys.stderr, flush=True)


def parse_viewer_url(url: str) -> tuple[str, int]:
    """Host and port of a rerun gRPC URL (``rerun+http://127.0.0.1:9876/proxy``)."""
    parts = urlsplit(url)
    if parts.scheme not in ("rerun", "rerun+http", "rerun+https") or not parts.hostname:
        raise ValueError(
            f"not a rerun viewer URL: {url!r} (expected e.g. {DEFAULT_VIEWER_URL})"
        )
    port = parts.port
    if port is None:
        port = 443 if parts.scheme in ("rerun", "rerun+https") else 80
    return parts.hostname, port


def viewer_reachable(url: str, timeout_s: float = 0.5) -> tuple[bool, str]:
    """Whether something accepts TCP connections at a viewer URL, and why not.

    rerun's own connection does not say: it blocks for seconds and then drops the data
    silently when nothing listens.
    """
    host, port = parse_viewer_url(url)
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return True, ""
    except OSError as exc:
        return False, exc.strerror or str(exc) or type(exc).__name__


class ViewerWatch:
    """Checks in a background thread that a gRPC viewer still accepts connections.

    ``lost`` turns True when a check fails and False again when one succeeds.

    Parameters
    ----------
    url : str
    interval_s, timeout_s : float
    """

    def __init__(self, url: str, interval_s: float = 1.0, timeout_s: float = 0.5) -> None:
        self.url = url
        self.interval_s = float(interval_s)
        self.timeout_s = float(timeout_s)
        self.lost = False
        self.reason = ""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="viewer-watch", daemon=True)

    def start(self) -> ViewerWatch:
        self._thread.start()
        return self

    def check(self) -> bool:
        """One check now; True when the viewer is reachable."""
        ok, reason = viewer_reachable(self.url, self.timeout_s)
        self.lost, self.reason = not ok, reason
        return ok

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.check()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(self.interval_s + self.timeout_s + 1.0)


class LiveViewerSink:
    """The rerun output as a live-loop sink (:mod:`tracker.live.loop`).

    Per frame: the 3-D scene at the estimate with the +/-2 sigma fan, the segmented and
    reprojected markers, the images (every ``image_every``-th frame), the series of delta_L,
    error (where the truth is known) and NIS, and the loop's latency and its dropped and
    predict-only frames.

    Parameters
    ----------
    viewer : RerunSink
    scene : replay.simulation.simulator.Scene or anything with catheter, rig, R_w_b, o_b_w_mm
    method : str
        Name of the loop's estimator, for the series.
    images : bool
        Log the images at all.
    image_every : int
        Log the images of every n-th frame (the markers of every frame).
    truth : callable, optional
        Image time (s) -> true delta_L (rad) or None, for frames that do not carry their
        truth (a simulation feeding images to the loop).
    watch : ViewerWatch, optional
        A started watch of the viewer; a lost viewer is reported once (and its return), and
        the loop goes on.
    report : callable
        Receives one line per problem.
    close_stream : bool
        Close the stream when the loop closes the sink (False: the caller closes it, e.g. to
        keep serving web viewers after the run).

    Attributes
    ----------
    summary : tracker.live.loop.LiveSummary or None
        The loop's summary, for the dropped-frame series (set it once the loop is built).
    """

    name = "rerun"

    def __init__(
        self,
        viewer: RerunSink,
        scene,
        method: str,
        *,
        images: bool = True,
        image_every: int = 1,
        truth: Callable[[float], float | None] | None = None,
        watch: ViewerWatch | None = None,
        report: Callable[[str], None] = _report_stderr,
        close_stream: bool = True,
    ) -> None:
        if int(image_every) < 1:
            raise ValueError(f"image_every must be >= 1, got {image_every}")
        self.viewer, self.scene, self.method = viewer, scene, method
        self.images, self.image_every = images, int(image_every)
        self.truth, self.watch, self.report = truth, watch, report
        self.close_stream = close_stream
        self.summary = None
        self.frames = 0
        self._predict_only = 0
        self._lost_reported = False

    def handle(self, frame, observation, estimate, latency_s, status=0) -> None:
        if self.truth is not None and frame.delta_L_true_rad is None:
            truth = self.truth(frame.time_s)
            if truth is not None:
                frame = dataclasses.replace(frame, delta_L_true_rad=float(truth))
        images = self.images and self.frames % self.image_every == 0
        self.frames += 1
        self.viewer.log_frame(frame, observation, {self.method: estimate}, self.scene, images)
        self.viewer.log_estimate(self.method, estimate, frame.delta_L_true_rad)
        # LiveStatus: STALE_JOINTS = 1, NO_JOINTS = 2 (the estimator only predicted).
        self._predict_only += bool(int(status) & 3)
        dropped = None if self.summary is None else self.summary.frames_dropped
        self.viewer.log_live(frame.time_s, latency_s, dropped, self._predict_only)
        self._check_watch()

    def _check_watch(self) -> None:
        watch = self.watch
        if watch is None:
            return
        if watch.lost and not self._lost_reported:
            self._lost_reported = True
            self.report(
                f"the rerun viewer at {watch.url} is gone ({watch.reason}); tracking goes on,"
                " the viewer misses what is logged until it is back"
            )
        elif not watch.lost and self._lost_reported:
            self._lost_reported = False
            self.report(f"the rerun viewer at {watch.url} is back")

    def close(self) -> None:
        if self.watch is not None:
            self.watch.stop()
        # A viewer known to be gone gets a short flush (rerun adds 5 s of its own).
        lost = self.watch is not None and self.watch.lost
        if self.close_stream and not self.viewer.close(timeout_s=1.0 if lost else 5.0):
            self.report("the rerun output did not take everything logged before closing")


# ---------------------------------------------------------------------- command line
def add_rerun_args(parser, save_default: str | None = None) -> None:
    """The usual rerun flags (``rr.script_add_args``) in an argument group, and ``--spawn``.

    ``--save PATH`` writes an ``.rrd``; ``--connect`` (to ``--url``, default
    127.0.0.1:9876) logs to a running viewer; ``--spawn`` starts one; ``--serve`` hosts a
    gRPC server for viewers to connect to (``rerun rerun+http://127.0.0.1:9876/proxy``), and a
    web viewer too when it is bound beyond loopback and not ``--headless``. They combine:
    ``--save`` next to a viewer writes the file too. ``--stdout`` is not supported (the
    commands print their results there).
    """
    group = parser.add_argument_group("rerun output")
    rr.script_add_args(group)
    group.add_argument(
        "--spawn", action="store_true", help="start a rerun viewer and log to it"
    )
    if save_default is not None:
        parser.set_defaults(save=save_default)


@dataclass
class RerunOutput:
    """Where a command's rerun stream goes (:func:`open_rerun_output`)."""

    stream: rr.RecordingStream
    targets: list[str]  # human-readable, e.g. "file out/demo.rrd"
    rrd_path: Path | None = None
    viewer_url: str | None = None  # a gRPC viewer logged to (connected or spawned)
    served_url: str | None = None  # the gRPC server web viewers connect to

    def watch(self) -> ViewerWatch | None:
        """A started :class:`ViewerWatch` of the viewer logged to, if any."""
        return None if self.viewer_url is None else ViewerWatch(self.viewer_url).start()


def open_rerun_output(
    args,
    application_id: str = "cathtrack",
    *,
    blueprint: rrb.Blueprint | None = None,
    recording_id: str | None = None,
    bind: str = LOOPBACK,
    report: Callable[[str], None] = _report_stderr,
) -> RerunOutput | None:
    """Open the rerun outputs the flags of :func:`add_rerun_args` ask for (None: none).

    Like ``rr.script_setup``, but on an explicit :class:`rerun.RecordingStream` rather than
    the global one, with several outputs at once (``rr.RecordingStream.set_sinks``), the
    gRPC server bound to ``bind`` (loopback by default, not every interface; rerun's web
    viewer, which listens on every interface, only when ``bind`` is not loopback), and a viewer
    that is not running reported once (``report``) instead of blocking the command for
    seconds and losing the data silently: the command goes on without it.

    Raises
    ------
    ValueError
        ``--stdout``, or a malformed ``--url``.
    OSError
        The ``.rrd`` file cannot be created.
    """
    if getattr(args, "stdout", False):
        raise ValueError("--stdout is not supported: use --save PATH, --connect or --serve")
    sinks: list = []
    targets: list[str] = []
    output = {}
    save = getattr(args, "save", None)
    if save:
        path = Path(save)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(path))
        except Exception as exc:  # rerun raises its own error types for unwritable files
            raise OSError(f"cannot write the rerun recording {path}: {exc}") from None
        targets.append(f"file {path}")
        output["rrd_path"] = path
    url = None
    if getattr(args, "spawn", False):
        try:
            rr.spawn(port=DEFAULT_VIEWER_PORT, connect=False)
            url = DEFAULT_VIEWER_URL
        except Exception as exc:  # no rerun executable, no display...
            report(f"cannot start a rerun viewer ({exc}); going on without it")
    if getattr(args, "connect", False) or getattr(args, "url", None):
        url = args.url or DEFAULT_VIEWER_URL
    if url is not None:
        reachable, reason = viewer_reachable(url)
        if reachable:
            sinks.append(rr.GrpcSink(url))
            targets.append(f"viewer {url}")
            output["viewer_url"] = url
        else:
            report(f"no rerun viewer at {url} ({reason}); going on without it")
    server = None
    if getattr(args, "serve", False):
        server = rr.GrpcServerSink(bind_ip=bind, port=DEFAULT_VIEWER_PORT)
        sinks.append(server)
        targets.append(f"server {server.uri}")
        output["served_url"] = server.uri
    if not sinks:
        return None
    stream = rr.RecordingStream(application_id, recording_id=recording_id)
    stream.set_sinks(*sinks, default_blueprint=blueprint)
    if server is not None and bind != LOOPBACK and not args.headless:
        # rerun's web-viewer HTTP server listens on every interface: only when asked to serve
        # beyond this machine. On loopback, `rerun <uri>` (or the hosted web viewer) connects.
        rr.serve_web_viewer(open_browser=True, connect_to=server.uri)
        targets.append("web viewer on port 9090")
    return RerunOutput(stream, targets, **output)


def file_stream(
    path,
    application_id: str = "cathtrack",
    recording_id: str | None = None,
    blueprint: rrb.Blueprint | None = None,
) -> rr.RecordingStream:
    """A recording stream that writes a ``.rrd`` file (call before logging anything)."""
    stream = rr.RecordingStream(application_id, recording_id=recording_id)
    stream.save(str(path), default_blueprint=blueprint)
    return stream
