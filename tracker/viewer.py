"""Every rerun call of the project: entity paths, the default blueprint, and the logging sink.

The live loop and the offline replay share :class:`RerunSink`, which logs to an explicit
:class:`rerun.RecordingStream` (never the global one):

- ``world/...`` -- the 3-D scene in {W}, mm: the catheter model at the estimated bending plane
  and, where known, at the true one; the reconstructed markers; the tip's +/-2 sigma arc of
  uncertainty about the base axis; the cameras (pinhole views) with their images;
- ``world/cameras/<view>/...`` -- each camera's image, the segmented markers and the markers
  reprojected from the estimate (pinhole rigs); ``views/<view>/...`` the same points in mm
  for the paper's orthographic planes, which have no camera;
- ``series/...`` -- time series in degrees: delta_L of every method with the truth and the
  +/-2 sigma band, the bending-plane error, and the NIS.

Time is the ``time`` timeline (s since the start of the session) and the ``frame`` sequence.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from models.imaging import PinholeView
from models.rotations import wrap_angle
from tracker.observation import Estimate, Observation
from tracker.pipeline import Frame

Array = np.ndarray

VIEWS = ("front", "side")
TIMELINE = "time"
FRAME_SEQUENCE = "frame"

# Entity paths, in one place.
WORLD = "world"
CATHETER_ESTIMATE = "world/catheter/estimate"
CATHETER_TRUTH = "world/catheter/truth"
TIP_UNCERTAINTY = "world/catheter/uncertainty"
MARKERS_3D = "world/markers"
SERIES_DELTA_L = "series/delta_L"
SERIES_ERROR = "series/error"
SERIES_NIS = "series/nis"


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
SEGMENTED_COLOR = (0, 200, 255)
REPROJECTED_COLOR = (255, 60, 60)


def default_blueprint(methods: Sequence[str] = (), pinhole: bool = True) -> rrb.Blueprint:
    """3-D scene and both views on the left; delta_L, error and NIS over time on the right."""
    views = [rrb.Spatial2DView(origin=view_path(v, pinhole), name=f"{v} view") for v in VIEWS]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin=WORLD, name="3-D scene"),
                rrb.Horizontal(*views),
                row_shares=[3, 2],
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(origin=SERIES_DELTA_L, name="delta_L (deg)"),
                rrb.TimeSeriesView(origin=SERIES_ERROR, name="bending-plane error (deg)"),
                rrb.TimeSeriesView(origin=SERIES_NIS, name="NIS"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


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
    """

    def __init__(
        self, stream: rr.RecordingStream, primary: str | None = None, backbone_points: int = 40
    ) -> None:
        self.stream = stream
        self.primary = primary
        self._s = None
        self._backbone_points = int(backbone_points)
        self._scene_id: int | None = None
        self._methods: list[str] = []
        self._frame_index = 0
        self._truth_logged = False

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

    def set_time(self, time_s: float) -> None:
        self.stream.set_time(TIMELINE, duration=float(time_s))

    # ---------------------------------------------------------------- per frame
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
        scene : replay.simulator.Scene or anything with catheter, rig, R_w_b, o_b_w_mm
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
                self.stream.log(image_path(name), rr.Image(frame.images[k]))
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
            self.stream.log(f"{SERIES_DELTA_L}/truth", rr.Scalars(np.degrees(truth_rad)))
            error = np.degrees(wrap_angle(estimate.delta_L_rad - truth_rad))
            self.stream.log(error_path(name), rr.Scalars(error))
        if estimate.nis is not None and np.isfinite(estimate.nis):
            self.stream.log(nis_path(name), rr.Scalars(estimate.nis))

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
            indexes=[rr.TimeColumn(TIMELINE, duration=t)],
            columns=rr.Scalars.columns(scalars=values),
        )


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
