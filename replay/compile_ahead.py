"""Compile every numba kernel now, several at a time (``cathtrack compile``; ``make`` runs it
after installing).

The kernels are compiled the first time they are used on a machine and cached on disk next
to the code (about a minute and a half on one core of a 2-core machine, once; loaded in a
fraction of a second after that). Compiled here, in one process per core, that time is spent
once at install, and shorter, rather than by the first demo, replay or test that needs them.
A kernel that is already cached is only loaded.

The jobs call the kernels' own warm-ups (the argument types the segmenter and the filters
pass), then replay a short simulated session through every estimator and run a few trials
of each study, so that a first replay or study finds the versions it uses cached too. The
tests use a few versions of their own, which they still compile.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator

from replay.parallel import execute


def _models() -> None:
    from models import _fit_kernels, _imaging_kernels, _shape_kernels
    from tracker.estimators import check_kernels

    for module in (_shape_kernels, _fit_kernels, _imaging_kernels, check_kernels):
        module.warm_up()


def _segmentation() -> None:
    from tracker.vision import band_fit, kernels, pair_kernels

    for module in (kernels, band_fit, pair_kernels):
        module.warm_up()


def _filter_rules() -> None:
    from tracker.estimators import ukf_rules

    ukf_rules.warm_up()


def _grid() -> None:
    from tracker.estimators import grid_kernels

    grid_kernels.warm_up()


def _filters() -> None:
    """The filter's step, and a short simulated session replayed through every estimator:
    the batch paths (the filters' compiled runs over many frames) that no ``warm_up``
    covers."""
    from models.catheter import default_catheter
    from replay.simulation.sources import simulated_session
    from tracker.estimators import (
        estimator_names,
        make_estimator,
        measurement_kernels,
        ukf_kernels,
        ukf_step,
    )
    from tracker.reconstruction import Reconstructor

    for module in (measurement_kernels, ukf_kernels, ukf_step):
        module.warm_up()
    catheter = default_catheter()
    session = simulated_session(2.0, 20.0, noise=0.5, catheter=catheter)
    scene = session.scene
    reconstructor = Reconstructor(catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    observations = reconstructor.observe_batch(session.frames)
    for name in estimator_names():
        make_estimator(name, catheter).run(observations)


def _study() -> None:
    """A few trials of each sensitivity study: the filters stepped as a bank of trials
    (``cathtrack sensitivity``), arrays of other shapes than one filter's."""
    from replay.studies.settings import SensitivitySettings, Task, study_points
    from replay.studies.trials import run_task

    settings = SensitivitySettings(
        trials=4, chunk_trials=4, noise_levels_mm=(1.0,), theta_L1_deg=(60.0,),
        theta_L2_deg=(60.0,), deflection_levels_mm=(4.0,),
    )  # fmt: skip
    studies = set()
    for point in study_points(settings):
        if point.study not in studies:
            studies.add(point.study)
            run_task(settings, Task(point, 0, 0, settings.trials))


# Label and job, in stages: a stage starts when the one before it has ended. The filters'
# step and runs call the filters' rules, which would otherwise be compiled twice at once (in
# the rules' job and in theirs). Longest first within a stage, so that it ends together.
STAGES: tuple[tuple[tuple[str, Callable[[], None]], ...], ...] = (
    (
        ("the filters' rules", _filter_rules),
        ("the segmentation", _segmentation),
        ("the grid filter", _grid),
        ("the model", _models),
    ),
    (
        ("the filters' step and every estimator's run", _filters),
        ("the sensitivity studies' trials", _study),
    ),
)


def _compiled(_settings: None, job: tuple[str, Callable[[], None]]) -> float:
    """Run one job (label, function); its time, s. A failure is raised naming the job."""
    label, function = job
    started = time.perf_counter()
    try:
        function()
    except Exception as exc:
        raise RuntimeError(f"compiling {label} failed: {exc}") from exc
    return time.perf_counter() - started


def compile_all(
    jobs: int | None = None,
    report: Callable[[str], None] = print,
    stages: tuple[tuple[tuple[str, Callable[[], None]], ...], ...] = STAGES,
) -> float:
    """Run every job of ``stages`` (default :data:`STAGES`), stage after stage, ``jobs``
    worker processes at a time (default: the processors this process may use) with
    :func:`replay.parallel.execute` (one job after the other in this process with ``jobs``
    1, or where no worker process can be started); report each job as it ends. The jobs
    are module-level functions. Returns the wall time, s.

    Raises
    ------
    RuntimeError
        Naming the job whose kernels failed to compile, with its error (the other workers
        are ended, and the later stages not run).
    KeyboardInterrupt
        Ctrl-C: the workers are ended at once.
    """
    started = time.perf_counter()
    total = sum(len(stage) for stage in stages)
    done = 0
    for stage in stages:

        def finished(index: int, took: float, stage=stage) -> None:
            nonlocal done
            done += 1
            report(f"  {stage[index][0]}: {took:.1f} s ({done} of {total})")

        execute(_compiled, None, stage, jobs, on_result=finished, unit="job", report=report)
    return time.perf_counter() - started


SLOW_SET_UP_S = 5.0
SLOW_SET_UP = (
    "still setting up: the first run on a machine compiles the numba kernels (about a minute,"
    " once; 'cathtrack compile' does it ahead, and make runs it after installing)"
)


class SlowSetUpNotice:
    """Reports :data:`SLOW_SET_UP`, once, when a block run under :meth:`during` (a
    command's set-up: its segmenter and filters, which load the kernels or compile them) is
    still running after ``after_s``."""

    def __init__(self, report: Callable[[str], None], after_s: float = SLOW_SET_UP_S) -> None:
        self.report = report
        self.after_s = after_s
        self.said = False

    @contextlib.contextmanager
    def during(self) -> Iterator[None]:
        timer = threading.Timer(self.after_s, self._say)
        timer.daemon = True
        timer.start()
        try:
            yield
        finally:
            timer.cancel()

    def _say(self) -> None:
        if not self.said:
            self.said = True
            self.report(SLOW_SET_UP)
