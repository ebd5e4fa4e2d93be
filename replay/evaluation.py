"""Run estimators over frames and summarise their accuracy; replay and evaluate recordings.

The first part runs estimators over a sequence of frames (:func:`run_methods`) and tabulates
their accuracy (:func:`markdown_table`). The second replays a recording (tracker.io.recording)
through the same pipeline as the live loop -- frames, optional segmentation of the images,
reconstruction, every estimator -- and summarises each method's bending-plane error (the
wrapped difference between estimated and true ``delta_1 = q_r + delta_L``, which is the
difference of the delta_L) as in the paper: RMS and maximum over all configurations, per
bending plane, against tip deflection and against segmentation noise, next to the per-frame
Cramer-Rao bound of the tip. For the UKF the NEES against its chi-square band and the coverage
of the +/-2 sigma interval say whether its uncertainty is honest. :func:`evaluate_recording`
writes markdown, CSV, PNG figures and a rerun ``.rrd``; :func:`evaluate_batch` runs many
recordings on a local process pool or a Dask cluster (``cathtrack evaluate``).
"""

from __future__ import annotations

import csv
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from models.bounds import crb_tip
from models.catheter import Catheter
from models.rotations import wrap_angle
from replay.simulation.simulator import Scene
from tracker.estimators import estimator_names, make_estimator
from tracker.io.recording import (
    MarkerQuality,
    ReadReport,
    RecordedFrame,
    Recording,
    RecordingError,
    open_recording,
)
from tracker.reconstruction import Reconstructor
from tracker.types import Estimate, Flag, Frame, Observation, ViewMeasurement

Array = np.ndarray


@dataclass(frozen=True)
class MethodResult:
    """One estimator's estimates over a session and their errors against the truth."""

    name: str
    estimates: tuple[Estimate, ...]
    truth_rad: Array  # (T,)

    @property
    def valid(self) -> Array:
        return np.array([e.valid for e in self.estimates], dtype=bool)

    @property
    def errors_rad(self) -> Array:
        """Wrapped estimate - truth for valid frames (NaN elsewhere), rad."""
        est = np.array([e.delta_L_rad for e in self.estimates])
        return np.where(self.valid, wrap_angle(np.nan_to_num(est) - self.truth_rad), np.nan)

    @property
    def std_rad(self) -> Array:
        return np.array([e.std_rad for e in self.estimates])

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
            "rejected": int(sum(Flag.OUTLIER_REJECTED in e.flags for e in self.estimates)),
        }


def observations_from_frames(reconstructor: Reconstructor, frames: Sequence[Frame]) -> list:
    reconstructor.reset()
    return [reconstructor.observe(frame) for frame in frames]


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
        estimates = tuple(estimator.step(obs) for obs in observations)
        results[name] = MethodResult(name, estimates, np.asarray(truth_rad, dtype=float))
    return results


def markdown_table(results: dict[str, MethodResult], bound_rms_deg: float | None = None) -> str:
    """A markdown table of every method's accuracy, degrees."""
    lines = [
        "| method | RMS error (deg) | median abs (deg) | max abs (deg) | valid frames | "
        "within 2 sigma |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, result in results.items():
        s = result.summary()
        lines.append(
            f"| {name} | {s['rms_deg']:.2f} | {s['median_deg']:.2f} | {s['max_deg']:.2f} | "
            f"{100 * s['valid']:.0f}% | {100 * s['coverage_2sigma']:.0f}% |"
        )
    if bound_rms_deg is not None:
        lines.append(f"| Cramer-Rao bound, tip, per frame | {bound_rms_deg:.2f} | | | | |")
    return "\n".join(lines)


# ------------------------------------------------------------------------ replay: frames
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
BOUND_NAME = "crb-tip"
"""Name of the per-frame Cramer-Rao bound of the tip in the tables."""
SOURCES = ("auto", "markers", "images")


def default_methods() -> list[str]:
    """Every estimator, in the order of the paper's table, then the others."""
    names = estimator_names()
    return [m for m in METHOD_ORDER if m in names] + [m for m in names if m not in METHOD_ORDER]


def observations_batch(reconstructor: Reconstructor, frames: Sequence[Frame]) -> list[Observation]:
    """What ``reconstructor.observe`` gives for the frames in order after a reset, in one batch.

    The two-view reconstruction and its covariance run once over every point of every frame;
    the finite-difference velocities, single-view measurements and checks follow
    :meth:`tracker.reconstruction.Reconstructor.observe` exactly.
    """
    reconstructor.reset()
    if not frames:
        return []
    P = reconstructor.n_points
    shapes = {"uv_front": (P, 2), "uv_side": (P, 2), "cov_front": (P, 2, 2), "cov_side": (P, 2, 2)}
    arrays = {}
    for name, shape in shapes.items():
        try:
            arrays[name] = np.array([getattr(f, name) for f in frames], dtype=float)
            if arrays[name].shape[1:] != shape:
                raise ValueError
        except ValueError:
            k = next(k for k, f in enumerate(frames) if np.shape(getattr(f, name)) != shape)
            raise ValueError(
                f"frame {k} {name} has shape {np.shape(getattr(frames[k], name))}, expected"
                f" {shape}: the tip and every marker of the catheter model"
            ) from None
    q_all = np.array([f.q for f in frames], dtype=float)
    if q_all.shape != (len(frames), 3) or not np.all(np.isfinite(q_all)):
        bad = next(
            k for k, f in enumerate(frames) if np.shape(f.q) != (3,) or not np.all(np.isfinite(f.q))
        )
        raise ValueError(
            f"frame {bad} has joint values {frames[bad].q}: three finite numbers needed"
        )
    uv_f, uv_s = arrays["uv_front"], arrays["uv_side"]
    cov_f, cov_s = arrays["cov_front"], arrays["cov_side"]
    ok_f = np.all(np.isfinite(uv_f), -1) & np.all(np.isfinite(cov_f), (-2, -1))
    ok_s = np.all(np.isfinite(uv_s), -1) & np.all(np.isfinite(cov_s), (-2, -1))
    both = ok_f & ok_s
    F = len(frames)
    points_b = np.full((F, P, 3), np.nan)
    covs_b = np.tile(np.eye(3), (F, P, 1, 1))
    R_w_b, o_b_w = reconstructor.R_w_b, reconstructor.o_b_w_mm
    rig = reconstructor.rig
    if both.any():
        points_w = rig.reconstruct(uv_f[both], uv_s[both])
        cov_w = rig.reconstruction_covariance(points_w, cov_f[both], cov_s[both])
        R_b_w = R_w_b.T
        points_b[both] = (points_w - o_b_w) @ R_b_w.T
        covs_b[both] = R_b_w @ cov_w @ R_w_b
    # Finite-difference velocities as Reconstructor.observe forms them: from the previous
    # frame when both frames have the tip in both views, over 0 < dt <= the largest gap,
    # and only for frames with joint rates (velocity_from_positions, for all frames at once).
    times = np.array([f.time_s for f in frames], dtype=float)
    tip = both[:, 0]
    has_rates = np.array([f.q_dot is not None for f in frames], dtype=bool)
    dt = np.full(F, np.nan)
    dt[1:] = times[1:] - times[:-1]
    formed = np.zeros(F, dtype=bool)
    formed[1:] = tip[1:] & tip[:-1]
    formed &= (dt > 0) & (dt <= reconstructor.max_velocity_gap_s) & has_rates
    velocity = cov_velocity = cross = None
    if formed.any():
        i = np.flatnonzero(formed)
        step = dt[i]
        velocity = (points_b[i, 0] - points_b[i - 1, 0]) / step[:, None]
        cov_velocity = (covs_b[i, 0] + covs_b[i - 1, 0]) / (step**2)[:, None, None]
        cross = covs_b[i, 0] / step[:, None, None]
        slot = np.full(F, -1)
        slot[i] = np.arange(i.size)
    single_f, single_s = ok_f & ~both, ok_s & ~both
    has_single = single_f.any(axis=1) | single_s.any(axis=1)
    out = []
    for i, frame in enumerate(frames):
        views = []
        if has_single[i]:
            for view, single, uv, cov in (
                (rig.front, single_f[i], uv_f[i], cov_f[i]),
                (rig.side, single_s[i], uv_s[i], cov_s[i]),
            ):
                if single.any():
                    views.append(
                        ViewMeasurement(
                            view=view,
                            R_w_b=R_w_b,
                            o_b_w_mm=o_b_w,
                            uv=uv[single],
                            cov=cov[single],
                            point_index=np.flatnonzero(single) - 1,
                        )
                    )
        extra = {}
        if formed[i]:
            k = slot[i]
            extra = dict(
                velocity_b_mm_s=velocity[k],
                velocity_cov_b=cov_velocity[k],
                velocity_tip_cov_b=cross[k],
            )
        out.append(
            Observation(
                time_s=float(frame.time_s),
                q=q_all[i],
                q_dot=None if frame.q_dot is None else np.asarray(frame.q_dot, dtype=float),
                tip_b_mm=points_b[i, 0],
                tip_cov_b=covs_b[i, 0],
                markers_b_mm=points_b[i, 1:],
                markers_cov_b=covs_b[i, 1:],
                views=tuple(views),
                **extra,
            )
        )
    return out


def recording_scene(recording: Recording) -> Scene:
    """The catheter, rig and registered base pose stored in a recording."""
    catheter = recording.catheter()
    rig, R_w_b, o_b_w_mm = recording.rig()
    return Scene(catheter, rig, R_w_b, o_b_w_mm)


def _progress(total: int, description: str, enabled: bool, unit: str = "frame"):
    from tqdm import tqdm

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
    from tracker.vision.segmentation import (
        PairSegmenter,
        SegmentationSettings,
        segmentation_settings_from_dict,
    )

    if not recording.has_images:
        raise RecordingError(f"{recording.path}: the recording has no images to segment")
    if any(bg is None for bg in recording.backgrounds):
        raise RecordingError(
            f"{recording.path}: no background (empty-scene) image of "
            + " and ".join(
                v
                for v, bg in zip(("front", "side"), recording.backgrounds, strict=True)
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
    bar = _progress(len(recording), "segment", progress)
    for i, recorded in enumerate(recording.frames(images=True)):
        f = recorded.frame
        bar.update()
        if f.images is None:
            missing += 1
            nan_uv = np.full_like(np.asarray(f.uv_front, float), np.nan)
            nan_cov = np.full_like(np.asarray(f.cov_front, float), np.nan)
            frame = replace(f, uv_front=nan_uv, uv_side=nan_uv, cov_front=nan_cov, cov_side=nan_cov)
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
        quality = (
            MarkerQuality.from_segmentation(seg.front),
            MarkerQuality.from_segmentation(seg.side),
        )
        out.append(RecordedFrame(frame, recorded.labels, quality))
    bar.close()
    if missing:
        recording.report.warnings.append(
            f"{missing} frame(s) lack an image of one view: their points count as missing"
        )
    return out


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

    @property
    def truth_rad(self) -> Array:
        return np.array(
            [
                np.nan if r.frame.delta_L_true_rad is None else r.frame.delta_L_true_rad
                for r in self.frames
            ],
            dtype=float,
        )

    @property
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
    observations = observations_batch(reconstructor, [r.frame for r in frames])
    timings["reconstruction"] = time.perf_counter() - started
    truth = np.array(
        [np.nan if r.frame.delta_L_true_rad is None else r.frame.delta_L_true_rad for r in frames],
        dtype=float,
    )
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
    from replay.studies import single_blas_thread

    with single_blas_thread():
        estimator = make_estimator(name, catheter)
        started = time.perf_counter()
        estimates = tuple(estimator.step(obs) for obs in observations)
        return estimates, time.perf_counter() - started


def _run_estimators(
    catheter: Catheter,
    observations: Sequence[Observation],
    methods: Sequence[str],
    workers: int,
    progress: bool,
) -> dict[str, tuple[tuple[Estimate, ...], float]]:
    bar = _progress(len(methods), "estimate", progress, unit="method")
    out = {}
    try:
        if workers <= 1 or len(methods) <= 1:
            for name in methods:
                bar.set_postfix_str(name)
                out[name] = _run_method(name, catheter, observations)
                bar.update()
            return out
        from concurrent.futures import ProcessPoolExecutor, as_completed

        # The slowest methods first, so that they do not start last.
        slow_first = sorted(methods, key=lambda m: (not m.endswith("-lsq"), m))
        with ProcessPoolExecutor(max_workers=min(workers, len(methods))) as pool:
            futures = {
                pool.submit(_run_method, name, catheter, observations): name for name in slow_first
            }
            for future in as_completed(futures):
                out[futures[future]] = future.result()
                bar.update()
        return out
    finally:
        bar.close()


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
            for c in (r.frame.cov_front, r.frame.cov_side)
            if np.all(np.isfinite(np.asarray(c, float)[0]))
        ]
        if variances:
            sigma[i] = math.sqrt(float(np.mean(variances)))
    return bound, sigma


# ------------------------------------------------------------------------ replay: tables
def _stats(errors_rad: Array, valid: Array, std_rad: Array, known: Array) -> dict:
    """One method over a group of frames: the share of frames with an estimate, and the RMS,
    max and median |error| (degrees) and 2-sigma coverage over those that also have a truth."""
    n = int(valid.size)
    scored = valid & known & np.isfinite(errors_rad)
    err = errors_rad[scored]
    row = {
        "frames": n,
        "with_truth": int(np.count_nonzero(known)),
        "valid": float(np.count_nonzero(valid) / n) if n else 0.0,
    }
    if err.size == 0:
        row.update(rms_deg=math.nan, max_deg=math.nan, median_deg=math.nan)
    else:
        deg = np.degrees(np.abs(err))
        row.update(
            rms_deg=float(np.sqrt(np.mean(deg**2))),
            max_deg=float(deg.max()),
            median_deg=float(np.median(deg)),
        )
    ok = scored & np.isfinite(std_rad)
    row["within_2sigma"] = (
        float(np.mean(np.abs(errors_rad[ok]) <= 2 * std_rad[ok])) if ok.any() else math.nan
    )
    return row


def _bound_stats(bound_rad: Array) -> dict:
    b = bound_rad[~np.isnan(bound_rad)]
    b = np.minimum(b, np.pi)  # an uninformative frame can be no worse than a half turn
    n = int(bound_rad.size)
    if b.size == 0:
        return {
            "frames": n,
            "valid": 0.0,
            "rms_deg": math.nan,
            "max_deg": math.nan,
            "median_deg": math.nan,
        }
    deg = np.degrees(b)
    return {
        "frames": n,
        "valid": float(b.size / n) if n else 0.0,
        "rms_deg": float(np.sqrt(np.mean(deg**2))),
        "max_deg": float(deg.max()),
        "median_deg": float(np.median(deg)),
    }


def _groups(values: Array) -> list[tuple[object, Array]]:
    """(value, mask) per distinct non-None value, in sorted order."""
    present = [v for v in values if v is not None]
    out = []
    for value in sorted(set(present)):
        out.append((value, np.array([v == value for v in values], dtype=bool)))
    return out


TABLES = ("overall", "plane", "deflection", "noise", "configuration", "consistency")


def replay_tables(replay: Replay) -> dict[str, list[dict]]:
    """Every table as rows (long format, degrees): overall, per plane, deflection, noise,
    configuration, and the UKF consistency."""
    truth = replay.truth_rad
    known = np.isfinite(truth)
    groupings = {
        "overall": [("all", np.ones(len(replay.frames), dtype=bool))],
        "plane": _groups(replay.label("plane")),
        "deflection": _groups(replay.label("deflection_mm")),
        "noise": _groups(replay.label("noise_level")),
        "configuration": _groups(replay.label("configuration")),
    }
    tables: dict[str, list[dict]] = {name: [] for name in TABLES}
    for table, groups in groupings.items():
        for value, mask in groups:
            mask = mask & replay.scored
            extra = {}
            if table == "noise":
                sigma = replay.sigma_image[mask]
                extra["sigma_image"] = (
                    float(np.nanmedian(sigma)) if np.isfinite(sigma).any() else math.nan
                )
            if table == "plane":
                delta_L = truth[mask & known]
                extra["delta_L_true_deg"] = (
                    float(np.degrees(delta_L[0])) if delta_L.size else math.nan
                )
                targets = replay.settings.get("delta_1_targets_rad")
                if (
                    isinstance(targets, list)
                    and isinstance(value, int)
                    and 0 <= value < len(targets)
                ):
                    extra["delta_1_target_deg"] = float(np.degrees(targets[value]))
            for name, result in replay.results.items():
                row = _stats(
                    result.errors_rad[mask], result.valid[mask], result.std_rad[mask], known[mask]
                )
                tables[table].append(
                    {"table": table, "group": value, "method": name, **extra, **row}
                )
            tables[table].append(
                {
                    "table": table,
                    "group": value,
                    "method": BOUND_NAME,
                    **extra,
                    **_bound_stats(replay.bound_rad[mask]),
                }
            )
    from scipy.stats import chi2

    for name, result in replay.results.items():
        if not any(e.nis is not None for e in result.estimates):
            continue
        ok = result.valid & known & replay.scored & (result.std_rad > 0)
        err, std = result.errors_rad[ok], result.std_rad[ok]
        n = int(err.size)
        nees = (err / std) ** 2
        steps = [
            (e.nis, e.nis_dof)
            for e, scored in zip(result.estimates, replay.scored, strict=True)
            if scored and e.nis is not None and np.isfinite(e.nis)
        ]
        nis = np.array([x for x, _ in steps], dtype=float)
        dof = np.array([d for _, d in steps], dtype=float)
        low, high = (chi2.ppf(0.025, n) / n, chi2.ppf(0.975, n) / n) if n else (math.nan, math.nan)
        mean_nees = float(nees.mean()) if n else math.nan
        tables["consistency"].append(
            {
                "table": "consistency",
                "group": "all",
                "method": name,
                "frames": n,
                "mean_nees": mean_nees,
                "nees_band_low": float(low),
                "nees_band_high": float(high),
                "consistent": bool(low <= mean_nees <= high) if n else False,
                "within_2sigma": float(np.mean(np.abs(err) <= 2 * std)) if n else math.nan,
                "mean_nis_per_dof": float(nis.sum() / dof.sum()) if dof.sum() > 0 else math.nan,
            }
        )
    return tables


@dataclass(frozen=True)
class Check:
    claim: str
    holds: bool | None
    detail: str


def paper_checks(tables: dict[str, list[dict]], bound_factor: float = 1.5) -> list[Check]:
    """The paper's findings, checked on the overall table (None: a method was not run)."""
    overall = {row["method"]: row for row in tables["overall"]}

    def rms(name: str) -> float | None:
        row = overall.get(name)
        return None if row is None or not np.isfinite(row["rms_deg"]) else row["rms_deg"]

    checks = []
    tip, bound, ukf, velocity = (
        rms("tip-position"),
        rms(BOUND_NAME),
        rms("ukf"),
        rms("tip-velocity"),
    )
    if tip is not None and bound is not None:
        ratio = tip / bound
        checks.append(
            Check(
                f"closed-form Tip Position within {bound_factor:g} x the Cramer-Rao bound",
                ratio <= bound_factor,
                f"RMS {tip:.3g} deg vs bound {bound:.3g} deg (x {ratio:.2f})",
            )
        )
    else:
        checks.append(Check(f"Tip Position within {bound_factor:g} x the bound", None, "not run"))
    if tip is not None and ukf is not None:
        checks.append(
            Check(
                "the UKF is better than Tip Position", ukf < tip, f"RMS {ukf:.3g} vs {tip:.3g} deg"
            )
        )
    else:
        checks.append(Check("the UKF is better than Tip Position", None, "not run"))
    # Tip Velocity against the other data (its least-squares twin is the same estimator)
    others = {
        m: r["rms_deg"]
        for m, r in overall.items()
        if m != BOUND_NAME and not m.startswith("tip-velocity") and np.isfinite(r["rms_deg"])
    }
    if velocity is not None and others:
        worst_other = max(others, key=others.get)
        checks.append(
            Check(
                "Tip Velocity is the worst method",
                velocity > others[worst_other],
                f"RMS {velocity:.3g} deg vs next worst {worst_other} {others[worst_other]:.3g} deg",
            )
        )
    else:
        checks.append(Check("Tip Velocity is the worst method", None, "not run"))
    return checks


def _fmt(x, digits: int = 2) -> str:
    if x is None:
        return ""
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int | np.integer):
        return str(int(x))
    if isinstance(x, float | np.floating):
        if not np.isfinite(x):
            return "n/a" if np.isnan(x) else "inf"
        return f"{x:.{digits}f}"
    return str(x)


def _percent(x: float | None, digits: int) -> str:
    if x is None:
        return ""
    return f"{100 * x:.{digits}f}%" if np.isfinite(x) else "n/a"


def _pivot(rows: list[dict], methods: Sequence[str], lead: Sequence[tuple[str, str]]) -> list[str]:
    """Markdown: one row per group, one "RMS / max" column per method."""
    groups: dict[object, dict[str, dict]] = {}
    for row in rows:
        groups.setdefault(row["group"], {})[row["method"]] = row
    header = "| " + " | ".join([title for title, _ in lead] + ["frames"] + list(methods)) + " |"
    lines = [header, "|" + "---|" * len(lead) + "---:|" + "---:|" * len(methods)]
    for group, by_method in groups.items():
        first = next(iter(by_method.values()))
        cells = [_fmt(group) if key == "group" else _fmt(first.get(key), 1) for _, key in lead]
        cells.append(str(first["frames"]))
        for m in methods:
            r = by_method.get(m)
            cells.append("" if r is None else f"{_fmt(r['rms_deg'])} / {_fmt(r['max_deg'])}")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def replay_markdown(replay: Replay, tables: dict[str, list[dict]]) -> str:
    """The report: the paper's table and its breakdowns, the UKF's consistency, throughput."""
    methods = list(replay.results) + [BOUND_NAME]
    settings = replay.settings
    lines = [f"# Replay evaluation of {Path(replay.path).name}", ""]
    unscored = int(np.count_nonzero(~replay.scored))
    lines.append(
        f"{len(replay.frames)} frames"
        + (
            f" ({unscored} while moving between configurations: replayed, not scored)"
            if unscored
            else ""
        )
        + (
            ", markers segmented from the recorded images"
            if replay.source == "images"
            else ", markers as recorded"
        )
        + (f", protocol '{settings['protocol']}'" if "protocol" in settings else "")
        + f", rig {replay.scene.rig.kind}. Bending-plane error = wrapped (estimated - true)"
        " delta_1, degrees; the bound is the per-frame Cramer-Rao bound of the tip at the truth"
        f" ({BOUND_NAME})."
    )
    if replay.report.warnings:
        lines += ["", "Read report:", ""] + [f"- {w}" for w in replay.report.warnings]
    if not np.isfinite(replay.truth_rad).any():
        lines += [
            "",
            "The recording has no ground truth: the tables give the share of frames with an"
            " estimate, no errors.",
        ]
    bound = next((r for r in tables["overall"] if r["method"] == BOUND_NAME), None)
    lines += [
        "",
        "## Over all configurations",
        "",
        "| method | RMS (deg) | max (deg) | median (deg) | valid frames | within 2 sigma"
        " | RMS / bound |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in tables["overall"]:
        ratio = (
            row["rms_deg"] / bound["rms_deg"]
            if bound is not None and row["method"] != BOUND_NAME and bound["rms_deg"] > 0
            else math.nan
        )
        within = row.get("within_2sigma")
        lines.append(
            f"| {row['method']} | {_fmt(row['rms_deg'])} | {_fmt(row['max_deg'])} |"
            f" {_fmt(row['median_deg'])} | {100 * row['valid']:.0f}% |"
            f" {_percent(within, 0)} | {_fmt(ratio)} |"
        )
    lines += ["", "Checks against the paper's findings:", ""]
    for check in paper_checks(tables):
        mark = {True: "holds", False: "DOES NOT HOLD", None: "not checked"}[check.holds]
        lines.append(f"- {check.claim}: **{mark}** ({check.detail})")
    if tables["plane"]:
        lines += ["", "## Per bending plane (RMS / max, deg)", ""]
        lines += _pivot(
            tables["plane"],
            methods,
            [
                ("plane", "group"),
                ("delta_1 target (deg)", "delta_1_target_deg"),
                ("true delta_L (deg)", "delta_L_true_deg"),
            ],
        )
    if tables["deflection"]:
        lines += ["", "## Against tip deflection (RMS / max, deg)", ""]
        lines += _pivot(tables["deflection"], methods, [("deflection (mm)", "group")])
    if tables["noise"]:
        unit = settings.get("noise_unit", "")
        image_unit = "px" if replay.scene.rig.kind == "pinhole" else "mm"
        lines += [
            "",
            "## Against segmentation noise (RMS / max, deg)"
            + (f"; noise level in {unit}" if unit else ""),
            "",
        ]
        lines += _pivot(
            tables["noise"],
            methods,
            [
                ("noise level", "group"),
                (f"tip segmentation sigma ({image_unit}, median)", "sigma_image"),
            ],
        )
    if tables["consistency"]:
        lines += [
            "",
            "## Consistency of the filters' uncertainty",
            "",
            "| method | frames | mean NEES | 95% band for independent frames | consistent"
            " | within 2 sigma (expect 95%) | NIS / dof |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for row in tables["consistency"]:
            lines.append(
                f"| {row['method']} | {row['frames']} | {_fmt(row['mean_nees'])} |"
                f" {_fmt(row['nees_band_low'])} to {_fmt(row['nees_band_high'])} |"
                f" {_fmt(row['consistent'])} | {_percent(row['within_2sigma'], 1)} |"
                f" {_fmt(row['mean_nis_per_dof'])} |"
            )
        lines += [
            "",
            "Successive filter estimates are correlated, so the band (for independent frames) is"
            " narrower than the real spread of the mean NEES; the 2 sigma coverage is the more"
            " robust figure.",
        ]
    lines += ["", "## Throughput", ""]
    n = max(len(replay.frames), 1)
    for step, seconds in replay.timings_s.items():
        lines.append(f"- {step}: {seconds:.2f} s ({1e6 * seconds / n:.0f} us per frame)")
    return "\n".join(lines) + "\n"


CSV_COLUMNS = (
    "table",
    "group",
    "method",
    "frames",
    "with_truth",
    "valid",
    "rms_deg",
    "max_deg",
    "median_deg",
    "within_2sigma",
    "delta_1_target_deg",
    "delta_L_true_deg",
    "sigma_image",
    "mean_nees",
    "nees_band_low",
    "nees_band_high",
    "consistent",
    "mean_nis_per_dof",
)


def write_tables_csv(tables: dict[str, list[dict]], path: Path) -> Path:
    """Every table row in one long CSV (the columns of :data:`CSV_COLUMNS`)."""
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for rows in tables.values():
            for row in rows:
                writer.writerow({k: ("" if v is None else v) for k, v in row.items()})
    return path


def write_frames_csv(replay: Replay, path: Path) -> Path:
    """One row per frame: labels, truth, bound, and each method's estimate, std and error (deg)."""
    truth = replay.truth_rad
    columns = [
        "time_s",
        "plane",
        "configuration",
        "deflection_mm",
        "noise_level",
        "q_r_rad",
        "q_p_mm",
        "q_d_mm",
        "delta_L_true_deg",
        "bound_deg",
        "sigma_image",
    ]
    for name in replay.results:
        columns += [f"{name}_delta_L_deg", f"{name}_std_deg", f"{name}_error_deg", f"{name}_flags"]
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        errors = {n: r.errors_rad for n, r in replay.results.items()}
        for i, recorded in enumerate(replay.frames):
            fr, lab = recorded.frame, recorded.labels
            row = [
                f"{fr.time_s:.6f}",
                lab.plane,
                lab.configuration,
                lab.deflection_mm,
                lab.noise_level,
                *(f"{x:.9g}" for x in fr.q),
                f"{np.degrees(truth[i]):.6g}",
                f"{np.degrees(replay.bound_rad[i]):.6g}",
                f"{replay.sigma_image[i]:.6g}",
            ]
            for name, result in replay.results.items():
                e = result.estimates[i]
                row += [
                    f"{np.degrees(e.delta_L_rad):.6g}",
                    f"{np.degrees(e.std_rad):.6g}",
                    f"{np.degrees(errors[name][i]):.6g}",
                    int(e.flags.value),
                ]
            writer.writerow(["" if v is None else v for v in row])
    return path


# ------------------------------------------------------------------------ replay: figures
def write_figures(replay: Replay, tables: dict[str, list[dict]], out_dir: Path) -> list[Path]:
    """experiment.png (like the paper's experimental figure) and conditions.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(replay.results)
    colors = plt.get_cmap("tab10")
    paths = []
    # (a) estimated against true bending plane, per configuration (median), in polar axes;
    # (b) RMS error per configuration, planes separated, log scale.
    fig = plt.figure(figsize=(13, 5.5))
    ax_polar = fig.add_subplot(1, 2, 1, projection="polar")
    ax_err = fig.add_subplot(1, 2, 2)
    truth = replay.truth_rad
    q_r = np.array([r.frame.q[0] for r in replay.frames])
    configs = _groups(replay.label("configuration"))
    planes = replay.label("plane")
    targets = replay.settings.get("delta_1_targets_rad")
    if isinstance(targets, list):
        for t in targets:
            ax_polar.plot([t, t], [0, len(methods) + 1.5], color="0.3", lw=0.8)
    for m, name in enumerate(methods):
        result = replay.results[name]
        est = np.array([e.delta_L_rad for e in result.estimates])
        delta_1 = wrap_angle(q_r + est)
        xs, ys = [], []
        for _, mask in configs:
            sel = mask & result.valid
            if sel.any():
                # circular median is awkward: use the circular mean of the configuration
                xs.append(np.angle(np.mean(np.exp(1j * delta_1[sel]))))
                ys.append(m + 1)
        ax_polar.scatter(xs, ys, s=12, color=colors(m % 10), label=name)
    true_1 = wrap_angle(q_r + truth)[replay.scored & np.isfinite(truth)]
    shown = true_1[:: max(1, true_1.size // 500)]
    ax_polar.scatter(shown, np.full(shown.size, len(methods) + 1), s=8, color="k", label="truth")
    ax_polar.set_yticklabels([])
    ax_polar.set_title("bending plane per configuration (mean), one ring per method", fontsize=9)
    ax_polar.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=7)
    x = np.arange(len(configs))
    for m, name in enumerate(methods):
        rows = {r["group"]: r for r in tables["configuration"] if r["method"] == name}
        values = [rows[c]["rms_deg"] if c in rows else np.nan for c, _ in configs]
        ax_err.plot(x, values, marker=".", lw=0.8, color=colors(m % 10), label=name)
    bound_rows = {r["group"]: r for r in tables["configuration"] if r["method"] == BOUND_NAME}
    ax_err.plot(
        x,
        [bound_rows[c]["rms_deg"] if c in bound_rows else np.nan for c, _ in configs],
        color="k",
        ls="--",
        lw=1.0,
        label="Cramer-Rao bound (tip)",
    )
    boundaries = [
        i
        for i in range(1, len(configs))
        if _plane_of(planes, configs[i][1]) != _plane_of(planes, configs[i - 1][1])
    ]
    for b in boundaries:
        ax_err.axvline(b - 0.5, color="0.8", lw=0.8)
    ax_err.set_yscale("log")
    ax_err.set_xlabel("configuration (grouped by bending plane)")
    ax_err.set_ylabel("bending-plane error, RMS per configuration (deg)")
    ax_err.legend(fontsize=7)
    ax_err.grid(True, which="both", alpha=0.3)
    fig.suptitle(f"{Path(replay.path).name}: bending-plane estimation per configuration")
    fig.tight_layout()
    path = out_dir / "experiment.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    paths.append(path)
    # Against deflection and noise.
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, table, xlabel in (
        (axes[0], "deflection", "tip deflection (mm)"),
        (axes[1], "noise", "noise level"),
    ):
        for m, name in enumerate(methods + [BOUND_NAME]):
            rows = [r for r in tables[table] if r["method"] == name]
            if not rows:
                continue
            style = dict(color="k", ls="--") if name == BOUND_NAME else dict(color=colors(m % 10))
            ax.plot(
                [r["group"] for r in rows],
                [r["rms_deg"] for r in rows],
                marker="o",
                label=name,
                **style,
            )
        ax.set_yscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("RMS bending-plane error (deg)")
        ax.grid(True, which="both", alpha=0.3)
    if axes[1].get_legend_handles_labels()[0]:
        axes[1].legend(fontsize=7)
    fig.tight_layout()
    path = out_dir / "conditions.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    paths.append(path)
    return paths


def _plane_of(planes: Array, mask: Array):
    values = planes[mask]
    return values[0] if values.size else None


# ------------------------------------------------------------------------ replay: rerun
def write_rrd(replay: Replay, path: Path, frame_every: int = 1) -> Path:
    """A rerun recording of the replay: every ``frame_every``-th frame in 3-D and in both
    views (with the images the replay kept), and every method's series."""
    import uuid

    from tracker.viewer.sink import RerunSink, default_blueprint, file_stream

    methods = list(replay.results)
    primary = "ukf" if "ukf" in methods else (methods[0] if methods else None)
    stream = file_stream(
        path,
        recording_id=str(uuid.uuid5(uuid.NAMESPACE_URL, str(Path(replay.path).resolve()))),
        blueprint=default_blueprint(methods, pinhole=replay.scene.rig.kind == "pinhole"),
    )
    sink = RerunSink(stream, primary=primary)
    for i in range(0, len(replay.frames), max(1, int(frame_every))):
        estimates = {name: r.estimates[i] for name, r in replay.results.items()}
        sink.log_frame(replay.frames[i].frame, replay.observations[i], estimates, replay.scene)
    truth = replay.truth_rad
    for name, result in replay.results.items():
        sink.log_series(name, result.estimates, truth)
    stream.flush()
    stream.disconnect()
    return path


# ------------------------------------------------------------------------ evaluate
@dataclass(frozen=True)
class EvaluationOutput:
    path: str
    replay: Replay
    tables: dict[str, list[dict]]
    files: tuple[Path, ...]

    def checks(self) -> list[Check]:
        return paper_checks(self.tables)


def evaluate_recording(
    path: str | Path,
    out_dir: str | Path | None,
    methods: Sequence[str] | None = None,
    source: str = "auto",
    rrd: bool = True,
    rrd_frame_every: int = 4,
    rrd_image_every: int = 20,
    figures: bool = True,
    progress: bool = False,
    workers: int = 1,
) -> EvaluationOutput:
    """Replay one recording and write its report (``summary.md``, ``summary.csv``,
    ``frames.csv``, ``experiment.png``, ``conditions.png``, ``replay.rrd``) to ``out_dir``.

    Parameters
    ----------
    path : str or Path
        The recording.
    out_dir : str or Path or None
        Output directory (created); None writes nothing (tables only).
    methods, source, progress
        See :func:`replay_recording`.
    rrd : bool
        Write ``replay.rrd``; ``rrd_frame_every`` thins the per-frame 3-D scene and
        ``rrd_image_every`` the images in it (every method's series is always complete).
    figures : bool
        Write the PNG figures.
    workers : int
        Processes running the estimators (see :func:`replay_recording`).
    """
    from replay.studies import single_blas_thread

    keep = (
        (lambda i: rrd and i % max(1, rrd_image_every) == 0)
        if out_dir is not None
        else (lambda i: False)
    )
    with single_blas_thread():
        started = time.perf_counter()
        with open_recording(path) as recording:
            read_s = time.perf_counter() - started
            replay = replay_recording(
                recording, methods, source, progress, keep_images=keep, workers=workers
            )
        replay.timings_s = {"read": read_s, **replay.timings_s}
        tables = replay_tables(replay)
        files: list[Path] = []
        if out_dir is not None:
            out = Path(out_dir)
            out.mkdir(parents=True, exist_ok=True)
            files.append(write_tables_csv(tables, out / "summary.csv"))
            files.append(write_frames_csv(replay, out / "frames.csv"))
            if figures:
                files += write_figures(replay, tables, out)
            if rrd:
                started = time.perf_counter()
                files.append(write_rrd(replay, out / "replay.rrd", rrd_frame_every))
                replay.timings_s["rerun"] = time.perf_counter() - started
            summary = out / "summary.md"
            summary.write_text(replay_markdown(replay, tables))
            files.insert(0, summary)
    return EvaluationOutput(str(path), replay, tables, tuple(files))


@dataclass(frozen=True)
class BatchItem:
    """One recording of a batch: its overall rows and checks, or the error that stopped it."""

    path: str
    out_dir: str | None
    overall: tuple[dict, ...] = ()
    checks: tuple[Check, ...] = ()
    warnings: tuple[str, ...] = ()
    error: str | None = None


def _batch_task(path: str, out_dir: str | None, options: dict) -> BatchItem:
    try:
        result = evaluate_recording(path, out_dir, **options)
    except (ValueError, OSError) as exc:
        return BatchItem(path, out_dir, error=str(exc))
    return BatchItem(
        path,
        out_dir,
        tuple(result.tables["overall"]),
        tuple(result.checks()),
        tuple(result.replay.report.warnings),
    )


def evaluate_batch(
    paths: Sequence[str | Path],
    out_dir: str | Path,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
    **options,
) -> list[BatchItem]:
    """Evaluate many recordings, each into ``out_dir/<name>/``, on a local process pool
    (``workers``, default all CPUs) or a Dask cluster (``scheduler`` address); writes
    ``out_dir/batch.md`` and ``out_dir/batch.csv``. A recording that cannot be read is
    reported in the batch table, the others are evaluated."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = _unique_names([Path(p) for p in paths])
    jobs = [(str(p), str(out / name)) for p, name in zip(paths, names, strict=True)]
    options = {**options, "progress": False, "workers": 1}
    workers = (os.cpu_count() or 1) if workers is None else int(workers)
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    bar = _progress(len(jobs), "evaluate", progress, unit="recording")
    items: list[BatchItem | None] = [None] * len(jobs)
    try:
        if scheduler:
            try:
                from dask.distributed import Client, as_completed
            except ImportError as exc:  # pragma: no cover - dask is a dependency
                raise ValueError("--scheduler needs dask.distributed installed") from exc
            try:
                client = Client(scheduler, set_as_default=False, timeout="10s")
            except (OSError, TimeoutError) as exc:
                raise ValueError(
                    f"cannot connect to the Dask scheduler at {scheduler}: {exc}"
                ) from exc
            try:
                futures = [client.submit(_batch_task, p, o, options, pure=False) for p, o in jobs]
                index = {f.key: i for i, f in enumerate(futures)}
                for future in as_completed(futures, loop=client.loop):
                    items[index[future.key]] = future.result()
                    bar.update()
            finally:
                client.close()
        elif workers == 1 or len(jobs) == 1:
            for i, (p, o) in enumerate(jobs):
                items[i] = _batch_task(p, o, options)
                bar.update()
        else:
            from concurrent.futures import ProcessPoolExecutor, as_completed

            with ProcessPoolExecutor(max_workers=min(workers, len(jobs))) as pool:
                futures = {
                    pool.submit(_batch_task, p, o, options): i for i, (p, o) in enumerate(jobs)
                }
                for future in as_completed(futures):
                    items[futures[future]] = future.result()
                    bar.update()
    finally:
        bar.close()
    done = [item for item in items if item is not None]
    write_batch(done, out)
    return done


def _unique_names(paths: Sequence[Path]) -> list[str]:
    names, seen = [], {}
    for p in paths:
        stem = p.stem or "recording"
        seen[stem] = seen.get(stem, 0) + 1
        names.append(stem if seen[stem] == 1 else f"{stem}-{seen[stem]}")
    return names


def write_batch(items: Sequence[BatchItem], out: Path) -> list[Path]:
    """batch.csv (overall rows of every recording) and batch.md (RMS / max per method)."""
    rows = []
    for item in items:
        for row in item.overall:
            rows.append({"recording": item.path, **row})
    csv_path = out / "batch.csv"
    with open(csv_path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=("recording",) + CSV_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
        for item in items:
            if item.error:
                writer.writerow({"recording": item.path, "table": "error", "group": item.error})
    methods: list[str] = []
    for item in items:
        for row in item.overall:
            if row["method"] not in methods:
                methods.append(row["method"])
    lines = [
        "# Batch evaluation (RMS / max bending-plane error, deg)",
        "",
        "| recording | " + " | ".join(methods) + " | checks |",
        "|---|" + "---:|" * len(methods) + "---|",
    ]
    for item in items:
        if item.error:
            lines.append(
                f"| {item.path} | " + " | ".join("" for _ in methods) + f" | error: {item.error} |"
            )
            continue
        by = {r["method"]: r for r in item.overall}
        cells = [
            f"{_fmt(by[m]['rms_deg'])} / {_fmt(by[m]['max_deg'])}" if m in by else ""
            for m in methods
        ]
        held = sum(c.holds is True for c in item.checks)
        checked = sum(c.holds is not None for c in item.checks)
        lines.append(f"| {item.path} | " + " | ".join(cells) + f" | {held}/{checked} hold |")
    md_path = out / "batch.md"
    md_path.write_text("\n".join(lines) + "\n")
    return [md_path, csv_path]
