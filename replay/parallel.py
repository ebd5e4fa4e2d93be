"""Running independent tasks in parallel, and one BLAS thread inside each task.

:func:`execute` maps ``function(settings, task)`` over tasks in this process, on a local
process pool or on a Dask cluster, and returns the results in task order, so that what the
tasks compute never depends on how many workers ran them. :func:`single_blas_thread` keeps the
linear algebra of a task on one thread (threadpoolctl), which is what tiny matrices want.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed

from threadpoolctl import threadpool_limits
from tqdm import tqdm

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
    """Local worker processes: the number of CPUs when not given."""
    return (os.cpu_count() or 1) if workers is None else int(workers)


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
) -> list:
    """``[function(settings, task) for task in tasks]`` in task order, run in parallel.

    Parameters
    ----------
    function : callable
        ``function(settings, task)``; picklable (a module-level function) for a pool or Dask.
    workers : int, optional
        Local worker processes (default: the number of CPUs; 1 runs in this process).
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://host:8786``) to run the tasks on instead.
    progress : bool
        Show a progress bar on stderr.
    on_result : callable, optional
        ``on_result(index, result)`` as each task finishes (in completion order), e.g. to keep
        what was done when a later task raises.
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
    if workers == 1 or len(tasks) <= 1:
        results = []
        with progress_bar() as bar:
            for i, task in enumerate(tasks):
                results.append(function(settings, task))
                done(i, results[-1])
                bar.update()
        return results
    with ProcessPoolExecutor(max_workers=min(workers, len(tasks))) as pool:
        # Submit before the bar exists: its monitor thread must not be alive when the pool
        # forks its workers.
        futures = {pool.submit(function, settings, task): i for i, task in enumerate(tasks)}
        results = [None] * len(tasks)
        with progress_bar() as bar:
            for future in as_completed(futures):
                i = futures[future]
                results[i] = future.result()
                done(i, results[i])
                bar.update()
        return results


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
