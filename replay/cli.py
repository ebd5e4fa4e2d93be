"""The ``cathtrack`` command line: one entry point, one subcommand per job.

``main(argv)`` only wires things together so tests can call it: this module holds the parser
and each command's ``run(args)`` is in :mod:`replay.commands`. Errors a user can cause end in
one clear line on stderr and exit code 2, not a traceback; Ctrl-C, at any moment, in one line
and exit code 130.

This module imports only what builds the parser quickly; rerun (and every command's libraries)
load inside ``main``'s error handling, so a Ctrl-C while they load is handled too.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Callable
from importlib import import_module

from replay.setup_commands import add_fit_model_parser, add_import_parser, add_register_parser

DEMO_RRD = "out/demo.rrd"
EXIT_ERROR = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports a process that Ctrl-C ended


def add_rerun_args(parser: argparse.ArgumentParser, **kwargs) -> None:
    """:func:`tracker.viewer.output.add_rerun_args`, imported when the parser is built: that
    imports rerun (about 0.3 s), which must happen inside ``main``'s handling of Ctrl-C."""
    import_module("tracker.viewer.output").add_rerun_args(parser, **kwargs)


def _command(name: str) -> Callable[[argparse.Namespace], int]:
    """The ``run(args)`` of :mod:`replay.commands.<name>`, imported when the command runs:
    importing every command's module up front (the studies, the evaluation, the live loop and
    their libraries) would add about 0.7 s to the start of each command."""

    def run(args: argparse.Namespace) -> int:
        return import_module(f"replay.commands.{name}").run(args)

    return run


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cathtrack",
        description=(
            "Estimate the torsional loss delta_L and the bending plane of a two-segment "
            "steerable catheter from joint values and bi-plane images."
        ),
    )
    version = import_module("tracker").__version__  # importlib.metadata: 17 ms, inside main
    parser.add_argument("--version", action="version", version=f"cathtrack {version}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

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
    demo.add_argument(
        "--image-noise-gray",
        type=float,
        default=2.0,
        metavar="GRAY",
        help="sensor noise of the rendered images, gray levels (default 2)",
    )
    demo.add_argument(
        "--no-keep-awake",
        action="store_true",
        help="let the processors sleep deeply between frames (default: kept awake while the"
        " loop runs, where permitted; docs/live.md)",
    )
    demo.add_argument(
        "--no-segmentation-worker",
        action="store_true",
        help="segment every view in the loop's process (default: the views after the first"
        " in a worker process, at the same time, with two processors or more; docs/live.md)",
    )
    demo.add_argument(
        "--no-realtime",
        action="store_true",
        help="leave each frame's work at the ordinary priority (default: a real-time"
        " priority, SCHED_FIFO, where permitted; docs/live.md)",
    )
    _add_nuisance(demo)
    add_rerun_args(demo, save_default=DEMO_RRD, bind_option=True)
    demo.set_defaults(run=_command("demo"))
    _add_track(sub)
    _add_sensitivity(sub)
    _add_calibrate(sub)
    _add_simulate(sub)
    _add_evaluate(sub)
    add_fit_model_parser(sub)
    add_register_parser(sub)
    add_import_parser(sub)
    _add_view(sub)
    return parser


def _add_nuisance(p) -> None:
    """What the simulated cameras change between the background and each frame
    (:class:`replay.simulation.render.ImagingNuisance`; read by
    :func:`replay.commands.nuisance.nuisance_from_args`)."""
    g = p.add_argument_group(
        "imaging nuisances (each frame differs from the background image; default none)"
    )
    g.add_argument(
        "--gain-flicker", type=float, default=0.0, metavar="F",
        help="each frame's gain varies within 1 +/- F (0.15: 0.85 to 1.15)",
    )
    g.add_argument(
        "--gain-drift", type=float, default=0.0, metavar="F",
        help="standard deviation of a slow drift of the gain (a lamp, automatic brightness)",
    )
    g.add_argument(
        "--offset-gray", type=float, default=0.0, metavar="GRAY",
        help="each frame's offset (dark level) varies within +/- GRAY gray levels",
    )
    g.add_argument(
        "--gamma-range", type=float, default=0.0, metavar="R",
        help="each frame's gamma varies within 1 +/- R",
    )
    g.add_argument(
        "--vibration-px", type=float, default=0.0, metavar="PX",
        help="standard deviation of each frame's shift of the whole image, px",
    )
    g.add_argument(
        "--camera-shift-px", type=float, nargs=2, default=(0.0, 0.0), metavar=("DX", "DY"),
        help="the cameras moved by this since their backgrounds were taken, px",
    )


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
    p.set_defaults(run=_command("sensitivity"))


def _add_calibrate(sub) -> None:
    p = sub.add_parser(
        "calibrate",
        help="calibrate the cameras and write a rig file from checkerboard images",
        description=(
            "Calibrate each camera by Zhang's method from images of a checkerboard, then the "
            "pose of every camera relative to the first from the images where both saw the "
            "board; the board of the first image seen by every camera defines the world frame. "
            "Images are matched across the folders by sorted file name. Writes a rig file "
            "(TOML, docs/vision.md) and prints the per-view and total reprojection errors in px."
        ),
    )
    p.add_argument(
        "--view",
        action="append",
        metavar="NAME=DIR",
        help="a camera's name and folder of board images, once per camera in the rig's order"
        " (the bi-plane rig: --view front=DIR --view side=DIR)",
    )
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
    p.set_defaults(run=_command("calibrate"))


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
            "segmented markers with realistic noise, --no-images). Options add what a lab "
            "meets: contact deviations of the joints, a model error, wrong and missing markers, "
            "torsion wind-up with play. Seeded: the same options give the same recording "
            "whatever the number of workers."
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
    _add_nuisance(p)
    _add_lab_conditions(p)
    p.add_argument("--workers", type=int, help="processes rendering the images (default: all CPUs)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(run=_command("simulate"))


def _add_lab_conditions(p) -> None:
    """What a lab meets beyond segmentation noise
    (:class:`replay.simulation.simulator.LabConditions`; read by
    :func:`replay.commands.simulate.lab_conditions_from_args`)."""
    g = p.add_argument_group("what a lab meets (default none)")
    g.add_argument(
        "--contact-joint-std-mm", type=float, default=0.0, metavar="MM",
        help="contact deviation: per configuration the true q_p and q_d are off by normal"
        " deviations of this std, mm (on top of the deflection levels)",
    )
    g.add_argument(
        "--model-scale-error", type=float, default=0.0, metavar="X",
        help="model error: the true catheter bends 1 + X times as much as the model's modal"
        " matrices say (relative; 0.05: 5 %%); the recording keeps the model",
    )
    g.add_argument(
        "--outlier-rate", type=float, default=0.0, metavar="P",
        help="markers only: probability that a segmented point in one view is a gross error",
    )
    g.add_argument(
        "--outlier-size-mm", type=float, default=None, metavar="MM",
        help="size of such an error, mm in the image plane at the isocentre (default 10)",
    )
    g.add_argument(
        "--dropout-rate", type=float, default=0.0, metavar="P",
        help="markers only: probability that a point is missing in one view",
    )
    g.add_argument(
        "--windup-play-deg", type=float, default=0.0, metavar="DEG",
        help="torsion wind-up: the tip follows the base's turns only beyond this play, deg",
    )


def _add_evaluate(sub) -> None:
    p = sub.add_parser(
        "evaluate",
        help="replay recordings through the estimators and report the paper's tables",
        description=(
            "Replay each recording (MCAP, docs/recording.md) through the chosen estimators, "
            "with the joint values interpolated to the frame times, and report per method the "
            "RMS and maximum bending-plane error (degrees) over all configurations, per bending "
            "plane, against tip deflection and against segmentation noise, next to the "
            "Cramer-Rao bound; per method the 2-sigma coverage, the mean NEES and the "
            "configurations where it is confidently wrong (error above 30 deg, std below 10); "
            "for the filters also NEES consistency and NIS. Writes "
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
        "--rrd-frame-every",
        type=int,
        default=4,
        metavar="N",
        help="without images: markers and 3-D scene every N frames (4)",
    )
    p.add_argument(
        "--rrd-image-every",
        type=int,
        default=20,
        metavar="N",
        help="with images: images, markers and 3-D scene every N frames (20)",
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
    p.set_defaults(run=_command("evaluate"))


def _add_view(sub) -> None:
    p = sub.add_parser(
        "view",
        help="show a recording (MCAP) in rerun with the project's layout",
        description=(
            "Log a recording to rerun with the project's blueprint: the joint values, the "
            "segmented markers, the truth, the images, the estimates recorded live (as "
            "recorded-<method>) and, with --methods, estimators run on it now; on the "
            "session's time (s since its start), named after the file. Without --save, "
            "--connect or --serve it starts a viewer (--spawn)."
        ),
    )
    p.add_argument("recording", metavar="RECORDING", help="recording file (MCAP)")
    p.add_argument(
        "--methods",
        nargs="+",
        metavar="NAME",
        help="also run these estimators on it (default: none, the recorded estimates only)",
    )
    p.add_argument(
        "--source",
        choices=["auto", "markers", "images"],
        default="auto",
        help="markers of those estimators: recorded, or segmented from the images (auto:"
        " images if present)",
    )
    p.add_argument(
        "--frame-every",
        type=int,
        default=1,
        metavar="N",
        help="images, markers and 3-D scene every N frames (1; the series have every frame)",
    )
    p.add_argument("--no-images", action="store_true", help="no images")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_rerun_args(p, bind_option=True)
    p.set_defaults(run=_command("view"))

    p = sub.add_parser(
        "compile",
        help="compile the numba kernels now (make does it after installing)",
        description=(
            "Compile every numba kernel (segmentation, filters, model) now, one process per"
            " processor, and cache them on disk: otherwise the first demo, replay or track on"
            " a machine compiles them as it goes (about a minute and a half on one core)."
            " Kernels already cached are only loaded."
        ),
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=None,
        metavar="N",
        help="processes at a time (default: one per processor)",
    )
    p.set_defaults(run=_command("compile"))


# ------------------------------------------------------------------------------ track
def _add_track(sub) -> None:
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
    src.add_argument(
        "--camera",
        action="append",
        metavar="INDEX",
        help="a camera (OpenCV index): give one per view of the rig, in its order (front, side)",
    )
    src.add_argument(
        "--video",
        action="append",
        metavar="FILE",
        help="a video file: give one per view of the rig, in its order (front, side)",
    )
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
        nargs="+",
        metavar="IMAGE",
        help="images of the empty scene, one per view in the rig's order (needed to segment"
        " images)",
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
    out.add_argument(
        "--csv", metavar="FILE", help="one CSV row per frame: estimate, joints, status, latency"
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
    run.add_argument(
        "--no-pin",
        action="store_true",
        help="leave the loop's thread to the scheduler (default: on a processor of its own,"
        " the other threads off it, with two processors or more; docs/live.md)",
    )
    run.add_argument(
        "--no-keep-awake",
        action="store_true",
        help="let the processors sleep deeply between frames (default: kept awake through"
        " /dev/cpu_dma_latency while the loop runs, where permitted; docs/live.md)",
    )
    run.add_argument(
        "--no-segmentation-worker",
        action="store_true",
        help="segment every view in the loop's process (default: the views after the first"
        " in a worker process, at the same time, with two processors or more; docs/live.md)",
    )
    run.add_argument(
        "--no-realtime",
        action="store_true",
        help="leave each frame's work at the ordinary priority (default: a real-time"
        " priority, SCHED_FIFO, where permitted; docs/live.md)",
    )
    p.set_defaults(run=_command("track"))


class _FirstInterrupt:
    """A SIGINT handler that raises KeyboardInterrupt once and ignores every later Ctrl-C, so
    that a second one cannot cut short the closing of files after the first."""

    def __init__(self) -> None:
        self.seen = False

    def __call__(self, signum, frame) -> None:
        if not self.seen:
            self.seen = True
            raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    """Run one command line; returns the exit code (0, 2 for an error a user can cause, 130
    when interrupted).

    Ctrl-C at any moment -- while the parser is built and the libraries load, during the
    command, twice -- ends in one line on stderr and exit code 130: the first interrupts (a
    command such as ``track`` may take it over to stop cleanly), later ones are ignored while
    the command closes its files.
    """
    name = "cathtrack"
    interrupts = _FirstInterrupt()
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGINT, interrupts)
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if getattr(args, "run", None) is None:
            parser.print_help()
            return 0
        name = f"cathtrack {args.command}"
        return int(args.run(args) or 0)
    except (ValueError, OSError) as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        interrupts.seen = True  # raised by a command's own handler: ignore the next ones too
        if previous is not None:
            # The process is about to exit: later Ctrl-Cs stay ignored until it has. SIG_IGN,
            # not a Python handler: the interpreter's shutdown restores the default action of
            # its own handlers, and a Ctrl-C then (rerun flushing at exit) would kill it.
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        print(f"{name}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        if previous is not None and not interrupts.seen:
            signal.signal(signal.SIGINT, previous)


if __name__ == "__main__":
    sys.exit(main())
