"""What ``cathtrack evaluate`` writes for one recording: CSV tables, figures and a rerun file.

:func:`evaluate_recording` replays a recording (:func:`~replay.evaluation.run.replay_recording`),
tabulates it (:func:`~replay.evaluation.tables.replay_tables`) and writes ``summary.md``,
``summary.csv``, ``frames.csv``, ``experiment.png``, ``conditions.png`` and ``replay.rrd``.
"""

from __future__ import annotations

import csv
import time
import uuid
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.rotations import wrap_angle
from replay.evaluation.run import Replay, replay_recording
from replay.evaluation.tables import (
    BOUND_NAME,
    Check,
    group_frames,
    paper_checks,
    replay_markdown,
    replay_tables,
)
from replay.parallel import single_blas_thread
from tracker.io.recording import open_recording
from tracker.types import Estimate, Frame
from tracker.viewer.layout import default_blueprint
from tracker.viewer.output import file_stream
from tracker.viewer.sink import RerunSink

Array = np.ndarray
RRD_JPEG_QUALITY = 85

CSV_COLUMNS = (
    "table",
    "group",
    "group_median",
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
    "confidently_wrong_frames",
    "confidently_wrong_configurations",
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
    # Imported here: only this output needs matplotlib, and it must choose its backend first.
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
    configs = group_frames(replay.label("configuration"), np.ones(len(replay.frames), bool))
    planes = replay.label("plane")
    targets = replay.settings.get("delta_1_targets_rad")
    if isinstance(targets, list):
        for t in targets:
            ax_polar.plot([t, t], [0, len(methods) + 1.5], color="0.3", lw=0.8)
    for m, name in enumerate(methods):
        result = replay.results[name]
        delta_1 = wrap_angle(q_r + result.delta_L_rad)
        xs, ys = [], []
        for group in configs:
            sel = group.frames[result.valid[group.frames]]
            if sel.size:
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
        values = [rows[g.key]["rms_deg"] if g.key in rows else np.nan for g in configs]
        ax_err.plot(x, values, marker=".", lw=0.8, color=colors(m % 10), label=name)
    bound_rows = {r["group"]: r for r in tables["configuration"] if r["method"] == BOUND_NAME}
    ax_err.plot(
        x,
        [bound_rows[g.key]["rms_deg"] if g.key in bound_rows else np.nan for g in configs],
        color="k",
        ls="--",
        lw=1.0,
        label="Cramer-Rao bound (tip)",
    )
    boundaries = [
        i
        for i in range(1, len(configs))
        if planes[configs[i].frames[0]] != planes[configs[i - 1].frames[0]]
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
    # Against deflection and noise, at the median label value of each group.
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
                [r["group_median"] for r in rows],
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


# ------------------------------------------------------------------------ replay: rerun
def scene_frames(replay: Replay, frame_every: int = 1) -> list[int]:
    """The frames whose scene (3-D, markers, dial) a rerun recording shows: those whose images
    the replay kept, so that images, markers and 3-D always agree; without images, every
    ``frame_every``-th frame."""
    with_images = [i for i, r in enumerate(replay.frames) if r.frame.images is not None]
    return with_images or list(range(0, len(replay.frames), max(1, int(frame_every))))


def primary_method(methods: Sequence[str]) -> str | None:
    """The method drawn in 3-D: the UKF when it ran, else the first."""
    methods = list(methods)
    return "ukf" if "ukf" in methods else (methods[0] if methods else None)


def log_replay(
    sink,
    replay: Replay,
    frames: Iterable[tuple[int, Frame]],
    estimates: Mapping[str, Sequence[Estimate]] | None = None,
) -> None:
    """The scene at the given (index, frame) pairs, then every method's series.

    Parameters
    ----------
    sink : tracker.viewer.sink.RerunSink
    replay : Replay
    frames : iterable of (int, Frame)
        Frame indices of the replay with the frame to draw (the replay's own, or the same
        frame with its images read again from the recording).
    estimates : mapping of method name to one estimate per frame, optional
        What to draw (default: the replay's methods).
    """
    if estimates is None:
        estimates = {name: r.estimates for name, r in replay.results.items()}
    for i, frame in frames:
        at_frame = {name: values[i] for name, values in estimates.items()}
        sink.log_frame(frame, replay.observations[i], at_frame, replay.scene)
    truth = replay.truth_rad
    for name, values in estimates.items():
        sink.log_series(name, values, truth)


def write_rrd(replay: Replay, path: Path, frame_every: int = 1) -> Path:
    """A rerun recording of the replay: the scene in 3-D, in every view and on the dial on
    the frames of :func:`scene_frames` (with their images, JPEG), and every method's
    series on every frame."""
    methods = list(replay.results)
    stream = file_stream(
        path,
        recording_id=str(uuid.uuid5(uuid.NAMESPACE_URL, str(Path(replay.path).resolve()))),
        blueprint=default_blueprint(methods, scene=replay.scene, primary=primary_method(methods)),
        recording_name=f"replay of {Path(replay.path).name}",
    )
    sink = RerunSink(stream, primary=primary_method(methods), jpeg_quality=RRD_JPEG_QUALITY)
    indices = scene_frames(replay, frame_every)
    log_replay(sink, replay, ((i, replay.frames[i].frame) for i in indices))
    sink.close()
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
        Write ``replay.rrd``: the scene (images, markers, 3-D) on every
        ``rrd_image_every``-th frame of a recording with images, on every
        ``rrd_frame_every``-th of one without (:func:`scene_frames`); every method's series
        is always complete.
    figures : bool
        Write the PNG figures.
    workers : int
        Processes running the estimators (see :func:`replay_recording`).
    """
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
