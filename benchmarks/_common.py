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


@contextmanager
def timed_parts(parts, within):
    """Each frame's time in ``parts`` while the block runs: yields a dict, label -> list of
    per-frame sums, s.

    ``parts``: (label, owner, name) triples, ``owner`` a class or a module whose attribute
    ``name`` is the function to time. ``within``: the (class, name) of the method that is one
    frame (the live loop's step): only calls made inside it, by the thread that entered the
    block, count (a rehearsal between frames calls some of the same functions), and each
    frame's calls to one part are added up (a loop that segments both views calls the view's
    segmentation twice).
    """
    thread = threading.get_ident()
    frame: dict[str, float] | None = None
    sums: dict[str, list[float]] = {label: [] for label, _, _ in parts}  # labels may repeat

    def part(label, function):
        @functools.wraps(function)
        def timed(*args, **kwargs):
            if frame is None or threading.get_ident() != thread:
                return function(*args, **kwargs)
            started = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                frame[label] = frame.get(label, 0.0) + time.perf_counter() - started

        return timed

    def step(function):
        @functools.wraps(function)
        def one_frame(*args, **kwargs):
            nonlocal frame
            if frame is not None or threading.get_ident() != thread:
                return function(*args, **kwargs)
            frame = {}
            try:
                return function(*args, **kwargs)
            finally:
                if frame:  # a frame dropped before any part ran is not one
                    for label, values in sums.items():
                        values.append(frame.get(label, 0.0))
                frame = None

        return one_frame

    owner, name = within
    originals = [(o, n, o.__dict__[n]) for _, o, n in parts] + [(owner, name, owner.__dict__[name])]
    try:
        for label, o, n in parts:
            setattr(o, n, part(label, o.__dict__[n]))
        setattr(owner, name, step(owner.__dict__[name]))
        yield sums
    finally:
        for o, n, function in reversed(originals):
            setattr(o, n, function)
