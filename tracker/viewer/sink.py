"""The rerun sink: every ``log`` call of the project, on an explicit :class:`rerun.RecordingStream`.

:class:`RerunSink` logs frames and estimates (one at a time, or a whole replay as columns) to
the entity paths of :mod:`tracker.viewer.layout`; the offline replay uses it directly.
:class:`LiveViewerSink` is the live loop's rerun sink (:mod:`tracker.live.sinks`): it adds the
loop's latency and frame counts, thins out the images and reports a viewer that goes away.

What the series show (one rule for a frame at a time and for a whole replay,
:meth:`RerunSink._series_values`): delta_L unwrapped (each value the 2 pi multiple nearest the
unwrapped truth at that time, else nearest the method's previous value), its +/-2 sigma band,
the wrapped error and its +/-2 sigma about zero, and NIS per degree of freedom with the
chi-square 95% band of its degrees of freedom. A frame without an estimate is a gap (NaN),
not a line drawn across.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import rerun as rr
from scipy.stats import chi2

from models.imaging import PinholeView
from models.pose import Pose
from models.rotations import wrap_angle
from tracker.live.sinks import PREDICT_ONLY, LiveStatus
from tracker.types import Estimate, Frame, Observation
from tracker.viewer.layout import (
    BENDING_PLANE,
    CATHETER_ESTIMATE,
    CATHETER_TRUTH,
    DELTA_L_TRUTH,
    DIAL_FRAME,
    DIAL_TRUTH,
    DROPPED_COLOR,
    FAN_ALPHA,
    FRAME_SEQUENCE,
    FRAMES_DROPPED,
    FRAMES_PREDICT_ONLY,
    JOINT_COLORS,
    LATENCY_COLOR,
    LATENCY_ESTIMATE,
    MARKERS_3D,
    PLANE_ALPHA,
    PLANE_FAN,
    PREDICT_ONLY_COLOR,
    REFERENCE_COLOR,
    SEGMENTED_COLOR,
    SIDES,
    TIMELINE,
    TRUTH_COLOR,
    WORLD,
    band_path,
    bending_plane_w,
    camera_path,
    delta_L_path,
    dial_needle,
    dial_path,
    dial_points,
    error_band_path,
    error_path,
    image_path,
    joint_path,
    method_color,
    nis_band_path,
    nis_path,
    plane_fan_w,
    rings_2d,
    view_path,
)
from tracker.viewer.output import ViewerWatch

Array = np.ndarray
NIS_BAND = (0.025, 0.975)  # the chi-square 95% band
# Sizes of the marker glyphs: negative radii are UI points (the same on screen at any zoom).
RING_RADIUS = {True: 9.0, False: 1.2}  # segmented: rings of 9 px (cameras) or 1.2 mm (planes)
RING_LINE = -1.0
DOT_RADIUS = -3.0  # reprojected: filled dots
DIAL_ORDER = 50.0  # draw order of the dial's needles (rerun draws higher values on top)


def _report_stderr(message: str) -> None:
    print(f"cathtrack: {message}", file=sys.stderr, flush=True)


def rig_views(rig) -> tuple[tuple[str, object], ...]:
    """(name, view) of every view of a rig, in its order."""
    return tuple(zip(rig.names, rig.views, strict=True))


@functools.lru_cache(maxsize=64)
def nis_band_per_dof(dof: int) -> tuple[float, float]:
    """The chi-square 95% band of NIS / dof for ``dof`` degrees of freedom."""
    return tuple(float(chi2.ppf(p, dof) / dof) for p in NIS_BAND)  # type: ignore[return-value]


class _Unwrap:
    """Makes an angle continuous over time: each value is moved by the multiple of 2 pi that
    puts it nearest a reference (the truth at that time when known), else nearest the
    previous value."""

    def __init__(self) -> None:
        self.last_rad: float | None = None

    def __call__(self, angle_rad: float, reference_rad: float = math.nan) -> float:
        if not math.isfinite(angle_rad):
            return math.nan
        reference = reference_rad if math.isfinite(reference_rad) else self.last_rad
        value = angle_rad if reference is None else reference + wrap_angle(angle_rad - reference)
        self.last_rad = float(value)
        return self.last_rad


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
        self._s = self._truth_s = None
        self._backbone_points = int(backbone_points)
        self._scene_id: int | None = None
        self._pose: Pose | None = None  # the scene's registered base
        self._styled: set[str] = set()
        self._unwrap: dict[str, _Unwrap] = {}
        self._truth_unwrap = _Unwrap()
        self._truth_time_s: float | None = None
        self._truth_unwrapped_rad = math.nan
        self._truth_logged = False
        self._truth_lock = threading.Lock()
        self._frame_index = 0
        self._live_styled = False
        self._joints_styled = False
        self._closed = False

    # ---------------------------------------------------------------- static
    def _log_scene(self, scene) -> None:
        """Cameras (pose and intrinsics) and the dial's face, once per scene."""
        if self._scene_id == id(scene):
            return
        self._scene_id = id(scene)
        self._pose = Pose(scene.R_w_b, scene.o_b_w_mm)
        self._s = np.linspace(0.0, scene.catheter.length_mm, self._backbone_points)
        self._truth_s = np.linspace(0.0, scene.catheter.length_mm, 25)
        self.stream.log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for name, view in rig_views(scene.rig):
            if isinstance(view, PinholeView):
                self.stream.log(
                    camera_path(name),
                    rr.Transform3D(translation=view.center_w, mat3x3=np.asarray(view.R_cam_w).T),
                    rr.Pinhole(
                        image_from_camera=np.asarray(view.K),
                        resolution=list(view.image_size),
                        image_plane_distance=20.0,
                    ),
                    static=True,
                )
        self._style_truth()
        self._log_dial_face()

    def _style_truth(self) -> None:
        self.stream.log(
            DELTA_L_TRUTH,
            # Wide, and drawn first: the methods' lines on it stay visible.
            rr.SeriesLines(colors=[TRUTH_COLOR], names=["truth"], widths=[5.0]),
            static=True,
        )

    def _log_dial_face(self) -> None:
        """The dial: a circle with ticks every 90 deg, labelled."""
        ticks_deg = np.array([0.0, 90.0, 180.0, -90.0])
        ticks = np.radians(ticks_deg)
        circle = np.linspace(0.0, 2.0 * np.pi, 73)
        strips = [dial_points(circle, np.ones(circle.size))]
        strips += [dial_points([a, a], [0.92, 1.08]) for a in ticks]
        self.stream.log(
            f"{DIAL_FRAME}/circle",
            rr.LineStrips2D(strips, colors=[REFERENCE_COLOR], radii=[-0.75]),
            static=True,
        )
        self.stream.log(
            f"{DIAL_FRAME}/labels",
            rr.Points2D(
                dial_points(ticks, np.full(ticks.size, 1.25)),
                radii=[-0.5],
                colors=[REFERENCE_COLOR],
                labels=[f"{t:+.0f}" if t else "0 (x_b)" for t in ticks_deg],
                show_labels=True,
            ),
            static=True,
        )

    def _style_method(self, method: str) -> None:
        """A method's colour and legend name on every series it has: one legend entry per
        method and plot (the band carries the method's name too, so the legend merges it)."""
        if method in self._styled:
            return
        self._styled.add(method)
        color = method_color(method)
        lines = [(delta_L_path(method), 1.5), (error_path(method), 1.5)]
        lines += [(band_path(method, side), 1.0) for side in SIDES]
        lines += [(error_band_path(method, side), 1.0) for side in SIDES]
        for path, width in lines:
            self.stream.log(
                path, rr.SeriesLines(colors=[color], names=[method], widths=[width]), static=True
            )
        self.stream.log(
            nis_path(method),
            rr.SeriesPoints(colors=[color], names=[method], marker_sizes=[2.0]),
            static=True,
        )
        for side in ("low", "high"):
            self.stream.log(
                nis_band_path(method, side),
                rr.SeriesLines(colors=[REFERENCE_COLOR], names=["chi-square 95%"], widths=[1.0]),
                static=True,
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

    def _clear_estimate(self, names: Sequence[str], pinhole: bool) -> None:
        """No valid estimate: nothing drawn from it (rather than the last one, stale)."""
        for path in (CATHETER_ESTIMATE, PLANE_FAN, BENDING_PLANE):
            self.stream.log(path, rr.Clear(recursive=False))
        for name in names:
            for drawn in ("reprojected", "backbone"):
                self.stream.log(f"{view_path(name, pinhole)}/{drawn}", rr.Clear(recursive=False))

    def log_frame(
        self,
        frame: Frame,
        observation: Observation | None,
        estimates: Mapping[str, Estimate],
        scene,
        images: bool = True,
    ) -> None:
        """One frame: images and segmented markers, the 3-D scene at the primary estimate,
        the dial of every method given.

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
        views = rig_views(scene.rig)
        names = [name for name, _ in views]
        pose = self._pose
        for k, (name, uv) in enumerate(zip(names, frame.uv, strict=True)):
            if images and frame.images is not None and pinhole:
                self.stream.log(image_path(name), self._image(frame.images[k]))
            uv = np.asarray(uv, dtype=float)
            found = np.all(np.isfinite(uv), axis=-1)
            self.stream.log(
                f"{view_path(name, pinhole)}/segmented",
                rr.LineStrips2D(
                    rings_2d(uv[found], RING_RADIUS[pinhole]),
                    colors=[SEGMENTED_COLOR],
                    radii=[RING_LINE],
                ),
            )
        if observation is not None and observation.markers_b_mm is not None:
            points_b = np.vstack([observation.tip_b_mm, observation.markers_b_mm])
            points_b = points_b[np.all(np.isfinite(points_b), axis=-1)]
            self.stream.log(
                MARKERS_3D,
                rr.Points3D(pose.world_from_base(points_b), colors=[SEGMENTED_COLOR], radii=[0.5]),
            )
        q = np.asarray(frame.q, dtype=float)
        catheter = scene.catheter
        truth = frame.delta_L_true_rad
        if truth is not None and np.isfinite(truth):
            # Dots along the backbone: the estimate's line stays visible where they agree.
            truth_w = pose.world_from_base(catheter.backbone(q, truth, self._truth_s))
            self.stream.log(
                CATHETER_TRUTH, rr.Points3D(truth_w, colors=[TRUTH_COLOR], radii=[0.45])
            )
            self.stream.log(
                DIAL_TRUTH,
                rr.LineStrips2D(
                    dial_needle(q[0] + truth, math.inf, 1.15)[:1],
                    colors=[TRUTH_COLOR],
                    radii=[-3.0],
                    draw_order=DIAL_ORDER - 1,  # under the methods' needles
                ),
            )
        self._log_dials(estimates)
        primary = self.primary or next(iter(estimates), None)
        estimate = estimates.get(primary) if primary is not None else None
        if estimate is None or not estimate.valid:
            self._clear_estimate(names, pinhole)
            return
        color = method_color(primary)
        backbone_b = catheter.backbone(q, estimate.delta_L_rad, self._s)
        # Where the tip would be for delta_L within +/-2 sigma: an arc about the base axis.
        spread = min(2.0 * estimate.std_rad, np.pi)
        arc = estimate.delta_L_rad + np.linspace(-spread, spread, 25)
        tip_b = catheter.tip(np.broadcast_to(q, (arc.size, 3)), arc)
        fan_w, fan_triangles = plane_fan_w(
            catheter, q, estimate.delta_L_rad, estimate.std_rad, pose.R_w_b, pose.o_b_w_mm
        )
        # One entity, three lines: the catheter, the tip's arc, and the fan's outline (so that
        # a narrow fan, a certain estimate, still shows).
        self.stream.log(
            CATHETER_ESTIMATE,
            rr.LineStrips3D(
                [
                    pose.world_from_base(backbone_b),
                    pose.world_from_base(tip_b),
                    np.vstack([fan_w, fan_w[:1]]),
                ],
                colors=[color],
                radii=[0.3, 0.15, 0.08],
                labels=[primary, "", ""],
            ),
        )
        plane_w, plane_triangles = bending_plane_w(backbone_b, pose)
        for path, vertices_w, triangles, alpha in (
            (BENDING_PLANE, plane_w, plane_triangles, PLANE_ALPHA),
            (PLANE_FAN, fan_w, fan_triangles, FAN_ALPHA),
        ):
            self.stream.log(
                path,
                rr.Mesh3D(
                    vertex_positions=vertices_w,
                    triangle_indices=triangles,
                    albedo_factor=(*color, alpha),
                ),
            )
        arclengths = np.array((catheter.length_mm, *catheter.marker_arclengths_mm))
        points_w = pose.world_from_base(catheter.backbone(q, estimate.delta_L_rad, arclengths))
        for name, view in views:
            path = view_path(name, pinhole)
            try:
                uv = view.project(points_w)
            except ValueError:  # a point behind a camera: nothing to draw
                continue
            dots = rr.Points2D(uv, colors=[color], radii=[DOT_RADIUS])
            self.stream.log(f"{path}/reprojected", dots)
            if not pinhole:  # a plane has no image of the catheter: draw the estimated one
                backbone_uv = view.project(pose.world_from_base(backbone_b))
                self.stream.log(
                    f"{path}/backbone", rr.LineStrips2D([backbone_uv], colors=[color], radii=[-1.0])
                )

    def _log_dials(self, estimates: Mapping[str, Estimate]) -> None:
        """A needle at delta_1 = q_r + delta_L with its +/-2 sigma arc per method (nested
        radii, in the order given), cleared when the method has no estimate."""
        for k, (method, estimate) in enumerate(estimates.items()):
            if estimate is None or not estimate.valid:
                self.stream.log(dial_path(method), rr.Clear(recursive=False))
                continue
            strips = dial_needle(
                estimate.q_r_rad + estimate.delta_L_rad, estimate.std_rad, 1.0 - 0.12 * k
            )
            self.stream.log(
                dial_path(method),
                rr.LineStrips2D(
                    strips, colors=[method_color(method)], radii=[-1.5], draw_order=DIAL_ORDER + k
                ),
            )

    # ---------------------------------------------------------------- series
    def _series_values(
        self,
        method: str,
        estimates: Sequence[Estimate],
        truth_rad: Array,
        truth_unwrapped_rad: Array,
    ) -> dict[str, Array]:
        """Every series value of a method's estimates (one row each; NaN: nothing there).

        delta_L is unwrapped against the unwrapped truth (or the method's previous value),
        the band and the error band need a finite 2 sigma below 180 deg, the error needs the
        truth, NIS per dof and its band need a NIS.
        """
        unwrap = self._unwrap.setdefault(method, _Unwrap())
        n = len(estimates)
        delta = np.fromiter((e.delta_L_rad if e.valid else np.nan for e in estimates), float, n)
        std = np.fromiter((e.std_rad if e.valid else np.nan for e in estimates), float, n)
        nis = np.fromiter((np.nan if e.nis is None else e.nis for e in estimates), float, n)
        dof = np.fromiter((e.nis_dof for e in estimates), float, n)
        unwrapped = np.array(
            [unwrap(float(d), float(r)) for d, r in zip(delta, truth_unwrapped_rad, strict=True)]
        )
        value_deg = np.degrees(unwrapped)
        two_sigma_deg = np.degrees(2.0 * std)
        two_sigma_deg[~(two_sigma_deg < 180.0)] = np.nan
        error_deg = np.degrees(wrap_angle(delta - np.asarray(truth_rad, dtype=float)))
        has_error = np.isfinite(error_deg)
        has_nis = np.isfinite(nis) & (dof > 0)
        nis_per_dof = np.where(has_nis, nis / np.where(has_nis, dof, 1.0), np.nan)
        band = np.array([nis_band_per_dof(int(k)) if k > 0 else (np.nan,) * 2 for k in dof])
        low, high = np.where(has_nis[:, None], band.reshape(n, 2), np.nan).T
        return {
            delta_L_path(method): value_deg,
            band_path(method, "plus"): value_deg + two_sigma_deg,
            band_path(method, "minus"): value_deg - two_sigma_deg,
            error_path(method): error_deg,
            error_band_path(method, "plus"): np.where(has_error, two_sigma_deg, np.nan),
            error_band_path(method, "minus"): np.where(has_error, -two_sigma_deg, np.nan),
            nis_path(method): nis_per_dof,
            nis_band_path(method, "low"): low,
            nis_band_path(method, "high"): high,
        }

    def _truth_at(self, time_s: float, truth_rad: float | None) -> float:
        """The unwrapped truth at a frame time (rad, NaN unknown), logged once per frame.

        Locked: the live loop's sinks log estimates from threads of their own."""
        with self._truth_lock:
            if self._truth_time_s == time_s:
                return self._truth_unwrapped_rad
            self._truth_time_s = time_s
            truth = math.nan if truth_rad is None else float(truth_rad)
            self._truth_unwrapped_rad = self._truth_unwrap(truth)
            if math.isfinite(truth):
                self.stream.log(DELTA_L_TRUTH, rr.Scalars(np.degrees(self._truth_unwrapped_rad)))
            return self._truth_unwrapped_rad

    def log_estimate(self, name: str, estimate: Estimate, truth_rad: float | None = None) -> None:
        """One method's estimate as time series: delta_L unwrapped with its +/-2 sigma band
        (deg), the error with its +/-2 sigma (deg), NIS per dof with its chi-square band.

        An invalid estimate leaves a gap in the lines."""
        self._style_method(name)
        self.set_time(estimate.time_s)
        truth_unwrapped = self._truth_at(estimate.time_s, truth_rad)
        truth = np.array([math.nan if truth_rad is None else truth_rad], dtype=float)
        values = self._series_values(name, [estimate], truth, np.array([truth_unwrapped]))
        for path, value in values.items():
            is_nis = path.startswith(nis_path(name))
            if is_nis and not np.isfinite(value[0]):
                continue  # points, not lines: nothing to break
            self.stream.log(path, rr.Scalars(float(value[0])))

    def log_series(
        self,
        name: str,
        estimates: Sequence[Estimate],
        truth_rad: Array | None = None,
    ) -> None:
        """A whole replay of one method at once (columns; the same series as log_estimate)."""
        self._style_method(name)
        t = np.array([e.time_s for e in estimates], dtype=float)
        truth = np.full(t.size, np.nan) if truth_rad is None else np.asarray(truth_rad, dtype=float)
        unwrap_truth = _Unwrap()
        truth_unwrapped = np.array([unwrap_truth(float(x)) for x in truth])
        if not self._truth_logged and np.isfinite(truth).any():
            self._truth_logged = True
            self._style_truth()
            self._columns(DELTA_L_TRUTH, t, np.degrees(truth_unwrapped))
        for path, values in self._series_values(name, estimates, truth, truth_unwrapped).items():
            if path.startswith(nis_path(name)):
                keep = np.isfinite(values)
                self._columns(path, t[keep], values[keep])
            else:
                self._columns(path, t, values)

    def log_joints(self, time_s: Array, q: Array) -> None:
        """Joint values over time (columns): q_r in deg, q_p and q_d in mm."""
        if not self._joints_styled:
            self._joints_styled = True
            for joint, color in JOINT_COLORS.items():
                self.stream.log(
                    joint_path(joint),
                    rr.SeriesLines(colors=[color], names=[joint]),
                    static=True,
                )
        t = np.asarray(time_s, dtype=float)
        q = np.asarray(q, dtype=float).reshape(-1, 3)
        for k, joint in enumerate(JOINT_COLORS):
            values = np.degrees(q[:, k]) if k == 0 else q[:, k]
            self._columns(joint_path(joint), t, values)

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
            Image time stamp (or arrival) -> estimate sent, s.
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

    def _columns(self, path: str, t: Array, values: Array) -> None:
        if t.size == 0 or not np.isfinite(values).any():
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


FILE_FLUSH_EVERY_S = 0.2
"""How often the live viewer sink flushes a stream written to a file, s: rerun's own period
for files, whose chunks it keeps (:class:`LiveViewerSink`, ``flush_every_s``)."""


class LiveViewerSink:
    """The rerun output as a live-loop sink (:mod:`tracker.live.sinks`).

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
    flush_every_s : float
        The frames logged are flushed (put into chunks and handed to the outputs) after the
        frame that comes this long after the last flush, s (0: after every frame). Give the
        stream a long tick of its own (:func:`~tracker.viewer.output.open_rerun_output`'s
        ``flush_tick_s``): on its own clock (200 ms for a file, 8 ms for a viewer) rerun's
        batcher and file writer spend a few milliseconds at a time on the loop's other
        processor, which in some runs fell on every fourth frame while the segmentation
        worker needed that processor; flushed here, that work follows the frame's estimate.
        Every 200 ms keeps a file's chunks as rerun makes them (after every frame, the
        demo's ``.rrd`` took twice the space).

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
        flush_every_s: float = FILE_FLUSH_EVERY_S,
    ) -> None:
        if int(image_every) < 1:
            raise ValueError(f"image_every must be >= 1, got {image_every}")
        self.viewer, self.scene, self.method = viewer, scene, method
        self.images, self.image_every = images, int(image_every)
        self.truth, self.watch, self.report = truth, watch, report
        self.close_stream = close_stream
        self.flush_every_s = float(flush_every_s)
        self._flushed_s = -math.inf
        self.summary = None
        self.frames = 0
        self._predict_only = 0
        self._lost_reported = False

    def handle(self, frame, observation, estimate, latency_s, status=LiveStatus.NONE) -> None:
        if self.truth is not None and frame.delta_L_true_rad is None:
            truth = self.truth(frame.time_s)
            if truth is not None:
                frame = dataclasses.replace(frame, delta_L_true_rad=float(truth))
        images = self.images and self.frames % self.image_every == 0
        self.frames += 1
        self.viewer.log_frame(frame, observation, {self.method: estimate}, self.scene, images)
        self.viewer.log_estimate(self.method, estimate, frame.delta_L_true_rad)
        self._predict_only += bool(status & PREDICT_ONLY)
        dropped = None if self.summary is None else self.summary.frames_dropped
        self.viewer.log_live(frame.time_s, latency_s, dropped, self._predict_only)
        now = time.monotonic()
        if now - self._flushed_s >= self.flush_every_s:
            # Into chunks and out now, after the frame's estimate has left (started, not
            # waited for): see flush_every_s.
            self._flushed_s = now
            self.viewer.stream.flush(timeout_sec=0.0)
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
