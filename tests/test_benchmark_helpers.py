"""The benchmarks' timing helpers (benchmarks/_common.py): what they time and what they leave.

The benchmark scripts print and assert nothing, so their helpers are tested here: a wrong
attribution would print a plausible table of wrong numbers.
"""

from __future__ import annotations

import importlib.util
import threading
import time
from pathlib import Path

import pytest

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "_common.py"
_spec = importlib.util.spec_from_file_location("bench_common", _PATH)
common = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(common)


def _spin(seconds: float) -> int:
    """Busy for ``seconds`` of this thread's processor time (at least as much wall time)."""
    until = time.thread_time() + seconds
    spins = 0
    while time.thread_time() < until:
        spins += 1
    return spins


class Loop:
    """A loop whose step calls its parts: ``a`` once, ``b`` twice; ``a`` also between steps."""

    def step(self, a_s: float, b_s: float, parts: bool = True) -> str:
        if parts:  # a step may end before its parts (a frame dropped on arrival)
            self.a(a_s)
            self.b(b_s)
            self.b(b_s)
        return "stepped"

    def a(self, seconds: float) -> None:
        _spin(seconds)

    def b(self, seconds: float) -> None:
        _spin(seconds)

    def between(self) -> None:
        self.a(0.02)


PARTS = (("a", Loop, "a"), ("b", Loop, "b"))


def test_a_frame_adds_up_its_calls_of_a_part_and_counts_nothing_outside_a_step():
    loop = Loop()
    with common.timed_parts(PARTS, (Loop, "step")) as sums:
        for a_s, b_s in ((0.002, 0.001), (0.004, 0.003)):
            loop.between()  # 20 ms of ``a`` outside a step: not a frame's
            assert loop.step(a_s, b_s) == "stepped"
            assert loop.step(a_s, b_s, parts=False) == "stepped"  # no part ran: no frame
    assert len(sums["a"]) == len(sums["b"]) == 2
    for (a_s, b_s), a, b in zip(
        ((0.002, 0.001), (0.004, 0.003)), sums["a"], sums["b"], strict=True
    ):
        assert a_s <= a < a_s + 0.015  # not the 20 ms between the steps
        assert 2 * b_s <= b < 2 * b_s + 0.015  # both calls of the frame


def test_a_repeated_label_adds_its_functions_and_another_threads_calls_do_not_count():
    loop = Loop()
    done = []
    both = (("a and b", Loop, "a"), ("a and b", Loop, "b"))
    with common.timed_parts(both, (Loop, "step")) as sums:
        loop.step(0.001, 0.002)
        other = threading.Thread(target=lambda: done.append(loop.step(0.02, 0.02)))
        other.start()
        other.join()
    assert done == ["stepped"]
    assert list(sums) == ["a and b"]
    assert len(sums["a and b"]) == 1  # the other thread's step is not a frame
    assert 0.005 <= sums["a and b"][0] < 0.04  # not the other thread's 60 ms


def test_the_functions_are_put_back_also_when_the_block_fails():
    originals = {name: Loop.__dict__[name] for name in ("step", "a", "b")}
    with pytest.raises(RuntimeError), common.timed_parts(PARTS, (Loop, "step")):
        assert Loop.__dict__["a"] is not originals["a"]
        raise RuntimeError("stop")
    assert {name: Loop.__dict__[name] for name in originals} == originals


def test_slower_stretches_the_calling_threads_work_by_its_factor():
    loop = Loop()
    with common.slower(3.0, ((Loop, "a"),)):
        started = time.thread_time()
        loop.a(0.01)
        took = time.thread_time() - started
    assert 0.03 <= took < 0.045
    started = time.thread_time()
    loop.a(0.01)  # put back
    assert time.thread_time() - started < 0.02
