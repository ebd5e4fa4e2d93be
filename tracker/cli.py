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

    demo = sub.add_parser(
        "demo",
        help="simulate a bi-plane session and track it with every estimator",
        description=(
            "Simulate a session of the default catheter under two orthogonal imaging planes "
            "(1 mm segmentation noise, torsion wind-up while the base turns) and print the "
            "accuracy of every estimator next to the Cramer-Rao bound, in degrees."
        ),
    )
    demo.add_argument("--frames", type=int, default=400, help="number of frames (default 400)")
    demo.add_argument("--noise-mm", type=float, default=1.0, help="segmentation noise sigma, mm")
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument("--delta-2-deg", type=float, default=0.0, help="distal plane angle, deg")
    demo.set_defaults(run=_run_demo)
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
        "--ukf-trials", type=int, help="of those, how many the UKF steps through (50)"
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
    from tracker.rig_calibration import (
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
    from tracker.demo import run_demo

    return run_demo(
        frames=args.frames, noise_mm=args.noise_mm, seed=args.seed, delta_2_deg=args.delta_2_deg
    )


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
