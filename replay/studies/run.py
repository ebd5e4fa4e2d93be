"""Running the sensitivity studies and the least-squares baseline check, and their outputs."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from replay.parallel import execute, worker_count
from replay.studies.figures import write_figures
from replay.studies.findings import summary_markdown
from replay.studies.settings import (
    CLOSED_FORM_METHODS,
    SensitivitySettings,
    Task,
    make_tasks,
    study_points,
)
from replay.studies.tables import SensitivityResult, tabulate, write_settings, write_tables
from replay.studies.trials import baseline_task, run_task


def run_sensitivity(
    settings: SensitivitySettings,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> SensitivityResult:
    """Run the selected studies; the tables depend on the settings only.

    Parameters
    ----------
    workers : int, optional
        Local worker processes (default: the number of CPUs; 1 runs in this process).
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://host:8786``) to run the tasks on instead.
    progress : bool
        Show a progress bar on stderr.
    """
    started = time.perf_counter()
    points = study_points(settings)
    tasks = make_tasks(settings, points)
    results = execute(run_task, settings, tasks, workers, scheduler, progress, "sensitivity")
    rows = tabulate(settings, results)
    used = 0 if scheduler else worker_count(workers)
    return SensitivityResult(settings, rows, time.perf_counter() - started, used, scheduler)


def baseline_agreement(
    settings: SensitivitySettings,
    trials_per_point: int = 2,
    tolerance_rad: float = 1e-3,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> dict[str, float]:
    """How often the paper's least-squares baseline agrees with the closed form.

    Runs the first ``trials_per_point`` trials of every study point (the same frames the
    studies score) through both solvers. Returns, per estimator, the fraction of trials where
    the two estimates differ by less than ``tolerance_rad`` (wrapped); ``"all"`` over every
    solve, ``"bent"`` over the solves away from the straight configuration (where the cost does
    not depend on delta_L, so any angle minimises it), and the number of solves ``"trials"``.
    """
    points = study_points(settings)
    tasks = [Task(p, 0, 0, min(trials_per_point, settings.trials)) for p in points]
    results = execute(baseline_task, settings, tasks, workers, scheduler, progress, "baseline")
    bent = np.concatenate([np.full(t.stop - t.start, t.point.bending_deg >= 1.0) for t in tasks])
    rates: dict[str, float] = {}
    joined, joined_bent = [], []
    for name in CLOSED_FORM_METHODS:
        diff = np.concatenate([r[name] for r in results])
        agree = np.abs(np.nan_to_num(diff, nan=np.inf)) < tolerance_rad
        rates[name] = float(agree.mean())
        joined.append(agree)
        joined_bent.append(agree[bent])
    rates["all"] = float(np.concatenate(joined).mean())
    rates["bent"] = float(np.concatenate(joined_bent).mean())
    rates["trials"] = float(sum(a.size for a in joined))
    return rates


def write_outputs(result: SensitivityResult, out_dir: Path | str) -> list[Path]:
    """Write CSV tables, PNG figures, summary.md and settings.json into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = write_tables(result, out_dir)
    paths += write_figures(result, out_dir)
    summary = out_dir / "summary.md"
    summary.write_text(summary_markdown(result))
    paths += [summary, write_settings(result, out_dir)]
    return paths
