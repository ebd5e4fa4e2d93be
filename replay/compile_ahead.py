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
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator


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


def _timed(job: Callable[[], None]) -> float:
    started = time.perf_counter()
    job()
    return time.perf_counter() - started


def _ignore_interrupts() -> None:
    """A job process leaves Ctrl-C to the caller, which ends it (a compilation interrupted
    inside LLVM would only print a traceback and go on)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def processors() -> int:
    """The processors this process may run on (its affinity where the system tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def compile_all(
    jobs: int | None = None,
    report: Callable[[str], None] = print,
    stages: tuple[tuple[tuple[str, Callable[[], None]], ...], ...] = STAGES,
) -> float:
    """Run every job of ``stages`` (default :data:`STAGES`), stage after stage, ``jobs``
    processes at a time (default: :func:`processors`); report each as it ends. The jobs are
    module-level functions, each run in a spawned process; one after the other in this
    process with ``jobs`` 1, or where no process can be started (said in a line). Returns
    the wall time, s.

    Raises
    ------
    RuntimeError
        Naming the job whose kernels failed to compile, with its error (the jobs not yet
        started are not run).
    KeyboardInterrupt
        Ctrl-C: the job processes are ended at once.
    """
    jobs = max(1, jobs or processors())
    started = time.perf_counter()
    pool = None
    if jobs > 1:
        # Spawned processes: each compiles in a fresh interpreter, as a first run would.
        widest = max(len(stage) for stage in stages)
        try:
            pool = multiprocessing.get_context("spawn").Pool(
                min(jobs, widest), initializer=_ignore_interrupts
            )
        except (OSError, ImportError) as exc:  # no semaphores, say (a locked-down container)
            report(f"  no job processes here ({exc}): one job after the other in this one")
    if pool is None:
        _in_this_process(stages, report)
        return time.perf_counter() - started
    try:
        _in_pool(pool, stages, report)
        pool.close()
    finally:
        pool.terminate()  # after close: the processes have ended; else they are ended
        pool.join()
    return time.perf_counter() - started


def _done(label: str, took: float, count: list[int], total: int, report) -> None:
    count[0] += 1
    report(f"  {label}: {took:.1f} s ({count[0]} of {total})")


def _in_this_process(stages, report) -> None:
    total, count = sum(len(stage) for stage in stages), [0]
    for stage in stages:
        for label, job in stage:
            try:
                took = _timed(job)
            except Exception as exc:
                raise RuntimeError(f"compiling {label} failed: {exc}") from exc
            _done(label, took, count, total, report)


def _in_pool(pool, stages, report) -> None:
    total, count = sum(len(stage) for stage in stages), [0]
    for stage in stages:
        pending = [(label, pool.apply_async(_timed, (job,))) for label, job in stage]
        while pending:
            ready = [item for item in pending if item[1].ready()]
            if not ready:
                time.sleep(0.05)
                continue
            for item in ready:
                pending.remove(item)
                label, result = item
                try:
                    took = result.get()
                except Exception as exc:
                    raise RuntimeError(f"compiling {label} failed: {exc}") from exc
                _done(label, took, count, total, report)


SLOW_SET_UP_S = 5.0
SLOW_SET_UP = (
    "still setting up: the first run on a machine compiles the numba kernels (about a minute,"
    " once; 'cathtrack compile' does it ahead, and make runs it after installing)"
)


@contextlib.contextmanager
def slow_set_up_notice(
    report: Callable[[str], None], after_s: float = SLOW_SET_UP_S
) -> Iterator[None]:
    """Report :data:`SLOW_SET_UP` once if the block (a command's set-up: its segmenter and
    filters, which load the kernels or compile them) is still running after ``after_s``."""
    timer = threading.Timer(after_s, report, args=(SLOW_SET_UP,))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
