"""Running independent tasks in parallel, and one BLAS thread inside each task.

:func:`execute` maps ``function(settings, task)`` over tasks in this process, on a local
process pool or on a Dask cluster, and returns the results in task order, so that what the
tasks compute never depends on how many workers ran them. :func:`single_blas_thread` keeps the
linear algebra of a task on one thread (threadpoolctl), which is what tiny matrices want.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

from threadpoolctl import threadpool_limits
from tqdm import tqdm

from tracker.live.affinity import usable_processors

__all__ = ["execute", "single_blas_thread", "worker_count"]

_blas_lock = threading.Lock()
_blas_users = 0
_blas_limits: threadpool_limits | None = None


@contextlib.contextmanager
def single_blas_thread() -> Iterator[None]:
    """Run the block with BLAS (and OpenMP) on one thread, then restore the previous counts.

    Tasks are parallel over processes; inside a task the linear algebra is on tiny matrices
    (the UKF factorises a 12 x 12 covariance per frame), where OpenBLAS's own threads only
    cost: on a 2-core machine shared with other work they made a UKF step 10 to 30 times
    slower (about 2 ms instead of 0.2 ms). Tasks running in threads of one process (a Dask
    worker) share the setting: the first one in sets it, the last one out restores it (nested
    ``threadpool_limits`` blocks left in another order would restore the wrong counts).
    """
    global _blas_users, _blas_limits
    with _blas_lock:
        if _blas_users == 0:
            _blas_limits = threadpool_limits(limits=1)
        _blas_users += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_users -= 1
            if _blas_users == 0 and _blas_limits is not None:
                _blas_limits.restore_original_limits()
                _blas_limits = None


def worker_count(workers: int | None) -> int:
    """Local worker processes: the processors this process may use when not given."""
    return usable_processors() if workers is None else int(workers)


def _ignore_interrupts() -> None:
    """A worker process leaves Ctrl-C to the caller, which ends it at once (a task inside a
    library's callback, numba's compiler say, would print a traceback and go on)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _end(pool: ProcessPoolExecutor) -> None:
    """End the pool's worker processes now, running tasks and all (Ctrl-C, or a task that
    raised: what the others would compute is not wanted), and wait until they have gone."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    for process in processes:
        process.terminate()
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.join()


def execute(
    function: Callable,
    settings: object,
    tasks: Sequence,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = False,
    description: str = "",
    on_result: Callable[[int, object], None] | None = None,
    unit: str = "task",
    report: Callable[[str], None] | None = None,
) -> list:
    """``[function(settings, task) for task in tasks]`` in task order, run in parallel.

    Parameters
    ----------
    function : callable
        ``function(settings, task)``; picklable (a module-level function) for a pool or Dask.
    workers : int, optional
        Local worker processes (default: the processors this process may use; 1 runs in
        this process, as do all where no worker process can be started: ``report`` says so).
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://host:8786``) to run the tasks on instead.
    progress : bool
        Show a progress bar on stderr.
    on_result : callable, optional
        ``on_result(index, result)`` as each task finishes (in completion order), e.g. to keep
        what was done when a later task raises.
    report : callable, optional
        Takes the line that says the tasks run in this process for want of worker processes
        (default: stderr).

    A task that raises ends the local workers at once and is raised here; so does Ctrl-C
    (the workers ignore it themselves).
    """
    workers = worker_count(workers)
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")

    def done(index: int, result: object) -> None:
        if on_result is not None:
            on_result(index, result)

    def progress_bar() -> tqdm:
        return tqdm(
            total=len(tasks),
            desc=description,
            unit=unit,
            disable=not progress,
            file=sys.stderr,
            dynamic_ncols=True,
        )

    if scheduler:
        with progress_bar() as bar:
            return _execute_dask(function, settings, tasks, scheduler, bar, done)
    pool = None
    if workers > 1 and len(tasks) > 1:
        try:
            pool = ProcessPoolExecutor(
                max_workers=min(workers, len(tasks)), initializer=_ignore_interrupts
            )
        except OSError as exc:  # no semaphores (a locked-down container, say)
            (report or _report_stderr)(
                f"no worker processes here ({exc}): the {unit}s run one after the other in"
                " this process"
            )
    if pool is None:
        results = []
        with progress_bar() as bar:
            for i, task in enumerate(tasks):
                results.append(function(settings, task))
                done(i, results[-1])
                bar.update()
        return results
    try:
        # Submit before the bar exists: its monitor thread must not be alive when the pool
        # forks its workers.
        futures = {pool.submit(function, settings, task): i for i, task in enumerate(tasks)}
        results = [None] * len(tasks)
        pending = set(futures)
        with progress_bar() as bar:
            while pending:
                # A timeout, so that this thread runs Python often: a Ctrl-C that the system
                # handed to another thread is raised here within it, not after a long task.
                finished, pending = wait(pending, timeout=0.1, return_when=FIRST_COMPLETED)
                for future in finished:
                    i = futures[future]
                    results[i] = future.result()
                    done(i, results[i])
                    bar.update()
    except BaseException:
        _end(pool)
        raise
    pool.shutdown()
    return results


def _report_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _execute_dask(
    function: Callable, settings: object, tasks: Sequence, scheduler: str, bar, done: Callable
) -> list:
    # Imported here: dask.distributed takes a third of a second to import, and only this path
    # needs it.
    try:
        from dask.distributed import Client
        from dask.distributed import as_completed as dask_completed
    except ImportError as exc:  # pragma: no cover - dask is a dependency
        raise ValueError("--scheduler needs dask.distributed installed") from exc
    try:
        client = Client(scheduler, set_as_default=False, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise ValueError(f"cannot connect to the Dask scheduler at {scheduler}: {exc}") from exc
    try:
        futures = client.map(function, [settings] * len(tasks), tasks, pure=False)
        index = {future.key: i for i, future in enumerate(futures)}
        results = [None] * len(tasks)
        for future in dask_completed(futures, loop=client.loop):
            i = index[future.key]
            results[i] = future.result()
            done(i, results[i])
            bar.update()
        return results
    finally:
        client.close()
