"""``cathtrack view``: a recording (MCAP) in rerun with the project's blueprint.

rerun opens an MCAP file by itself, but shows only its images (its loader skips the JSON
channels), on a timeline of 1970 dates, as a recording named ``<unknown>``. This command logs
what the recording holds -- the joint values, the segmented markers, the truth, the images, the
estimates recorded live (as ``recorded-<method>``) and, with ``--methods``, estimators run on
it now -- through the same sink and blueprint as ``cathtrack evaluate`` and the live loop, on
the session's own time (s since its start), named after the file.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from replay.evaluation.outputs import log_replay, primary_method
from replay.evaluation.run import Replay, replay_recording
from tracker.io.recording import Recording, open_recording
from tracker.types import Estimate, Flag
from tracker.viewer.layout import RECORDED_PREFIX, default_blueprint
from tracker.viewer.output import open_rerun_output, serve_until_interrupted
from tracker.viewer.sink import RerunSink

MAX_JOINT_SAMPLES = 50_000  # per joint: thins a long 1 kHz stream for the plot


def _report(message: str) -> None:
    print(f"cathtrack view: {message}", file=sys.stderr, flush=True)


def recorded_estimates(recording: Recording, frame_times_s: np.ndarray) -> dict[str, list]:
    """The recording's estimates per method, one per frame (an invalid estimate where the
    method recorded none at that frame's time), named ``recorded-<method>``."""
    times = np.asarray(frame_times_s, dtype=float)
    out = {}
    for name, recorded in recording.estimates.items():
        per_frame: list[Estimate | None] = [None] * times.size
        for item in recorded:
            estimate = item.estimate
            k = int(np.searchsorted(times, estimate.time_s))
            for j in (k - 1, k):  # the frame at that time (to within a microsecond)
                if 0 <= j < times.size and abs(times[j] - estimate.time_s) < 1e-6:
                    per_frame[j] = estimate
        out[f"{RECORDED_PREFIX}{name}"] = [
            e
            if e is not None
            else Estimate(float(t), math.nan, math.nan, math.nan, Flag.NO_MEASUREMENT)
            for e, t in zip(per_frame, times, strict=True)
        ]
    return out


def _scene_frames(replay: Replay, recording: Recording, every: int, images: bool):
    """(index, frame) of every ``every``-th frame, with its images read again from the
    recording one at a time (the replay keeps none in memory)."""
    chosen = set(range(0, len(replay.frames), max(1, every)))
    if not (images and recording.has_images):
        for i in sorted(chosen):
            yield i, replay.frames[i].frame
        return
    for i, recorded in enumerate(recording.frames(images=lambda i: i in chosen)):
        if i in chosen:
            frame = replay.frames[i].frame
            if recorded.frame.images is not None:
                frame = dataclasses.replace(frame, images=recorded.frame.images)
            yield i, frame


def view_recording(
    path: str | Path,
    rerun_args: argparse.Namespace,
    methods: Sequence[str] = (),
    source: str = "auto",
    frame_every: int = 1,
    images: bool = True,
    progress: bool = False,
    out=print,
) -> int:
    """Log a recording to the rerun outputs of ``rerun_args``; returns the exit code.

    Parameters
    ----------
    path : str or Path
    rerun_args : argparse.Namespace
        The flags of :func:`tracker.viewer.output.add_rerun_args`.
    methods : sequence of str
        Estimators to run on the recording (:func:`replay_recording`), next to the
        recorded estimates.
    source : {"auto", "markers", "images"}
        Where the markers of those estimators come from.
    frame_every : int
        The scene (images, markers, 3-D) every n-th frame; the series have every frame.
    images : bool
        Log the images.
    """
    if not methods and source == "auto":
        source = "markers"  # nothing to run: show the markers as recorded, segment nothing
    with open_recording(path) as recording:
        replay = replay_recording(recording, list(methods), source, progress)
        estimates = {name: result.estimates for name, result in replay.results.items()}
        estimates.update(recorded_estimates(recording, recording.frame_times_s()))
        if not estimates:
            _report("the recording holds no estimates: give --methods to run some")
        primary = primary_method(list(estimates))
        output = open_rerun_output(
            rerun_args,
            blueprint=default_blueprint(
                list(estimates), scene=replay.scene, primary=primary, joints=True
            ),
            recording_name=Path(path).name,
            start_time_ns=recording.metadata.start_time_ns or None,
            report=_report,
        )
        if output is None:
            raise ValueError("nowhere to show it: give --save FILE, --connect, --spawn or --serve")
        out(f"cathtrack view: {Path(path).name} to {'; '.join(output.targets)}")
        sink = RerunSink(output.stream, primary=primary, jpeg_quality=85)
        try:
            joints = recording.joints
            step = max(1, joints.time_s.size // MAX_JOINT_SAMPLES)
            sink.log_joints(joints.time_s[::step], joints.q[::step])
            frames = _scene_frames(replay, recording, frame_every, images)
            log_replay(sink, replay, frames, estimates)
            if output.served_url is not None:
                sink.stream.flush()
                serve_until_interrupted(output, out)
        finally:
            sink.close()
            output.close()
    return 0


def run(args: argparse.Namespace) -> int:
    if not any(getattr(args, flag, None) for flag in ("save", "connect", "url", "serve")):
        args.spawn = True  # like `rerun FILE`: a viewer of its own
    return view_recording(
        args.recording,
        args,
        methods=args.methods or (),
        source=args.source,
        frame_every=args.frame_every,
        images=not args.no_images,
        progress=not args.no_progress,
    )
