"""``cathtrack track``: the live loop from options (docs/live.md).

The model, the rig and the registered base pose come from files (or a recording); the frames
from exactly one source: one camera or video file per view (segmented here), markers segmented
elsewhere over UDP, or a recording played back. :class:`tracker.live.session.LiveSession`
wires the rest: the joint receiver and the outputs.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Iterable
from pathlib import Path

from models.catheter import Catheter
from models.imaging import Rig
from models.model_file import DEFAULT_MODEL_PATH, load_catheter
from replay.compile_ahead import SlowSetUpNotice
from replay.simulation.simulator import Scene
from tracker.io.recording import Recording, open_recording
from tracker.io.udp import DEFAULT_JOINT_PORT, MarkerReceiver
from tracker.live.session import LiveSession, SessionSettings
from tracker.live.sources import RecordingSource, UdpMarkerSource, VideoSource
from tracker.vision.pair import PairSegmenter
from tracker.vision.parallel import ParallelPairSegmenter, pair_segmenter
from tracker.vision.settings import (
    SegmentationSettings,
    load_segmentation_settings,
    read_grayscale,
)


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
        "video": bool(args.video),
        "camera": bool(args.camera),
    }
    kinds = [kind for kind, on in given.items() if on]
    if len(kinds) != 1:
        got = f" (got {', '.join(kinds)})" if kinds else ""
        raise ValueError(
            "give one source of frames: --camera (one per view), --video (one per view),"
            f" --markers-port or --recording{got}"
        )
    kind = kinds[0]
    if kind in ("video", "camera") and len(getattr(args, kind)) < 2:
        raise ValueError(f"give one --{kind} per view of the rig (two or more, in its order)")
    if kind == "recording" and args.joints_port is not None:
        raise ValueError("--joints-port does not apply to --recording (its joints are recorded)")
    if args.speed < 0:
        raise ValueError(f"--speed must be >= 0 (0: as fast as possible), got {args.speed}")
    return kind


def _track_base(args: argparse.Namespace, base):
    """The registered base pose (a models.pose.Pose): the options, else the rig file's
    [base] or the recording's."""
    import numpy as np

    from models.pose import Pose

    if args.base_origin_mm is not None or args.base_rotvec_deg is not None:
        from scipy.spatial.transform import Rotation

        if args.base_origin_mm is None:
            raise ValueError("--base-rotvec-deg needs --base-origin-mm")
        rotvec = np.radians(args.base_rotvec_deg or (0.0, 0.0, 0.0))
        return Pose(Rotation.from_rotvec(rotvec).as_matrix(), np.asarray(args.base_origin_mm))
    if base is None:
        raise ValueError(
            "no registered base pose: give --base-origin-mm (and --base-rotvec-deg) or a rig"
            " file with a [base] table"
        )
    return base


def _read_rig(path: str, model: str):
    """The rig of a rig file and its [base] pose (models.pose.Pose), or None without one."""
    from models.rig_file import base_from_dict, read_rig_file, rig_from_dict

    data = read_rig_file(path)
    return rig_from_dict(data, path, model), base_from_dict(data, path)


def _session_settings(args: argparse.Namespace, kind: str) -> SessionSettings:
    estimate_to = (
        None if args.estimate_to == "off" else _host_port(args.estimate_to, "--estimate-to")
    )
    if kind == "recording":
        joints_port = None  # the recording's joints come with its frames
    else:
        joints_port = DEFAULT_JOINT_PORT if args.joints_port is None else args.joints_port
    return SessionSettings(
        estimator=args.estimator,
        bind=args.bind,
        joints_port=joints_port,
        joint_clock=args.joint_clock,
        estimate_to=estimate_to,
        igtl_port=args.igtl_port,
        record_path=args.record,
        csv_path=args.csv,
        live_clock=kind != "recording",
        queued=not (kind == "recording" and not args.speed),  # as fast as possible: inline
        images=not args.no_images,
        image_every=args.image_every,
        pin=not args.no_pin,
        keep_awake=not args.no_keep_awake,
        realtime=not args.no_realtime,
    )


def _scene(args: argparse.Namespace, recording: Recording | None) -> tuple[Scene, str]:
    """The catheter, rig and base pose of the session, and the model file's text."""
    model_toml = None
    if recording is not None:
        catheter = recording.catheter()
        model_toml = recording.metadata.model_toml
        rig, base = recording.rig()
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
    base = _track_base(args, base)
    return Scene(catheter, rig, base.R_w_b, base.o_b_w_mm), model_toml


def _segmenter(args: argparse.Namespace, scene: Scene) -> PairSegmenter | ParallelPairSegmenter:
    names = scene.rig.names
    if args.backgrounds is None or len(args.backgrounds) != len(names):
        raise ValueError(
            "segmenting images needs one image of the empty scene per view:"
            f" --backgrounds {' '.join(n.upper() for n in names)}"
        )
    backgrounds = tuple(read_grayscale(path) for path in args.backgrounds)
    settings = (
        load_segmentation_settings(args.segmentation)
        if args.segmentation
        else SegmentationSettings()
    )
    return pair_segmenter(
        scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, backgrounds, settings,
        parallel=False if args.no_segmentation_worker else None, report=_track_report,
        realtime=not args.no_realtime,
    )


def _open_source(
    args: argparse.Namespace,
    kind: str,
    catheter: Catheter,
    rig: Rig,
    recording: Recording | None,
    images: bool,
) -> tuple[Iterable, str]:
    """The source of frames, and what it is for the user."""
    if kind == "recording":
        source = RecordingSource(recording, speed=args.speed or None, images=images)
        pace = "full speed" if not args.speed else f"{args.speed:g}x real time"
        return source, f"recording {args.recording} at {pace}"
    if kind == "markers":
        receiver = MarkerReceiver(
            args.bind,
            args.markers_port,
            n_points=1 + len(catheter.marker_arclengths_mm),
            n_views=rig.n_views,
        )
        host, port = receiver.address
        return UdpMarkerSource(receiver), f"markers on udp://{host}:{port}"
    specs = args.video if kind == "video" else args.camera
    if len(specs) != rig.n_views:
        raise ValueError(
            f"the rig has {rig.n_views} views ({', '.join(rig.names)}): give one --{kind} for"
            f" each, got {len(specs)}"
        )
    described = ", ".join(f"{n} {s}" for n, s in zip(rig.names, specs, strict=True))
    source = VideoSource(specs, rig.names, realtime=kind == "video")
    return source, f"{kind}s {described}"


def run(args: argparse.Namespace) -> int:
    kind = _track_source_kind(args)
    settings = _session_settings(args, kind)
    with contextlib.ExitStack() as worker:  # the segmentation's worker process, at the end
        return _run(args, kind, settings, worker)


def _run(args: argparse.Namespace, kind: str, settings, worker: contextlib.ExitStack) -> int:
    with contextlib.ExitStack() as stack:  # closes what was opened if the set-up fails
        recording = None
        if kind == "recording":
            recording = open_recording(args.recording)
            stack.callback(recording.close)
            for warning in recording.report.warnings:  # what was lost, as evaluate reports it
                _track_report(f"{args.recording}: warning: {warning}")
        scene, model_toml = _scene(args, recording)
        with SlowSetUpNotice(_track_report).during():  # the kernels, compiled if not cached
            segmenter = _segmenter(args, scene) if kind in ("video", "camera") else None
            if segmenter is not None:
                worker.callback(segmenter.close)
            session = LiveSession(
                settings,
                scene,
                rerun_args=args,
                segmenter=segmenter,
                model_toml=model_toml,
                record_metadata={
                    "command": "track", "source": kind, "estimator": args.estimator,
                },
                report=_track_report,
            )  # fmt: skip
        stack.callback(session.close)
        images = session.viewer is not None and not args.no_images
        source, source_text = _open_source(
            args, kind, scene.catheter, scene.rig, recording, images
        )
        stack.pop_all()  # from here the session closes the source (and with it the recording)

    def announce() -> None:
        inputs = "; ".join([*session.inputs, source_text])
        print(f"cathtrack track: {args.estimator} on {inputs}", flush=True)
        outputs = "; ".join(session.outputs) or "nowhere"
        print(f"cathtrack track: out to {outputs}; Ctrl-C to stop", flush=True)

    with session:
        summary = session.run(
            source, idle_timeout_s=args.idle_timeout, max_frames=args.max_frames, announce=announce
        )
    print(summary, flush=True)
    return 130 if summary.interrupted else 0
