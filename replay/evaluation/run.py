"""Running estimators over observations, and replaying a recording through the pipeline.

:func:`replay_recording` replays a recording (tracker.io.recording) through the same pipeline
as the live loop -- frames, optional segmentation of the recorded images, reconstruction
(:meth:`tracker.reconstruction.Reconstructor.observe_batch`), every estimator -- and returns a
:class:`Replay`: the frames, the observations, each method's :class:`MethodResult` and the
per-frame Cramer-Rao bound of the tip.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from tqdm import tqdm

from models.bounds import crb_tip
from models.catheter import Catheter
from models.rotations import wrap_angle
from replay.parallel import execute, single_blas_thread
from replay.simulation.simulator import Scene
from tracker.estimators import estimator_names, make_estimator
from tracker.io.recording import (
    MarkerQuality,
    ReadReport,
    RecordedFrame,
    Recording,
    RecordingError,
)
from tracker.reconstruction import Reconstructor
from tracker.types import Estimate, Flag, Observation
from tracker.vision.pair import PairSegmenter
from tracker.vision.settings import SegmentationSettings, segmentation_settings_from_dict

Array = np.ndarray

METHOD_ORDER = (
    "tip-position",
    "body-positions",
    "tip-velocity",
    "tip-position-lsq",
    "body-positions-lsq",
    "tip-velocity-lsq",
    "ukf",
    "ukf-position",
)
"""The paper's table order; other estimators follow."""
SOURCES = ("auto", "markers", "images")


@dataclass(frozen=True, eq=False)
class MethodResult:
    """One estimator's estimates over a session and their errors against the truth.

    The per-frame arrays are made once, here, so that tables index them per group.

    Parameters
    ----------
    name : str
        The estimator's name.
    estimates : tuple of Estimate
        One per frame.
    truth_rad : array, shape (T,)
        True delta_L per frame, rad (NaN where unknown).

    Attributes
    ----------
    delta_L_rad, std_rad : arrays, shape (T,)
        Estimates and their standard deviations, rad (NaN where invalid).
    valid : array of bool, shape (T,)
        The step gave an estimate (:attr:`tracker.types.Estimate.valid`).
    errors_rad : array, shape (T,)
        Wrapped estimate - truth for valid frames (NaN elsewhere), rad.
    flags : array of int, shape (T,)
        :class:`tracker.types.Flag` values.
    nis : array, shape (T,)
        Normalised innovation squared where the step reported one, NaN elsewhere.
    nis_dof : array of int, shape (T,)
        Its degrees of freedom.
    reports_nis : bool
        Whether any step reported a NIS (a filter), i.e. whether consistency applies.
    """

    name: str
    estimates: tuple[Estimate, ...]
    truth_rad: Array
    delta_L_rad: Array = field(init=False, repr=False)
    std_rad: Array = field(init=False, repr=False)
    valid: Array = field(init=False, repr=False)
    errors_rad: Array = field(init=False, repr=False)
    flags: Array = field(init=False, repr=False)
    nis: Array = field(init=False, repr=False)
    nis_dof: Array = field(init=False, repr=False)
    reports_nis: bool = field(init=False, repr=False)

    def __post_init__(self) -> None:
        estimates = tuple(self.estimates)
        n = len(estimates)
        truth = np.array(self.truth_rad, dtype=float)  # a copy: made read-only below
        delta = np.fromiter((e.delta_L_rad for e in estimates), float, n)
        std = np.fromiter((e.std_rad for e in estimates), float, n)
        valid = np.isfinite(delta) & np.isfinite(std)
        nis = np.fromiter((np.nan if e.nis is None else e.nis for e in estimates), float, n)
        values = dict(
            estimates=estimates,
            truth_rad=truth,
            delta_L_rad=delta,
            std_rad=std,
            valid=valid,
            errors_rad=np.where(valid, wrap_angle(np.nan_to_num(delta) - truth), np.nan),
            flags=np.fromiter((e.flags.value for e in estimates), np.int64, n),
            nis=nis,
            nis_dof=np.fromiter((e.nis_dof for e in estimates), np.int64, n),
            reports_nis=any(e.nis is not None for e in estimates),
        )
        for name, value in values.items():
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
            object.__setattr__(self, name, value)

    def summary(self) -> dict[str, float]:
        """RMS, median absolute and maximum error in degrees; valid fraction; 2-sigma coverage."""
        err = self.errors_rad[self.valid]
        if err.size == 0:
            return {
                "rms_deg": np.inf,
                "median_deg": np.inf,
                "max_deg": np.inf,
                "valid": 0.0,
                "coverage_2sigma": 0.0,
                "rejected": 0,
            }
        std = self.std_rad[self.valid]
        return {
            "rms_deg": float(np.degrees(np.sqrt(np.mean(err**2)))),
            "median_deg": float(np.degrees(np.median(np.abs(err)))),
            "max_deg": float(np.degrees(np.max(np.abs(err)))),
            "valid": float(np.mean(self.valid)),
            "coverage_2sigma": float(np.mean(np.abs(err) <= 2 * std)),
            "rejected": int(np.count_nonzero(self.flags & Flag.OUTLIER_REJECTED.value)),
        }


def run_methods(
    catheter: Catheter,
    observations: Sequence[Observation],
    truth_rad: Array,
    names: Sequence[str],
) -> dict[str, MethodResult]:
    """Run every named estimator over the same observations."""
    results = {}
    for name in names:
        estimator = make_estimator(name, catheter)
        estimates = tuple(estimator.run(observations))
        results[name] = MethodResult(name, estimates, np.asarray(truth_rad, dtype=float))
    return results


def default_methods() -> list[str]:
    """Every estimator, in the order of the paper's table, then the others."""
    names = estimator_names()
    return [m for m in METHOD_ORDER if m in names] + [m for m in names if m not in METHOD_ORDER]


def recording_scene(recording: Recording) -> Scene:
    """The catheter, rig and registered base pose stored in a recording."""
    catheter = recording.catheter()
    rig, base = recording.rig()
    return Scene(catheter, rig, base.R_w_b, base.o_b_w_mm)


def progress_bar(total: int, description: str, enabled: bool, unit: str = "frame") -> tqdm:
    """A progress bar on stderr (disabled: counts silently)."""
    return tqdm(
        total=total,
        desc=description,
        unit=unit,
        disable=not enabled,
        file=sys.stderr,
        dynamic_ncols=True,
        leave=False,
    )


def _segmented(
    recording: Recording,
    scene: Scene,
    keep_images: Callable[[int], bool],
    progress: bool,
) -> list[RecordedFrame]:
    """Frames whose markers come from segmenting the recorded images (as the live loop does)."""
    if not recording.has_images:
        raise RecordingError(f"{recording.path}: the recording has no images to segment")
    if any(bg is None for bg in recording.backgrounds):
        raise RecordingError(
            f"{recording.path}: no background (empty-scene) image of "
            + " and ".join(
                v
                for v, bg in zip(recording.views, recording.backgrounds, strict=True)
                if bg is None
            )
            + ": the images cannot be segmented (use --source markers)"
        )
    table = recording.metadata.settings.get("segmentation")
    settings = (
        segmentation_settings_from_dict(table)
        if isinstance(table, dict)
        else SegmentationSettings()
    )
    segmenter = PairSegmenter(
        scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, recording.backgrounds, settings
    )
    out = []
    missing = 0
    bar = progress_bar(len(recording), "segment", progress)
    for i, recorded in enumerate(recording.frames(images=True)):
        f = recorded.frame
        bar.update()
        if f.images is None:
            missing += 1
            nan_uv = tuple(np.full_like(np.asarray(uv, float), np.nan) for uv in f.uv)
            nan_cov = tuple(np.full_like(np.asarray(cov, float), np.nan) for cov in f.cov)
            frame = replace(f, uv=nan_uv, cov=nan_cov)
            out.append(replace(recorded, frame=frame))
            continue
        seg = segmenter.segment(f.images)
        frame = seg.frame(
            f.time_s,
            f.q,
            f.q_dot,
            f.images if keep_images(i) else None,
            f.delta_L_true_rad,
        )
        quality = tuple(MarkerQuality.from_segmentation(view) for view in seg.views)
        out.append(RecordedFrame(frame, recorded.labels, quality))
    bar.close()
    if missing:
        recording.report.warnings.append(
            f"{missing} frame(s) lack an image of one view: their points count as missing"
        )
    return out


def _truth(frames: Sequence[RecordedFrame]) -> Array:
    """True delta_L per frame, rad (NaN where unknown)."""
    return np.array(
        [np.nan if r.frame.delta_L_true_rad is None else r.frame.delta_L_true_rad for r in frames],
        dtype=float,
    )


@dataclass
class Replay:
    """A recording replayed through the pipeline: frames, observations and every method."""

    path: str
    source: str
    scene: Scene
    frames: list[RecordedFrame]
    observations: list[Observation]
    results: dict[str, MethodResult]
    bound_rad: Array  # (F,) per-frame Cramer-Rao bound of the tip at the truth, inf if unknown
    sigma_image: Array  # (F,) segmentation noise of the tip, image unit (px or mm), NaN if none
    report: ReadReport
    settings: dict
    timings_s: dict[str, float] = field(default_factory=dict)

    @cached_property
    def truth_rad(self) -> Array:
        return _truth(self.frames)

    @cached_property
    def scored(self) -> Array:
        """Frames that count in the tables: those of a configuration of the protocol when the
        recording labels configurations (moves between them are replayed, not scored), else
        all."""
        configuration = self.label("configuration")
        labelled = np.array([c is not None for c in configuration], dtype=bool)
        return labelled if labelled.any() else np.ones(len(self.frames), dtype=bool)

    def label(self, name: str) -> Array:
        """One label per frame (object array; None where unknown)."""
        return np.array([getattr(r.labels, name) for r in self.frames], dtype=object)


def replay_recording(
    recording: Recording,
    methods: Sequence[str] | None = None,
    source: str = "auto",
    progress: bool = False,
    keep_images: Callable[[int], bool] = lambda i: False,
    workers: int = 1,
) -> Replay:
    """Replay a recording through the chosen estimators (default: all).

    Parameters
    ----------
    recording : Recording
    methods : list of str, optional
        Estimator names (:func:`tracker.estimators.estimator_names`).
    source : {"auto", "markers", "images"}
        Where the markers come from: the recorded markers, or the segmentation of the recorded
        images (``auto``: images when the recording has them).
    progress : bool
        Progress bars on stderr.
    keep_images : callable
        Which frame indices keep their images in memory (for the viewer).
    workers : int
        Processes running the estimators, one method each (the least-squares baselines cost
        milliseconds per frame; every method sees the same observations in the same order).
    """
    if source not in SOURCES:
        raise ValueError(f"source must be one of {SOURCES}, got {source!r}")
    methods = default_methods() if methods is None else list(methods)
    known = set(estimator_names())
    unknown = [m for m in methods if m not in known]
    if unknown:
        raise ValueError(
            f"unknown method(s) {', '.join(unknown)}; choose from {', '.join(sorted(known))}"
        )
    scene = recording_scene(recording)
    if source == "auto":
        source = (
            "images"
            if recording.has_images and all(b is not None for b in recording.backgrounds)
            else "markers"
        )
    timings: dict[str, float] = {}
    started = time.perf_counter()
    if source == "images":
        frames = _segmented(recording, scene, keep_images, progress)
        timings["segmentation"] = time.perf_counter() - started
    else:
        frames = list(recording.frames(images=keep_images))
        timings["frames"] = time.perf_counter() - started
    started = time.perf_counter()
    reconstructor = Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    observations = reconstructor.observe_batch([r.frame for r in frames])
    timings["reconstruction"] = time.perf_counter() - started
    truth = _truth(frames)
    results = {}
    runs = _run_estimators(scene.catheter, observations, methods, workers, progress)
    for name in methods:
        estimates, seconds = runs[name]
        timings[name] = seconds
        results[name] = MethodResult(name, estimates, truth)
    bound, sigma = _bound_and_sigma(scene.catheter, observations, frames, truth)
    return Replay(
        path=str(recording.path),
        source=source,
        scene=scene,
        frames=frames,
        observations=observations,
        results=results,
        bound_rad=bound,
        sigma_image=sigma,
        report=recording.report,
        settings=recording.metadata.settings,
        timings_s=timings,
    )


def _run_method(
    name: str, catheter: Catheter, observations: Sequence[Observation]
) -> tuple[tuple[Estimate, ...], float]:
    """One estimator over the observations in order: its estimates and the time it took."""
    with single_blas_thread():
        estimator = make_estimator(name, catheter)
        started = time.perf_counter()
        estimates = tuple(estimator.run(observations))
        return estimates, time.perf_counter() - started


def _method_task(data: tuple[Catheter, Sequence[Observation]], name: str):
    catheter, observations = data
    return _run_method(name, catheter, observations)


def _run_estimators(
    catheter: Catheter,
    observations: Sequence[Observation],
    methods: Sequence[str],
    workers: int,
    progress: bool,
) -> dict[str, tuple[tuple[Estimate, ...], float]]:
    # The slowest methods first, so that they do not start last.
    order = sorted(methods, key=lambda m: (not m.endswith("-lsq"), m))
    results = execute(
        _method_task,
        (catheter, observations),
        order,
        workers=workers,
        progress=progress,
        description="estimate",
        unit="method",
    )
    return dict(zip(order, results, strict=True))


def _bound_and_sigma(
    catheter: Catheter,
    observations: Sequence[Observation],
    frames: Sequence[RecordedFrame],
    truth: Array,
) -> tuple[Array, Array]:
    """Per-frame Cramer-Rao bound of the tip (rad; NaN where the frame has no reconstructed
    tip or no truth, inf where the configuration carries no information) and the tip's
    segmentation sigma (image unit)."""
    F = len(observations)
    bound = np.full(F, np.nan)
    usable = np.array([o.has_tip() for o in observations], dtype=bool) & np.isfinite(truth)
    if usable.any():
        idx = np.flatnonzero(usable)
        q = np.array([observations[i].q for i in idx])
        cov = np.array([observations[i].tip_cov_b for i in idx])
        bound[idx] = crb_tip(catheter, q, truth[idx], cov)
    sigma = np.full(F, np.nan)
    for i, r in enumerate(frames):
        variances = [
            np.trace(np.asarray(c, float)[0]) / 2
            for c in r.frame.cov
            if np.all(np.isfinite(np.asarray(c, float)[0]))
        ]
        if variances:
            sigma[i] = math.sqrt(float(np.mean(variances)))
    return bound, sigma
