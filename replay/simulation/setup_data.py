"""A simulated lab for the set-up workflow (docs/setup.md): the files a real lab would have.

A hidden truth (:func:`lab_truth`: two cameras, a catheter base pose, the default catheter)
makes everything the tutorial starts from:

- rendered checkerboard pairs for ``cathtrack calibrate`` (:func:`render_boards`); the first
  pair's board defines the world frame {W}, as the calibration takes it;
- measured backbone shapes with 0.1 mm noise for ``cathtrack fit-model``
  (:func:`measured_shapes`);
- the observations of the registration routine for ``cathtrack register``
  (:func:`routine_frames`: the robot steps through the routine with delta_L = 0);
- a short tracking session as the lab's own logs (joint samples, segmented points, truth in
  CSV files with the lab's own column names and units) and their mapping file for
  ``cathtrack import`` (:func:`session_logs`, :func:`write_lab_logs`).

Run as ``python -m replay.simulation.setup_data lab --out lab`` (everything but the routine's
observations) and ``python -m replay.simulation.setup_data observe ROUTINE --out FILE``.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from models.catheter import Catheter, default_catheter
from models.imaging import PinholeView, Rig
from models.pose import Pose
from models.rig_file import rig_toml
from models.rotations import wrap_angle
from models.shape_fit import PointShapes
from replay.simulation.render import (
    RenderSettings,
    default_render_rig,
    look_at_board,
    render_background,
    render_checkerboard,
)
from replay.simulation.simulator import (
    JOINT_RANGE_MM,
    JointTrajectory,
    NoiseSettings,
    Scene,
    hold,
    simulate_frames,
    sinusoidal,
)
from tracker.io.recording import VIEWS, FrameLabels
from tracker.io.routine import observations_from_frames, read_routine, write_observations
from tracker.io.shapes import write_shapes
from tracker.io.tables import write_csv
from tracker.types import Frame

Array = np.ndarray

BOARD_PATTERN = (9, 6)
BOARD_SQUARE_MM = 5.0
SHAPE_NOISE_MM = 0.1
IMAGE_NOISE_PX = 0.5


@dataclass(frozen=True, eq=False)
class LabTruth:
    """The simulated lab, in the world frame of its first checkerboard (as calibrated).

    Attributes
    ----------
    catheter : Catheter
    rig : Rig
        The true cameras.
    base : Pose
        The true base pose ``T_w_b``.
    boards : list of (R_w_board, o_board_w_mm)
        Checkerboard poses; the first is seen by both cameras and is {W} itself.
    both : int
        How many boards (the first ones) face both cameras; the rest alternate between the
        front and the side camera.
    """

    catheter: Catheter
    rig: Rig
    base: Pose
    boards: list[tuple[Array, Array]]
    both: int

    def scene(self) -> Scene:
        return Scene(self.catheter, self.rig, self.base.R_w_b, self.base.o_b_w_mm)


def _in_frame(view: PinholeView, R_s_w: Array, o_w_s: Array) -> PinholeView:
    """The view expressed in a frame {W} whose pose in the old world {S} is (R_s_w, o_w_s)."""
    R = np.asarray(view.R_cam_w) @ R_s_w
    t = np.asarray(view.R_cam_w) @ o_w_s + np.asarray(view.t_cam_w)
    return PinholeView(view.K, R, t, view.dist, view.image_size)


def _tilted(rng: np.random.Generator, toward: Array, tilt_rad: tuple[float, float]) -> Array:
    """A unit normal within ``tilt_rad`` of ``toward``, turned about a random axis."""
    n0 = np.asarray(toward, float) / np.linalg.norm(toward)
    side = np.cross(n0, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    axis = Rotation.from_rotvec(n0 * rng.uniform(0.0, 2.0 * np.pi)).apply(side)
    return Rotation.from_rotvec(axis * rng.uniform(*tilt_rad)).apply(n0)


def lab_truth(seed: int = 0, boards_both: int = 4, boards_single: int = 6) -> LabTruth:
    """The default rendering rig, a tilted base below the cameras' target, and board poses.

    The rig's own frame {S} has the cameras at -y (front) and +x (side), 400 mm away; the
    first board stands at its origin facing both; {W} is that board's frame (origin at its
    first inner corner, x along a row, y down the rows, z into the board).
    """
    rng = np.random.default_rng(seed)
    up = np.array([0.0, 0.0, 1.0])
    both = np.array([1.0, -1.0, 0.0])
    poses = [look_at_board(np.zeros(3), both, up, BOARD_PATTERN, BOARD_SQUARE_MM)]
    normals = [_tilted(rng, both, (0.0, 0.2)) for _ in range(boards_both - 1)]
    for k in range(boards_single):
        toward = np.array([0.0, -1.0, 0.0]) if k % 2 == 0 else np.array([1.0, 0.0, 0.0])
        normals.append(_tilted(rng, toward, (0.35, 0.7)))
    for n in normals:
        board_up = Rotation.from_rotvec(n * rng.uniform(-0.4, 0.4)).apply(up)
        poses.append(
            look_at_board(rng.uniform(-5, 5, 3), n, board_up, BOARD_PATTERN, BOARD_SQUARE_MM)
        )
    R_s_w, o_w_s = poses[0]
    rig_s = default_render_rig()
    rig = Rig(*(_in_frame(v, R_s_w, o_w_s) for v in rig_s.views), names=rig_s.names)
    # The base 15 mm below the cameras' target, turned 25 deg about z and tilted a little.
    R_s_b = Rotation.from_rotvec(np.radians([4.0, -3.0, 25.0])).as_matrix()
    o_b_s = np.array([1.5, -1.0, -15.0])
    base = Pose(R_s_w.T @ R_s_b, R_s_w.T @ (o_b_s - o_w_s))
    boards = [(R_s_w.T @ R, R_s_w.T @ (o - o_w_s)) for R, o in poses]
    return LabTruth(default_catheter(), rig, base, boards, boards_both)


def render_boards(truth: LabTruth, out_dir: str | Path, seed: int = 0) -> list[Path]:
    """Checkerboard pairs as ``out_dir/front/NN.png`` and ``out_dir/side/NN.png``."""
    rng = np.random.default_rng(seed)
    settings = RenderSettings(supersampling=2)
    written = []
    for k, (name, view) in enumerate(zip(truth.rig.names, truth.rig.views, strict=True)):
        folder = Path(out_dir) / name
        folder.mkdir(parents=True, exist_ok=True)
        background = render_background(view.image_size, 20 + k, settings)
        for i, (R, o) in enumerate(truth.boards):
            image = render_checkerboard(
                view, R, o, BOARD_PATTERN, BOARD_SQUARE_MM, rng, background, settings
            )
            path = folder / f"{i:02d}.png"
            if not cv2.imwrite(str(path), image):
                raise OSError(f"cannot write {path}")
            written.append(path)
    return written


def measured_shapes(
    catheter: Catheter,
    rng: np.random.Generator,
    grid: int = 7,
    points_per_segment: int = 6,
    noise_mm: float = SHAPE_NOISE_MM,
    q_range_mm: tuple[float, float] = JOINT_RANGE_MM,
) -> PointShapes:
    """Backbone points of ``grid x grid`` configurations (q_p, q_d) with Gaussian noise.

    Each shape has a random base rotation q_r and delta_L = 0; its points are evenly spaced
    along each segment (the last at the segment's tip), in {B}, with ``noise_mm`` per axis.
    """
    values = np.linspace(*q_range_mm, grid)
    q_p, q_d = (g.ravel() for g in np.meshgrid(values, values))
    q = np.column_stack([rng.uniform(-np.pi, np.pi, q_p.size), q_p, q_d])
    L1, L2 = catheter.proximal.length_mm, catheter.distal.length_mm
    n = points_per_segment
    s = np.concatenate([np.linspace(L1 / n, L1, n), L1 + np.linspace(L2 / n, L2, n)])
    points = catheter.backbone(q, 0.0, s)
    return PointShapes(q, s, points + noise_mm * rng.standard_normal(points.shape))


def routine_frames(
    scene: Scene,
    routine_q: Array,
    rng: np.random.Generator,
    frames_per_step: int = 5,
    sigma: float = IMAGE_NOISE_PX,
    delta_L_rad: float = 0.0,
) -> list[Frame]:
    """The rig's frames while the robot holds each configuration of the routine in turn."""
    frames = []
    for k, q in enumerate(np.asarray(routine_q, dtype=float)):
        trajectory = hold(q, frames_per_step / 20.0, 20.0)
        shifted = JointTrajectory(trajectory.time_s + k, trajectory.q, trajectory.q_dot)
        frames += simulate_frames(scene, shifted, delta_L_rad, NoiseSettings(sigma), rng)
    return frames


# -------------------------------------------------------------------------- session logs
@dataclass(frozen=True)
class SessionLogs:
    """A simulated session as a lab logs it: joint samples, frames and their labels."""

    joint_time_s: Array  # (n,)
    q: Array  # (n, 3)
    q_dot: Array  # (n, 3)
    frames: list[Frame]
    labels: list[FrameLabels]


def session_logs(
    scene: Scene,
    rng: np.random.Generator,
    planes_deg: tuple[float, ...] = (0.0, 120.0, 240.0),
    bends_mm: tuple[tuple[float, float], ...] = ((0.6, 0.3), (-0.5, 0.7)),
    delta_L_deg: tuple[float, ...] = (30.0, -45.0, 60.0),
    frames_per_configuration: int = 20,
    frame_rate_hz: float = 20.0,
    joint_rate_hz: float = 200.0,
    sigma: float = IMAGE_NOISE_PX,
) -> SessionLogs:
    """A few configurations per bending plane, each held with a little joint motion.

    The torsional loss is constant within a plane (``delta_L_deg``, one per plane); the joint
    stream runs at ``joint_rate_hz``, the frames at ``frame_rate_hz``.
    """
    step = int(round(joint_rate_hz / frame_rate_hz))
    duration_s = frames_per_configuration / frame_rate_hz
    times, qs, rates, frames, labels = [], [], [], [], []
    configuration = 0
    for plane, (q_r_deg, delta_L) in enumerate(zip(planes_deg, delta_L_deg, strict=True)):
        for q_p, q_d in bends_mm:
            start = configuration * duration_s
            joints = sinusoidal(
                mean=[np.radians(q_r_deg), q_p, q_d],
                amplitude=[0.02, 0.04, 0.04],
                period_s=[duration_s, duration_s, duration_s],
                duration_s=duration_s,
                frame_rate_hz=joint_rate_hz,
            )
            at_frames = JointTrajectory(
                joints.time_s[::step] + start, joints.q[::step], joints.q_dot[::step]
            )
            new = simulate_frames(scene, at_frames, np.radians(delta_L), NoiseSettings(sigma), rng)
            delta_1 = at_frames.q[:, 0] + np.radians(delta_L)
            frames += new
            labels += [
                FrameLabels(
                    plane=plane,
                    configuration=configuration,
                    deflection_mm=0.0,
                    noise_level=sigma,
                    delta_1_true_rad=float(wrap_angle(d)),
                )
                for d in delta_1
            ]
            times.append(joints.time_s + start)
            qs.append(joints.q)
            rates.append(joints.q_dot)
            configuration += 1
    return SessionLogs(
        np.concatenate(times), np.concatenate(qs), np.concatenate(rates), frames, labels
    )


LAB_MAPPING = """\
# How the lab's logs map to a cathtrack recording (cathtrack import, docs/setup.md).
format = "cathtrack-import"
version = 1
unit = "px"

[joints]
file = "logs/joints.csv"
time = "t_ms"
time_unit = "ms"
q_r = "qr_deg"
q_r_unit = "deg"
q_p = "qp"
q_d = "qd"

[front]
file = "logs/markers.csv"
time = "t_ms"
time_unit = "ms"
points = {front}
sigma = {sigma}

[side]
file = "logs/markers.csv"
time = "t_ms"
time_unit = "ms"
points = {side}
sigma = {sigma}

[truth]
file = "logs/truth.csv"
time = "t_ms"
time_unit = "ms"
delta_L = "dL_deg"
delta_L_unit = "deg"
plane = "plane"
configuration = "config"
"""


def write_lab_logs(out_dir: str | Path, logs: SessionLogs, sigma: float = IMAGE_NOISE_PX) -> Path:
    """The session as the lab's CSV logs in ``out_dir/logs`` and ``out_dir/import.toml``.

    The columns have the lab's names and units (ms, deg), which the mapping file translates.
    """
    out = Path(out_dir)
    (out / "logs").mkdir(parents=True, exist_ok=True)
    write_csv(
        out / "logs" / "joints.csv",
        {
            "t_ms": logs.joint_time_s * 1e3,
            "qr_deg": np.degrees(logs.q[:, 0]),
            "qp": logs.q[:, 1],
            "qd": logs.q[:, 2],
        },
        "joint samples of the controller",
    )
    n_points = logs.frames[0].uv[0].shape[0]
    points = ["tip"] + [f"m{k}" for k in range(n_points - 1)]
    names = {view: [[f"{view[0]}_{p}_u", f"{view[0]}_{p}_v"] for p in points] for view in VIEWS}
    columns = {"t_ms": np.array([f.time_s * 1e3 for f in logs.frames])}
    for k, view in enumerate(VIEWS):
        uv = np.array([f.uv[k] for f in logs.frames])
        for k, (u, v) in enumerate(names[view]):
            columns[u], columns[v] = uv[:, k, 0], uv[:, k, 1]
    write_csv(out / "logs" / "markers.csv", columns, "segmented points, px")
    write_csv(
        out / "logs" / "truth.csv",
        {
            "t_ms": columns["t_ms"],
            "dL_deg": np.degrees([f.delta_L_true_rad for f in logs.frames]),
            "plane": np.array([label.plane for label in logs.labels]),
            "config": np.array([label.configuration for label in logs.labels]),
        },
        "true torsional loss",
    )
    mapping = LAB_MAPPING.format(
        front=json.dumps(names["front"]),
        side=json.dumps(names["side"]),
        sigma=repr(float(sigma)),
    )
    path = out / "import.toml"
    path.write_text(mapping, encoding="utf-8")
    return path


def write_truth(path: str | Path, truth: LabTruth) -> Path:
    """The true rig and base pose as a rig file, to compare with what the workflow found."""
    comment = "The simulated lab's truth (replay.simulation.setup_data)."
    text = rig_toml(truth.rig, truth.base, comment)
    Path(path).write_text(text, encoding="utf-8")
    return Path(path)


def make_lab(out_dir: str | Path, seed: int = 0) -> list[Path]:
    """Every file of the simulated lab except the routine's observations."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    truth = lab_truth(seed)
    rng = np.random.default_rng(seed + 1)
    files = render_boards(truth, out / "boards", seed)
    files.append(
        write_shapes(
            out / "shapes.csv",
            measured_shapes(truth.catheter, rng),
            f"simulated shapes of the default catheter, {SHAPE_NOISE_MM} mm noise per axis",
        )
    )
    files.append(write_lab_logs(out, session_logs(truth.scene(), rng)))
    files.append(write_truth(out / "truth.toml", truth))
    return files


def observe_routine(routine_path: str | Path, out_path: str | Path, seed: int = 0) -> Path:
    """The rig's observations of the routine in ``routine_path`` (the simulated robot runs it)."""
    truth = lab_truth(seed)
    frames = routine_frames(
        truth.scene(), read_routine(routine_path), np.random.default_rng(seed + 2)
    )
    q, uv = observations_from_frames(frames)
    return write_observations(
        out_path, q, uv, comment="simulated observations of the registration routine, px"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m replay.simulation.setup_data",
        description="Make the files of a simulated lab for the set-up tutorial (docs/setup.md).",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    lab = sub.add_parser("lab", help="checkerboards, shapes, session logs and the truth")
    lab.add_argument("--out", default="lab", metavar="DIR", help="folder to write (lab)")
    lab.add_argument("--seed", type=int, default=0, help="random seed (0)")
    observe = sub.add_parser("observe", help="the rig's observations of a routine")
    observe.add_argument("routine", metavar="ROUTINE", help="routine file (cathtrack register)")
    observe.add_argument("--out", required=True, metavar="FILE", help="observation table")
    observe.add_argument("--seed", type=int, default=0, help="random seed of the lab (0)")
    args = parser.parse_args(argv)
    try:
        if args.command == "lab":
            files = make_lab(args.out, args.seed)
            print(f"wrote {len(files)} files to {args.out}")
        else:
            print(f"wrote {observe_routine(args.routine, args.out, args.seed)}")
    except (ValueError, OSError) as exc:
        print(f"setup_data {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
