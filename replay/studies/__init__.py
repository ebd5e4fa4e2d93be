"""The paper's three sensitivity studies, for every estimator, next to the Cramer-Rao bound.

Lawson, Chitale and Simaan (ICRA 2023) judge a bending-plane estimator by how its error
grows (a) with the segmentation noise, (b) over the workspace of tip angles, toward the
straight configuration, and (c) with a tip deflection by contact that the model does not know.
This package reproduces the three studies for the per-frame estimators (Tip Position, Body
Positions, Tip Velocity), the UKF and the Cramer-Rao bound, each for ``delta_2 = 0`` and a
non-planar ``delta_2``, and goes further: pinhole views as well as the paper's planes, an
out-of-plane deflection besides the paper's in-plane one, motion for Tip Velocity with stated
joint rates and frame interval, and the bound for a filter that uses every frame.

One trial
    Frames of moving joints ending at the study's configuration, with a true delta_L and
    segmentation noise; see :mod:`replay.studies.trials` for what is scored on which frame.

Speed
    The per-frame closed forms run on all trials of a task at once (one batched
    reconstruction, one batched rotation fit), and so does the UKF: one filter per trial,
    stepped together over the frames by :func:`tracker.estimators.ukf_batch.run_ukf_batch`
    (the same filter as :class:`~tracker.estimators.ukf.BendingPlaneUKF`, to rounding). Only
    the optional least-squares baselines step trial by trial. The UKF and the baselines run
    on the first ``ukf_trials`` trials of every study point (by default all of them).

Tasks and seeds
    Each (study, variant, delta_2, level, chunk of ``chunk_trials`` trials) is an independent
    task with its own random stream, ``SeedSequence(seed, spawn_key=task key)``, so the
    results do not depend on how many workers run them or in which order. Tasks run in-process
    (one worker), on a local process pool, or on a Dask cluster (:mod:`replay.parallel`).

Modules
    ``settings`` (what a run is: settings, study points, tasks), ``trials`` (one task:
    simulation and per-method errors), ``tables`` (statistics, CSV and settings files),
    ``findings`` (the paper's findings, the markdown summary), ``figures`` and ``run`` (the
    whole run and its outputs). This package re-exports what callers use.
"""

# Re-exported for callers from before replay.parallel held it.
from replay.parallel import single_blas_thread
from replay.studies.figures import FIGURES, write_figures
from replay.studies.findings import Finding, findings, summary_markdown
from replay.studies.run import baseline_agreement, run_sensitivity, write_outputs
from replay.studies.settings import (
    BOUND_ROWS,
    CSV_COLUMNS,
    DEFAULT_METHODS,
    DEFLECTIONS,
    METHODS,
    STUDIES,
    STUDY_TITLES,
    VIEWS,
    SensitivitySettings,
    StudyPoint,
    Task,
    load_settings,
    make_tasks,
    study_points,
)
from replay.studies.tables import (
    SensitivityResult,
    read_table,
    summarise,
    tabulate,
    write_settings,
    write_tables,
)
from replay.studies.trials import (
    TaskResult,
    TrialData,
    bound_std,
    closed_form_errors,
    run_task,
    simulate_task,
    stepped_errors,
    ukf_errors,
)

__all__ = [
    "BOUND_ROWS",
    "CSV_COLUMNS",
    "DEFAULT_METHODS",
    "DEFLECTIONS",
    "FIGURES",
    "METHODS",
    "STUDIES",
    "STUDY_TITLES",
    "VIEWS",
    "Finding",
    "SensitivityResult",
    "SensitivitySettings",
    "StudyPoint",
    "Task",
    "TaskResult",
    "TrialData",
    "baseline_agreement",
    "bound_std",
    "closed_form_errors",
    "findings",
    "load_settings",
    "make_tasks",
    "read_table",
    "run_sensitivity",
    "run_task",
    "simulate_task",
    "single_blas_thread",
    "stepped_errors",
    "study_points",
    "summarise",
    "summary_markdown",
    "tabulate",
    "ukf_errors",
    "write_figures",
    "write_outputs",
    "write_settings",
    "write_tables",
]
