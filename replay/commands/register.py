"""``cathtrack register``: the registration routine, and the base pose from its observations.

The routine and the fit are models.registration; the observations are a table
(tracker.io.routine) or a recording; the pose goes into the rig file's ``[base]`` table
(models.rig_file), with the rest of the file kept.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from models.catheter import Catheter
from models.model_file import DEFAULT_MODEL_PATH, load_catheter
from models.pose import Pose
from models.registration import (
    DEFAULT_BENDS_MM,
    Registration,
    register_base,
    registration_routine,
)
from models.rig_file import read_rig_file, rig_from_dict, rig_toml, written_model
from replay.setup_commands import CONVENTION
from tracker.io.recording import VIEWS, open_recording
from tracker.io.routine import observations_from_frames, read_observations, write_routine

Array = np.ndarray


def _routine(args: argparse.Namespace) -> Array:
    bends = DEFAULT_BENDS_MM if args.bends_mm is None else args.bends_mm
    if len(np.ravel(bends)) % 2:
        raise ValueError(f"--bends-mm takes (q_p, q_d) pairs, got {len(args.bends_mm)} numbers")
    return registration_routine(args.planes, np.reshape(bends, (-1, 2)))


def routine_lines(q: Array) -> list[str]:
    """The routine as a table for the console."""
    lines = [f"{'step':>4} {'q_r (deg)':>10} {'q_p (mm)':>9} {'q_d (mm)':>9}"]
    for k, (q_r, q_p, q_d) in enumerate(q, start=1):
        lines.append(f"{k:4d} {np.degrees(q_r):10.1f} {q_p:9.3f} {q_d:9.3f}")
    return lines


def _observations(path: str, catheter: Catheter) -> tuple[Array, tuple[Array, ...]]:
    if Path(path).suffix.lower() == ".mcap":
        with open_recording(path) as recording:
            frames = [recorded.frame for recorded in recording.frames(images=False)]
        return observations_from_frames(frames)
    return read_observations(path, 1 + len(catheter.marker_arclengths_mm), VIEWS)


def registered_rig_toml(data: dict, source: str, pose: Pose, comment: str, extra: dict) -> str:
    """The rig file ``data`` with ``[base]`` set to ``pose``: its views as written, every other
    table and key kept (rig_toml writes the views' own keys with the values read from them),
    ``extra`` tables added."""
    rig = rig_from_dict(data, source, written_model(data, source))
    kept = {name: table for name, table in data.items() if isinstance(table, dict)}
    kept.pop("base", None)
    return rig_toml(rig, pose, comment, {**kept, **extra})


def registration_lines(registration: Registration, names: tuple[str, ...], unit: str) -> list[str]:
    """The report of ``register``: residuals per view, pose and its uncertainty."""
    r = registration
    pose = r.pose
    residuals = ", ".join(
        f"{name} {value:.3f} {unit}" for name, value in zip(names, r.residual_rms, strict=True)
    )
    rotvec = np.degrees(Rotation.from_matrix(pose.R_w_b).as_rotvec())
    return [
        f"residual RMS: {residuals}; 3-D {r.residual_3d_rms_mm:.3f} mm (two-view points to the"
        " model)",
        f"base origin o_b_w: {_vector(pose.o_b_w_mm, 3)} mm, 1 sigma"
        f" {_vector(r.std_origin_mm, 3)} mm",
        f"base axis z_b in the world: {_vector(pose.R_w_b[:, 2], 4)}; rotation vector of R_w_b"
        f" {_vector(rotvec, 3)} deg",
        "rotation 1 sigma about x_b, y_b, z_b:"
        f" {_vector(np.degrees(r.std_rotation_base_rad), 3)} deg (the one about z_b adds to"
        " every delta_L)",
        f"convention: {CONVENTION}",
    ]


def _vector(v: Array, digits: int) -> str:
    return "[" + ", ".join(f"{x:.{digits}f}" for x in np.asarray(v, float)) + "]"


def run(args: argparse.Namespace) -> int:
    if args.observations is None:
        q = _routine(args)
        print(
            f"cathtrack register: registration routine, {len(q)} steps. Run it with the"
            " catheter body straight and untwisted (delta_L = 0 defines the base x axis),"
            " record image pairs at each step and give them to 'cathtrack register"
            " OBSERVATIONS --rig FILE'."
        )
        for line in routine_lines(q):
            print(line)
        if args.routine_out:
            print(f"wrote {write_routine(args.routine_out, q, 'cathtrack register routine')}")
        return 0
    if args.rig is None:
        raise ValueError("give the rig file of the calibrated cameras (--rig FILE)")
    catheter = load_catheter(DEFAULT_MODEL_PATH if args.model is None else args.model)
    data = read_rig_file(args.rig)
    rig = rig_from_dict(data, args.rig, args.rig_model)
    q, uv = _observations(args.observations, catheter)
    try:
        registration = register_base(catheter, rig, q, uv)
    except ValueError as exc:
        raise ValueError(f"{args.observations}: {exc}") from None
    unit = "px" if rig.kind == "pinhole" else "mm"
    points = zip(rig.names, registration.n_points, strict=True)
    print(
        f"cathtrack register: {registration.n_configurations} configurations,"
        f" {len(q)} image pairs, " + ", ".join(f"{n} {name} points" for name, n in points)
    )
    for line in registration_lines(registration, rig.names, unit):
        print(line)
    out = args.out or args.rig
    table = {
        "observations": Path(args.observations).name,
        "configurations": registration.n_configurations,
        "residual_rms": list(registration.residual_rms),
        "residual_unit": unit,
        "std_origin_mm": registration.std_origin_mm,
        "std_rotation_base_deg": np.degrees(registration.std_rotation_base_rad),
        "convention": CONVENTION,
    }
    comment = f"cathtrack register: base registered from {Path(args.observations).name}"
    text = registered_rig_toml(data, args.rig, registration.pose, comment, {"registration": table})
    try:
        Path(out).write_text(text, encoding="utf-8")
    except OSError as exc:
        raise OSError(f"cannot write rig file {out}: {exc.strerror or exc}") from None
    print(f"wrote {out} [base]")
    return 0
