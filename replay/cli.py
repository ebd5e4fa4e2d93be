"""The ``cathtrack`` command line: one entry point, one subcommand per job.

``main(argv)`` only wires things together so tests can call it. Errors a user can cause end
in one clear line on stderr and exit code 2, not a traceback.
"""

from __future__ import annotations

import argparse
import sys
from importlib import metadata


def _version() -> str:
    try:
        return metadata.version("cathtrack")
    except metadata.PackageNotFoundError:
        return "0+unknown"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cathtrack",
        description=(
            "Estimate the torsional loss delta_L and the bending plane of a two-segment "
            "steerable catheter from joint values and bi-plane images."
        ),
    )
    parser.add_argument("--version", action="version", version=f"cathtrack {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    from replay.demo import DEFAULT_RRD
    from tracker.viewer.sink import add_rerun_args

    demo = sub.add_parser(
        "demo",
        help="track a simulated bi-plane session live and write a rerun recording",
        description=(
            "Track a simulated session with the live loop of 'cathtrack track': a simulated "
            "controller streams the joint values at 1 kHz over loopback UDP, two simulated "
            "640x480 cameras render the catheter at 20 fps, and the loop segments every image "
            "pair, runs the UKF (and the closed-form Tip Position estimator on the same "
            "observations) and sends each estimate back to the controller. Writes a rerun "
            "recording (out/demo.rrd; --connect, --spawn or --serve to watch it live) and "
            "prints the accuracy in degrees and the latency at the end. Runs in real time."
        ),
    )
    demo.add_argument(
        "--seconds", type=float, default=15.0, help="length of the session, s (default 15)"
    )
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument(
        "--estimator", default="ukf", metavar="NAME", help="the loop's estimator (default ukf)"
    )
    demo.add_argument(
        "--frame-rate-hz", type=float, default=20.0, help="image pairs per second (default 20)"
    )
    demo.add_argument(
        "--no-images", action="store_true", help="no images in the rerun recording"
    )
    demo.add_argument(
        "--image-every",
        type=int,
        default=2,
        metavar="N",
        help="images of every N-th pair in the rerun recording (default 2)",
    )
    add_rerun_args(demo, save_default=DEFAULT_RRD)
    demo.set_defaults(run=_run_demo)
    _add_track(sub)
    _add_sensitivity(sub)
    _add_calibrate(sub)
    _add_simulate(sub)
    _add_evaluate(sub)
    return parser


# Command-line option -> SensitivitySettings field. Every option defaults to None: unset
# options keep the value of --settings FILE, or the documented default.
_SENSITIVITY_OPTIONS = {
    "seed": "seed",
    "trials": "trials",
    "ukf_trials": "ukf_trials",
    "chunk_trials": "chunk_trials",
    "methods": "methods",
    "studies": "studies",
    "delta_2_deg": "delta_2_deg",
    "view": "view",
    "noise_levels_mm": "noise_levels_mm",
    "noise_mm": "noise_mm",
    "configuration_deg": "configuration_theta_L_deg",
    "theta_l1_deg": "theta_L1_deg",
    "theta_l2_deg": "theta_L2_deg",
    "deflection_levels_mm": "deflection_levels_mm",
    "deflections": "deflections",
    "deflection_joint": "deflection_joint",
    "joint_rates": "joint_rates",
    "frame_interval_s": "frame_interval_s",
    "frames_per_trial": "frames_per_trial",
    "delta_l_deg": "delta_L_deg",
}


def _add_sensitivity(sub) -> None:
    p = sub.add_parser(
        "sensitivity",
        help="run the paper's three sensitivity studies for every estimator and the bound",
        description=(
            "The three sensitivity studies of Lawson, Chitale and Simaan (ICRA 2023) for Tip "
            "Position, Body Positions, Tip Velocity, the UKF and the Cramer-Rao bound, each for "
            "delta_2 = 0 and a non-planar delta_2: (a) error against segmentation noise, (b) over "
            "a grid of tip angles around the straight configuration, (c) against tip deflection "
            "by contact. Writes study_{a,b,c}.csv, study_{a,b,c}.png, summary.md and "
            "settings.json. Lists are space-separated; the same seed gives the same tables "
            "whatever the number of workers."
        ),
    )
    run = p.add_argument_group("run")
    run.add_argument("--out", default="results/sensitivity", help="output directory")
    run.add_argument(
        "--settings", metavar="FILE", help="start from the settings.json of an earlier run"
    )
    run.add_argument("--seed", type=int, help="random seed (default 0)")
    run.add_argument(
        "--workers", type=int, help="local worker processes (default: all CPUs; 1: in-process)"
    )
    run.add_argument(
        "--scheduler", metavar="ADDRESS", help="run on this Dask scheduler (tcp://host:8786)"
    )
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    what = p.add_argument_group("what to run")
    what.add_argument(
        "--methods",
        nargs="*",
        metavar="NAME",
        help="tip-position body-positions tip-velocity ukf crb (default), also ukf-position and"
        " the least-squares baselines *-lsq",
    )
    what.add_argument("--studies", nargs="*", metavar="X", help="any of a b c (default all)")
    what.add_argument(
        "--delta-2-deg", nargs="*", type=float, metavar="DEG", help="distal plane angles (0 90)"
    )
    what.add_argument("--view", metavar="KIND", help="orthographic (default) or pinhole")
    what.add_argument("--trials", type=int, help="trials per study point (500)")
    what.add_argument(
        "--ukf-trials",
        type=int,
        help="of those, how many the UKF and the least-squares baselines use (all)",
    )
    what.add_argument("--chunk-trials", type=int, help="trials per parallel task (500)")
    what.add_argument(
        "--delta-l-deg", type=float, help="fixed true delta_L (default uniform per trial)"
    )
    levels = p.add_argument_group("study levels")
    levels.add_argument(
        "--noise-levels-mm", nargs="*", type=float, metavar="MM", help="(a): 0 0.5 ... 5"
    )
    levels.add_argument("--noise-mm", type=float, help="(b), (c): noise (1 mm)")
    levels.add_argument(
        "--configuration-deg",
        nargs="*",
        type=float,
        metavar="DEG",
        help="(a), (c): tip angles theta_L1 theta_L2 (45 45; 90 is straight)",
    )
    levels.add_argument(
        "--theta-l1-deg", nargs="*", type=float, metavar="DEG", help="(b): grid (0 22.5 ... 180)"
    )
    levels.add_argument(
        "--theta-l2-deg", nargs="*", type=float, metavar="DEG", help="(b): grid (0 22.5 ... 180)"
    )
    levels.add_argument(
        "--deflection-levels-mm", nargs="*", type=float, metavar="MM", help="(c): 0 1 ... 10"
    )
    levels.add_argument(
        "--deflections", nargs="*", metavar="KIND", help="(c): in-plane out-of-plane (both)"
    )
    levels.add_argument(
        "--deflection-joint", metavar="JOINT", help="(c): joint of in-plane deflection (q_d)"
    )
    motion = p.add_argument_group("motion (Tip Velocity, UKF)")
    motion.add_argument(
        "--joint-rates",
        nargs="*",
        type=float,
        metavar="RATE",
        help="q_r rad/s, q_p mm/s, q_d mm/s (0.5 0.25 0.25)",
    )
    motion.add_argument("--frame-interval-s", type=float, help="frame interval, s (0.05)")
    motion.add_argument("--frames-per-trial", type=int, help="frames per trial, >= 2 (10)")
    p.set_defaults(run=_run_sensitivity)


def _run_sensitivity(args: argparse.Namespace) -> int:
    import dataclasses

    from replay import studies

    base = studies.SensitivitySettings()
    if args.settings:
        base = studies.load_settings(args.settings)
    changes = {
        field: getattr(args, option)
        for option, field in _SENSITIVITY_OPTIONS.items()
        if getattr(args, option) is not None
    }
    settings = dataclasses.replace(base, **changes)
    result = studies.run_sensitivity(
        settings, workers=args.workers, scheduler=args.scheduler, progress=not args.no_progress
    )
    paths = studies.write_outputs(result, args.out)
    print(
        f"cathtrack sensitivity: studies {', '.join(settings.studies)}, {settings.trials} trials"
        f" per point ({settings.effective_ukf_trials} for the UKF), seed {settings.seed},"
        f" {result.elapsed_s:.1f} s"
    )
    for finding in studies.findings(result.rows):
        mark = {True: "holds", False: "DOES NOT HOLD", None: "not checked"}[finding.holds]
        print(f"  {finding.claim}: {mark}")
    print(f"wrote {len(paths)} files to {args.out}: " + ", ".join(p.name for p in paths))
    return 0


def _add_calibrate(sub) -> None:
    p = sub.add_parser(
        "calibrate",
        help="calibrate the two cameras and write a rig file from checkerboard images",
        description=(
            "Calibrate each camera by Zhang's method from images of a checkerboard, then the "
            "pose of the side camera relative to the front one from the pairs where both saw "
            "the board; the board of the first such pair defines the world frame. Images are "
            "paired by sorted file name. Writes a rig file (TOML, docs/vision.md) and prints "
            "the per-view and total reprojection errors in px."
        ),
    )
    p.add_argument("--front", required=True, metavar="DIR", help="folder of front-camera images")
    p.add_argument("--side", required=True, metavar="DIR", help="folder of side-camera images")
    p.add_argument(
        "--board", default="9x6", help="inner corners per row x per column (default 9x6)"
    )
    p.add_argument(
        "--square-mm", type=float, default=25.0, help="side of one square, mm (default 25)"
    )
    p.add_argument(
        "--fix-aspect-ratio", action="store_true", help="calibrate with fx = fy"
    )
    p.add_argument("--out", default="rig.toml", metavar="FILE", help="rig file (rig.toml)")
    p.set_defaults(run=_run_calibrate)


def _run_calibrate(args: argparse.Namespace) -> int:
    from tracker.vision.rig_calibration import (
        calibrate_folders,
        parse_board,
        report_lines,
        write_rig,
    )

    pattern = parse_board(args.board)
    calibration, files_f, files_s = calibrate_folders(
        args.front, args.side, pattern, args.square_mm, args.fix_aspect_ratio
    )
    world = calibration.world_pair
    comment = (
        f"cathtrack calibrate: {len(files_f)} image pairs, board {pattern[0]}x{pattern[1]}"
        f" of {args.square_mm:g} mm squares;\nworld frame: the board in"
        f" {files_f[world].name} / {files_s[world].name}"
    )
    path = write_rig(args.out, calibration.rig, calibration, comment)
    for line in report_lines(calibration):
        print(line)
    print(f"world frame: the board in {files_f[world].name} / {files_s[world].name}")
    print(f"wrote {path}")
    return 0


def _add_simulate(sub) -> None:
    p = sub.add_parser(
        "simulate",
        help="write a recording (MCAP) of a simulated session of the paper's protocol",
        description=(
            "Simulate the experimental protocol of Lawson, Chitale and Simaan (ICRA 2023) and "
            "write it as a recording (MCAP, docs/recording.md): the catheter turned to 11 "
            "bending planes, 94 joint configurations in all, 100 frames each at 20 Hz with a "
            "little joint motion, joint values at 1 kHz, tip deflection by contact for part of "
            "the configurations, and both camera images rendered and segmented (or only the "
            "segmented markers with realistic noise, --no-images). Seeded: the same options "
            "give the same recording whatever the number of workers."
        ),
    )
    p.add_argument("--protocol", default="paper", choices=["paper"], help="protocol (paper)")
    p.add_argument("--out", default="recording.mcap", metavar="FILE", help="recording to write")
    p.add_argument("--no-images", action="store_true", help="segmented markers only, no images")
    p.add_argument(
        "--rig",
        choices=["pinhole", "orthographic"],
        default="pinhole",
        help="two 640x480 cameras (default) or the paper's orthographic planes (markers only)",
    )
    p.add_argument("--model", metavar="FILE", help="catheter model file (default model)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--planes", type=int, default=11, help="bending planes (11)")
    p.add_argument("--configs", type=int, default=94, help="joint configurations in all (94)")
    p.add_argument("--frames", type=int, default=100, help="frames per configuration (100)")
    p.add_argument("--frame-rate-hz", type=float, default=20.0, help="frame rate (20)")
    p.add_argument("--joint-rate-hz", type=float, default=1000.0, help="joint sample rate (1000)")
    p.add_argument(
        "--noise-levels-mm",
        nargs="+",
        type=float,
        metavar="MM",
        help="markers only: segmentation noise per configuration, cycled (0.5 1 1.5)",
    )
    p.add_argument(
        "--image-noise-levels-gray",
        nargs="+",
        type=float,
        metavar="GRAY",
        help="with images: sensor noise of the rendered frames, cycled (2 3.5 5)",
    )
    p.add_argument(
        "--deflection-levels-mm",
        nargs="+",
        type=float,
        metavar="MM",
        help="tip deflection per configuration, cycled after the noise (0 0 1.5 3)",
    )
    p.add_argument(
        "--no-transition-frames",
        action="store_true",
        help="record no frames while the joints move between configurations",
    )
    p.add_argument("--workers", type=int, help="processes rendering the images (default: all CPUs)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(run=_run_simulate)


def _run_simulate(args: argparse.Namespace) -> int:
    from replay.protocol import ProtocolSettings, simulate_protocol

    options = {
        "seed": args.seed,
        "planes": args.planes,
        "configurations": args.configs,
        "frames_per_configuration": args.frames,
        "frame_rate_hz": args.frame_rate_hz,
        "joint_rate_hz": args.joint_rate_hz,
        "images": not args.no_images,
        "rig": args.rig,
        "transition_frames": not args.no_transition_frames,
    }
    for option, field in (
        ("noise_levels_mm", "noise_levels_mm"),
        ("image_noise_levels_gray", "image_noise_levels_gray"),
        ("deflection_levels_mm", "deflection_levels_mm"),
    ):
        if getattr(args, option) is not None:
            options[field] = tuple(getattr(args, option))
    settings = ProtocolSettings(**options)
    summary = simulate_protocol(
        settings, args.out, args.model, workers=args.workers, progress=not args.no_progress
    )
    print(
        f"cathtrack simulate: wrote {summary.path}: protocol {args.protocol},"
        f" {settings.planes} planes, {settings.configurations} configurations,"
        f" {summary.frames} frames ({'images and markers' if settings.images else 'markers only'}),"
        f" {summary.joint_samples} joint samples, {summary.duration_s:.1f} s of session,"
        f" {summary.bytes / 1e6:.1f} MB"
    )
    return 0


def _add_evaluate(sub) -> None:
    p = sub.add_parser(
        "evaluate",
        help="replay recordings through the estimators and report the paper's tables",
        description=(
            "Replay each recording (MCAP, docs/recording.md) through the chosen estimators, "
            "with the joint values interpolated to the frame times, and report per method the "
            "RMS and maximum bending-plane error (degrees) over all configurations, per bending "
            "plane, against tip deflection and against segmentation noise, next to the "
            "Cramer-Rao bound; for the UKF also NEES consistency and 2-sigma coverage. Writes "
            "summary.md, summary.csv, frames.csv, experiment.png, conditions.png and "
            "replay.rrd (rerun) per recording. Several recordings run in parallel on local "
            "processes or a Dask cluster and add batch.md / batch.csv."
        ),
    )
    p.add_argument("recordings", nargs="+", metavar="RECORDING", help="recording file(s)")
    p.add_argument(
        "--methods",
        nargs="+",
        metavar="NAME",
        help="estimators (default all): tip-position body-positions tip-velocity, the"
        " least-squares baselines *-lsq, ukf, ukf-position",
    )
    p.add_argument(
        "--source",
        choices=["auto", "markers", "images"],
        default="auto",
        help="recorded markers, or segment the recorded images (auto: images if present)",
    )
    p.add_argument("--out", default="results/evaluate", metavar="DIR", help="output directory")
    p.add_argument("--no-rrd", action="store_true", help="do not write replay.rrd")
    p.add_argument(
        "--rrd-frame-every", type=int, default=4, metavar="N", help="3-D scene every N frames (4)"
    )
    p.add_argument(
        "--rrd-image-every", type=int, default=20, metavar="N", help="images every N frames (20)"
    )
    p.add_argument("--no-figures", action="store_true", help="do not write the PNG figures")
    p.add_argument(
        "--workers",
        type=int,
        help="local processes: one per recording, or one per method for a single recording"
        " (default: all CPUs)",
    )
    p.add_argument(
        "--scheduler", metavar="ADDRESS", help="run on this Dask scheduler (tcp://host:8786)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(run=_run_evaluate)


def _run_evaluate(args: argparse.Namespace) -> int:
    import os
    from pathlib import Path

    from replay import evaluation

    options = dict(
        methods=args.methods,
        source=args.source,
        rrd=not args.no_rrd,
        rrd_frame_every=args.rrd_frame_every,
        rrd_image_every=args.rrd_image_every,
        figures=not args.no_figures,
    )
    if len(args.recordings) == 1 and not args.scheduler:
        result = evaluation.evaluate_recording(
            args.recordings[0],
            args.out,
            progress=not args.no_progress,
            workers=(os.cpu_count() or 1) if args.workers is None else args.workers,
            **options,
        )
        print(Path(result.files[0]).read_text(), end="")
        print(
            f"wrote {len(result.files)} files to {args.out}: "
            + ", ".join(f.name for f in result.files)
        )
        return 0
    items = evaluation.evaluate_batch(
        args.recordings,
        args.out,
        workers=args.workers,
        scheduler=args.scheduler,
        progress=not args.no_progress,
        **options,
    )
    print((Path(args.out) / "batch.md").read_text(), end="")
    failed = [item for item in items if item.error]
    for item in failed:
        print(f"cathtrack evaluate: {item.path}: error: {item.error}", file=sys.stderr)
    print(f"wrote {Path(args.out) / 'batch.md'}, batch.csv and one folder per recording")
    return 1 if failed else 0


def _run_demo(args: argparse.Namespace) -> int:
    from replay.demo import DemoSettings, run_demo

    settings = DemoSettings(
        seconds=args.seconds,
        frame_rate_hz=args.frame_rate_hz,
        seed=args.seed,
        estimator=args.estimator,
        images=not args.no_images,
        image_every=args.image_every,
    )
    return run_demo(settings, args)


# ------------------------------------------------------------------------------ track
def _add_track(sub) -> None:
    from tracker.viewer.sink import add_rerun_args

    p = sub.add_parser(
        "track",
        help="track the catheter live: joints over UDP, images or markers in, estimates out",
        description=(
            "The online loop (docs/live.md): joint values arrive as UDP datagrams (up to "
            "1 kHz) and are interpolated to each image time; frames come from two cameras or "
            "video files (segmented here), from an external segmenter over UDP, or from a "
            "recording played back at real time; every frame is reconstructed and the "
            "estimator's result goes to the outputs: UDP datagrams to the controller, "
            "OpenIGTLink transforms for 3D Slicer, an MCAP recording and rerun. Listeners "
            "bind to 127.0.0.1 unless --bind says otherwise. Ctrl-C stops cleanly: the "
            "summary is printed, files are finished and sockets released (exit code 130)."
        ),
    )
    src = p.add_argument_group("frames (exactly one source)")
    src.add_argument("--camera-front", metavar="INDEX", help="front camera (OpenCV index)")
    src.add_argument("--camera-side", metavar="INDEX", help="side camera (OpenCV index)")
    src.add_argument("--video-front", metavar="FILE", help="front video file")
    src.add_argument("--video-side", metavar="FILE", help="side video file")
    src.add_argument(
        "--markers-port",
        type=int,
        metavar="PORT",
        help="segmented markers as UDP datagrams on this port (docs/live.md; e.g. 25002)",
    )
    src.add_argument(
        "--recording",
        metavar="FILE",
        help="play a recording (MCAP) back, with its model, rig, base pose and joint values",
    )
    src.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="playback speed of --recording (default 1: real time; 0: as fast as possible)",
    )
    src.add_argument(
        "--backgrounds",
        nargs=2,
        metavar=("FRONT", "SIDE"),
        help="images of the empty scene, one per camera (needed to segment images)",
    )
    src.add_argument("--segmentation", metavar="FILE", help="segmentation settings (TOML)")
    joints = p.add_argument_group("joint values")
    joints.add_argument(
        "--joints-port",
        type=int,
        metavar="PORT",
        help="UDP port of the joint datagrams (default 25000; not with --recording)",
    )
    joints.add_argument(
        "--joint-clock",
        choices=["aligned", "sender", "arrival"],
        default="aligned",
        help="time base of the joint samples (default aligned: the controller's sampling on"
        " this machine's clock; sender: its time stamps as they are)",
    )
    model = p.add_argument_group("model, rig and base")
    model.add_argument("--model", metavar="FILE", help="catheter model file (default model)")
    model.add_argument(
        "--rig", metavar="FILE", help="rig file (TOML, docs/vision.md), with the base in [base]"
    )
    model.add_argument(
        "--rig-model",
        choices=["pinhole", "orthographic"],
        default="pinhole",
        help="the rig's cameras (default) or the paper's orthographic planes (markers in mm)",
    )
    model.add_argument(
        "--base-origin-mm",
        nargs=3,
        type=float,
        metavar=("X", "Y", "Z"),
        help="registered base origin in the world frame (default: the rig's or recording's)",
    )
    model.add_argument(
        "--base-rotvec-deg",
        nargs=3,
        type=float,
        metavar=("RX", "RY", "RZ"),
        help="registered base orientation as a rotation vector, deg (default 0 0 0 with"
        " --base-origin-mm)",
    )
    p.add_argument(
        "--estimator", default="ukf", metavar="NAME", help="estimator (default ukf)"
    )
    out = p.add_argument_group("outputs")
    out.add_argument(
        "--estimate-to",
        default="127.0.0.1:25001",
        metavar="HOST:PORT",
        help="send the estimate datagrams here (default 127.0.0.1:25001; 'off': do not)",
    )
    out.add_argument(
        "--igtl-port",
        type=int,
        metavar="PORT",
        help="serve OpenIGTLink transforms for 3D Slicer on this port (e.g. 18944)",
    )
    out.add_argument(
        "--record", metavar="FILE", help="record the inputs and the estimates (MCAP)"
    )
    out.add_argument(
        "--bind",
        default="127.0.0.1",
        metavar="HOST",
        help="address of every listener (default 127.0.0.1; the lab network's interface to"
        " take datagrams from a real-time target)",
    )
    out.add_argument("--no-images", action="store_true", help="no images in rerun")
    out.add_argument(
        "--image-every",
        type=int,
        default=2,
        metavar="N",
        help="images of every N-th frame in rerun (default 2)",
    )
    add_rerun_args(p)
    run = p.add_argument_group("run")
    run.add_argument(
        "--idle-timeout",
        type=float,
        metavar="S",
        help="stop after S seconds without a frame (default: run until Ctrl-C)",
    )
    run.add_argument("--max-frames", type=int, metavar="N", help="stop after N frames")
    p.set_defaults(run=_run_track)


def _track_report(message: str) -> None:
    print(f"cathtrack track: {message}", file=sys.stderr, flush=True)


def _host_port(text: str, option: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"{option} must be HOST:PORT, e.g. 127.0.0.1:25001, got {text!r}")
    return host, int(port)


def _track_source_kind(args: argparse.Namespace) -> str:
    given = {
        "recording": args.recording is not None,
        "markers": args.markers_port is not None,
        "video": bool(args.video_front or args.video_side),
        "camera": bool(args.camera_front or args.camera_side),
    }
    kinds = [kind for kind, on in given.items() if on]
    if len(kinds) != 1:
        got = f" (got {', '.join(kinds)})" if kinds else ""
        raise ValueError(
            "give one source of frames: --camera-front/--camera-side, --video-front/"
            f"--video-side, --markers-port or --recording{got}"
        )
    kind = kinds[0]
    if kind in ("video", "camera") and not all(
        getattr(args, f"{kind}_{view}") for view in ("front", "side")
    ):
        raise ValueError(f"give both --{kind}-front and --{kind}-side")
    if kind == "recording" and args.joints_port is not None:
        raise ValueError("--joints-port does not apply to --recording (its joints are recorded)")
    if args.speed < 0:
        raise ValueError(f"--speed must be >= 0 (0: as fast as possible), got {args.speed}")
    return kind


def _track_base(args: argparse.Namespace, base):
    """The registered base pose: the options, else the rig file's [base] or the recording's."""
    import numpy as np

    if args.base_origin_mm is not None or args.base_rotvec_deg is not None:
        from scipy.spatial.transform import Rotation

        if args.base_origin_mm is None:
            raise ValueError("--base-rotvec-deg needs --base-origin-mm")
        rotvec = np.radians(args.base_rotvec_deg or (0.0, 0.0, 0.0))
        return Rotation.from_rotvec(rotvec).as_matrix(), np.asarray(args.base_origin_mm, float)
    if base is None:
        raise ValueError(
            "no registered base pose: give --base-origin-mm (and --base-rotvec-deg) or a rig"
            " file with a [base] table"
        )
    return base


def _read_rig(path: str, model: str):
    """The rig of a rig file and its [base] (R_w_b, o_b_w_mm), or None without one."""
    import numpy as np

    from models.rig_file import RigFileError, read_rig_file, rig_from_dict

    data = read_rig_file(path)
    rig = rig_from_dict(data, path, model)
    base = data.get("base")
    if base is None:
        return rig, None
    try:
        R_w_b = np.asarray(base["R_w_b"], float).reshape(3, 3)
        o_b_w_mm = np.asarray(base["o_b_w_mm"], float).reshape(3)
    except (KeyError, TypeError, ValueError):
        raise RigFileError(f"{path} [base]: needs R_w_b (3x3) and o_b_w_mm (3)") from None
    return rig, (R_w_b, o_b_w_mm)


def _run_track(args: argparse.Namespace) -> int:
    import contextlib
    import time
    from pathlib import Path

    from models.model_file import DEFAULT_MODEL_PATH, load_catheter
    from replay.simulation.simulator import Scene
    from tracker.estimators import make_estimator
    from tracker.io.udp import DEFAULT_JOINT_PORT, EstimateSender, JointReceiver
    from tracker.live.loop import LiveTracker
    from tracker.reconstruction import Reconstructor
    from tracker.viewer.sink import (
        LiveViewerSink,
        RerunSink,
        default_blueprint,
        open_rerun_output,
    )

    report = _track_report
    kind = _track_source_kind(args)
    if args.image_every < 1:
        raise ValueError(f"--image-every must be >= 1, got {args.image_every}")
    estimate_to = (
        None if args.estimate_to == "off" else _host_port(args.estimate_to, "--estimate-to")
    )
    inputs: list[str] = []
    with contextlib.ExitStack() as stack:  # closes what was opened if the set-up fails
        # ---- model, rig, base
        recording = None
        model_toml = None
        if kind == "recording":
            from tracker.io.recording import open_recording

            recording = open_recording(args.recording)
            stack.callback(recording.close)
            catheter = recording.catheter()
            model_toml = recording.metadata.model_toml
            rig, R_w_b, o_b_w_mm = recording.rig()
            base = (R_w_b, o_b_w_mm)
        else:
            if args.rig is None:
                raise ValueError("give the rig file (--rig FILE) of the cameras")
            base = None
        if args.model is not None:
            catheter = load_catheter(args.model)
            model_toml = Path(args.model).read_text(encoding="utf-8")
        elif recording is None:
            catheter = load_catheter(DEFAULT_MODEL_PATH)
            model_toml = DEFAULT_MODEL_PATH.read_text(encoding="utf-8")
        if args.rig is not None:
            rig, rig_base = _read_rig(args.rig, args.rig_model)
            base = rig_base or base
        R_w_b, o_b_w_mm = _track_base(args, base)
        scene = Scene(catheter, rig, R_w_b, o_b_w_mm)
        estimator = make_estimator(args.estimator, catheter)
        reconstructor = Reconstructor(catheter, rig, R_w_b, o_b_w_mm)

        # ---- outputs first (a port in use fails before anything listens)
        sinks: list = []
        igtl = None
        if estimate_to is not None:
            sender = EstimateSender(estimate_to, report=report)
            stack.callback(sender.close)
            sinks.append(sender)
        if args.igtl_port is not None:
            from tracker.io.igtl import IgtlSink

            igtl = IgtlSink(
                catheter, R_w_b, o_b_w_mm, host=args.bind, port=args.igtl_port, report=report
            )
            stack.callback(igtl.close)
            sinks.append(igtl)
        output = open_rerun_output(
            args,
            "cathtrack",
            blueprint=default_blueprint([args.estimator], rig.kind == "pinhole", live=True),
            bind=args.bind,
            report=report,
        )
        viewer_sink = None
        if output is not None:
            viewer = RerunSink(
                output.stream, primary=args.estimator, jpeg_quality=80, time_origin_s=None
            )
            stack.callback(viewer.close)
            viewer_sink = LiveViewerSink(
                viewer,
                scene,
                args.estimator,
                images=not args.no_images,
                image_every=args.image_every,
                watch=output.watch(),
                report=report,
            )
            stack.callback(viewer_sink.close)  # stops the viewer watch too
            sinks.append(viewer_sink)

        # ---- inputs
        joints = segmenter = None
        if kind != "recording":
            joints = JointReceiver(
                args.bind,
                DEFAULT_JOINT_PORT if args.joints_port is None else args.joints_port,
                clock=args.joint_clock,
            )
            stack.callback(joints.close)
            host, port = joints.address
            inputs.append(f"joints on udp://{host}:{port} ({args.joint_clock} clock)")
        if kind == "recording":
            from tracker.live.sources import RecordingSource

            want_images = viewer_sink is not None and not args.no_images
            source = RecordingSource(recording, speed=args.speed or None, images=want_images)
            pace = "full speed" if not args.speed else f"{args.speed:g}x real time"
            inputs.append(f"recording {args.recording} at {pace}")
        elif kind == "markers":
            from tracker.io.udp import MarkerReceiver
            from tracker.live.sources import UdpMarkerSource

            receiver = MarkerReceiver(
                args.bind, args.markers_port, n_points=1 + len(catheter.marker_arclengths_mm)
            )
            stack.callback(receiver.close)
            source = UdpMarkerSource(receiver)
            host, port = receiver.address
            inputs.append(f"markers on udp://{host}:{port}")
        else:
            from tracker.live.sources import VideoSource
            from tracker.vision.segmentation import (
                PairSegmenter,
                SegmentationSettings,
                load_segmentation_settings,
                read_grayscale,
            )

            if args.backgrounds is None:
                raise ValueError(
                    "segmenting images needs the empty scene: --backgrounds FRONT SIDE"
                )
            backgrounds = tuple(read_grayscale(path) for path in args.backgrounds)
            settings = (
                load_segmentation_settings(args.segmentation)
                if args.segmentation
                else SegmentationSettings()
            )
            segmenter = PairSegmenter(catheter, rig, R_w_b, o_b_w_mm, backgrounds, settings)
            specs = (
                (args.video_front, args.video_side)
                if kind == "video"
                else (args.camera_front, args.camera_side)
            )
            source = VideoSource(*specs, realtime=kind == "video")
            stack.callback(source.close)
            inputs.append(f"{kind}s {specs[0]} and {specs[1]}")

        if args.record is not None:
            from tracker.io.recording import VIEWS, RecordingWriter, rig_toml
            from tracker.live.loop import RecordingSink

            writer = RecordingWriter(
                args.record,
                model_toml=model_toml,
                rig_toml=rig_toml(rig, R_w_b, o_b_w_mm),
                settings={"command": "track", "source": kind, "estimator": args.estimator},
                point_unit="px" if rig.kind == "pinhole" else "mm",
                # Live time stamps are monotonic seconds: log times become wall-clock time.
                start_time_ns=0 if kind == "recording" else time.time_ns() - time.monotonic_ns(),
            )
            stack.callback(writer.close)
            if segmenter is not None:
                for view, background in zip(VIEWS, segmenter.backgrounds, strict=True):
                    writer.write_background(view, background)
            sinks.append(RecordingSink(writer, args.estimator, joints=joints))

        tracker = LiveTracker(
            reconstructor, estimator, sinks, joints=joints, segmenter=segmenter, report=report
        )
        if viewer_sink is not None:
            viewer_sink.summary = tracker.summary
        stack.pop_all()  # from here the loop closes every sink, the receiver and the source

    outputs = []
    if estimate_to is not None:
        outputs.append(f"estimates to udp://{estimate_to[0]}:{estimate_to[1]}")
    if igtl is not None:
        outputs.append(f"OpenIGTLink on tcp://{igtl.host}:{igtl.port}")
    if args.record is not None:
        outputs.append(f"recording {args.record}")
    if output is not None:
        outputs.extend(f"rerun {target}" for target in output.targets)
    print(f"cathtrack track: {args.estimator} on {'; '.join(inputs)}", flush=True)
    print(f"cathtrack track: out to {'; '.join(outputs) or 'nowhere'}; Ctrl-C to stop", flush=True)
    try:
        summary = tracker.run(source, idle_timeout_s=args.idle_timeout, max_frames=args.max_frames)
    except KeyboardInterrupt:  # Ctrl-C before the loop took it over: close all the same
        tracker.close(source)
        summary = tracker.summary
        summary.stop_reason = "interrupted"
    print(summary, flush=True)
    return 130 if summary.interrupted else 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "run", None) is None:
        parser.print_help()
        return 0
    try:
        return int(args.run(args) or 0)
    except (ValueError, OSError) as exc:
        print(f"cathtrack {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"cathtrack {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
