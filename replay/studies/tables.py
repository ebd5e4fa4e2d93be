"""The study tables: statistics per study point, and the CSV and settings files."""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from replay.studies.settings import (
    ABS_NORMAL_QUANTILES,
    CSV_COLUMNS,
    SensitivitySettings,
    StudyPoint,
    row_order,
)
from replay.studies.trials import TaskResult
from tracker import __version__

Array = np.ndarray


@dataclass(frozen=True)
class SensitivityResult:
    """Every row of every study table, and how the run went."""

    settings: SensitivitySettings
    rows: dict[str, list[dict]]  # study -> rows with the CSV_COLUMNS
    elapsed_s: float
    workers: int
    scheduler: str | None


def summarise(values: Array, kind: str) -> dict[str, float]:
    """Median, quartiles and RMS of |error| in degrees (bounds: of an efficient estimator)."""
    values = np.asarray(values, dtype=float)
    n = values.size
    if kind == "bound":
        rms = float(np.sqrt(np.mean(values**2))) if n else math.nan
        stats = {name: factor * rms for name, factor in ABS_NORMAL_QUANTILES.items()}
        stats["rms"] = rms
        return {
            **{f"{k}_deg": math.degrees(v) for k, v in stats.items()},
            "n": n,
            "valid_fraction": 1.0,
        }
    valid = np.isfinite(values)
    err = np.abs(values[valid])
    if err.size == 0:
        stats = dict.fromkeys(("median", "p25", "p75", "rms"), math.nan)
    else:
        p25, median, p75 = np.percentile(err, [25, 50, 75])
        stats = {"median": median, "p25": p25, "p75": p75, "rms": np.sqrt(np.mean(err**2))}
    return {
        **{f"{k}_deg": math.degrees(float(v)) for k, v in stats.items()},
        "n": int(err.size),
        "valid_fraction": float(valid.mean()) if n else 0.0,
    }


def tabulate(settings: SensitivitySettings, results: Sequence[TaskResult]) -> dict[str, list]:
    """Rows of every study table from the task results (chunks joined in trial order)."""
    by_point: dict[tuple, list[TaskResult]] = {}
    points: dict[tuple, StudyPoint] = {}
    for result in results:
        by_point.setdefault(result.task.point.key, []).append(result)
        points[result.task.point.key] = result.task.point
    rows: dict[str, list[dict]] = {study: [] for study in settings.studies}
    for key in sorted(by_point):
        chunks = sorted(by_point[key], key=lambda r: r.task.chunk)
        point = points[key]
        for method, kind in row_order(settings):
            parts = [r.values[method] for r in chunks if method in r.values]
            values = np.concatenate(parts) if parts else np.zeros(0)
            row = {**point.label, "method": method, "kind": kind, **summarise(values, kind)}
            rows[point.study].append(row)
    return rows


def _format(value) -> str:
    if isinstance(value, float):
        return repr(round(value, 9)) if math.isfinite(value) else str(value)
    return str(value)


def write_tables(result: SensitivityResult, out_dir: Path) -> list[Path]:
    paths = []
    for study, rows in result.rows.items():
        path = out_dir / f"study_{study}.csv"
        with path.open("w", newline="") as f:
            writer = csv.writer(f, lineterminator="\n")
            writer.writerow(CSV_COLUMNS)
            for row in rows:
                writer.writerow([_format(row[c]) for c in CSV_COLUMNS])
        paths.append(path)
    return paths


def read_table(path: Path) -> list[dict]:
    """Rows of a study CSV with numbers parsed (for tests and further analysis)."""
    with Path(path).open(newline="") as f:
        rows = list(csv.DictReader(f))
    text = {"study", "variant", "method", "kind"}
    return [{k: (v if k in text else float(v)) for k, v in row.items()} for row in rows]


def write_settings(result: SensitivityResult, out_dir: Path) -> Path:
    s = result.settings
    record = {
        "cathtrack_version": __version__,
        "seed": s.seed,
        "settings": s.to_dict(),
        "notes": {
            "units": "noise and deflection in mm, angles in degrees, joint rates in rad/s, mm/s,"
            " mm/s, frame interval in s",
            "ukf_trials": f"the UKF runs on the first {s.effective_ukf_trials} of the {s.trials}"
            " trials of every point; the per-frame estimators and bounds on all of them",
            "bound_rows": "rms_deg is the Cramer-Rao bound on the std of delta_L; median/p25/p75"
            " are those of |error| of an efficient unbiased estimator (0.674, 0.319, 1.150 x)",
            "views": "default_orthographic_rig (noise in mm in the plane) or default_pinhole_rig"
            " (noise in mm at the isocentre, times f / distance = px)",
        },
        "run": {
            "workers": result.workers,
            "scheduler": result.scheduler,
            "elapsed_s": round(result.elapsed_s, 3),
        },
    }
    path = out_dir / "settings.json"
    path.write_text(json.dumps(record, indent=2) + "\n")
    return path
