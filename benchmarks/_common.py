"""Shared by the benchmark scripts: run from a checkout without installing, and verdicts.

Importing this module puts the repository root on ``sys.path`` so that ``python
benchmarks/bench_*.py`` works from a plain checkout as well as from the project's venv.
"""

from __future__ import annotations

import functools
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def verdict(ok: bool) -> str:
    """PASS or MISS against a benchmark target."""
    return "PASS" if ok else "MISS"


@contextmanager
def busy_processes(n: int):
    """``n`` processes that spin for as long as the block runs (a CPU hog each)."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


@contextmanager
def slower(factor: float, methods):
    """A processor ``factor`` times slower for the calling thread's work in ``methods``.

    ``methods``: (class, name) pairs. While the block runs, each of these methods called by
    the thread that entered the block (other threads' calls are left as they are) spins,
    once it returns, until its thread CPU time is ``factor`` times what the call took: the
    extra holds the processor as slower work would, and a preemption meanwhile does not count
    as work. A call made inside another stretched call is stretched with it, once.
    """
    if factor <= 1.0:
        yield
        return
    thread = threading.get_ident()
    depth = [0]

    def stretch(function):
        @functools.wraps(function)
        def stretched(*args, **kwargs):
            if depth[0] or threading.get_ident() != thread:
                return function(*args, **kwargs)
            depth[0] += 1
            started = time.thread_time()
            try:
                return function(*args, **kwargs)
            finally:
                until = started + factor * (time.thread_time() - started)
                while time.thread_time() < until:
                    pass  # busy on purpose: the extra processor time of the slower machine
                depth[0] -= 1

        return stretched

    originals = [(owner, name, owner.__dict__[name]) for owner, name in methods]
    try:
        for owner, name, function in originals:
            setattr(owner, name, stretch(function))
        yield
    finally:
        for owner, name, function in originals:
            setattr(owner, name, function)
