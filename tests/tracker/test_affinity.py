"""The live loop's thread on a processor of its own (tracker/live/affinity.py)."""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from pathlib import Path

import pytest

from tracker.live.affinity import LoopAffinity

pytestmark = pytest.mark.skipif(
    not hasattr(os, "sched_setaffinity"), reason="processor affinity is Linux's"
)

ALLOWED = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set()


def _in_thread(work):
    """Run ``work()`` in a thread of its own (the loop's), return its result or raise."""
    out = {}

    def run():
        try:
            out["value"] = work()
        except BaseException as exc:  # re-raised in the test's thread
            out["error"] = exc

    thread = threading.Thread(target=run)
    thread.start()
    thread.join(30)
    if "error" in out:
        raise out["error"]
    return out["value"]


def _parked():
    """A thread that waits until told to end; (thread, its native id, the event)."""
    done = threading.Event()
    ready = threading.Event()
    ids = {}

    def park():
        ids["tid"] = threading.get_native_id()
        ready.set()
        done.wait(30)

    thread = threading.Thread(target=park)
    thread.start()
    ready.wait(30)
    return thread, ids["tid"], done


def test_one_processor_allowed_pins_nothing():
    affinity = LoopAffinity(allowed={min(ALLOWED)})
    assert affinity.loop_cpu is None
    assert not _in_thread(affinity.apply)
    assert not affinity.active
    assert os.sched_getaffinity(0) == ALLOWED


@pytest.mark.skipif(len(ALLOWED) < 2, reason="needs two processors to share out")
def test_the_loop_thread_gets_a_processor_and_everything_else_leaves_it():
    other, other_tid, other_done = _parked()
    capture, capture_tid, capture_done = _parked()
    child = multiprocessing.get_context("spawn").Process(target=_sleep_in_a_thread, args=(30,))
    child.start()
    child_threads = Path(f"/proc/{child.pid}/task")
    while len(os.listdir(child_threads)) < 2:  # its thread started
        time.sleep(0.01)
    affinity = LoopAffinity()
    loop_cpu, others = max(ALLOWED), set(ALLOWED) - {max(ALLOWED)}
    assert affinity.loop_cpu == loop_cpu and affinity.others == others

    def child_cpus():
        return [os.sched_getaffinity(int(tid)) for tid in os.listdir(child_threads)]

    def loop():
        assert affinity.apply(with_loop=(capture_tid, None))
        seen = {"loop": os.sched_getaffinity(0), "other": os.sched_getaffinity(other_tid),
                "capture": os.sched_getaffinity(capture_tid), "child": child_cpus()}  # fmt: skip
        # A thread the loop's thread starts inherits its processor until a sweep.
        late, late_tid, late_done = _parked()
        seen["late, before the sweep"] = os.sched_getaffinity(late_tid)
        affinity.sweep()
        seen["late, after the sweep"] = os.sched_getaffinity(late_tid)
        affinity.restore()
        seen["restored"] = {
            "loop": os.sched_getaffinity(0), "other": os.sched_getaffinity(other_tid),
            "capture": os.sched_getaffinity(capture_tid),
            "child": child_cpus(), "late": os.sched_getaffinity(late_tid),
        }  # fmt: skip
        late_done.set()
        late.join()
        return seen

    try:
        seen = _in_thread(loop)
    finally:
        for thread, done in ((other, other_done), (capture, capture_done)):
            done.set()
            thread.join()
        child.terminate()
        child.join()
    assert seen["loop"] == seen["capture"] == {loop_cpu}
    # Every thread of a child process: the demo's controller streams from one of its own.
    assert seen["other"] == others and seen["child"] == [others, others]
    assert seen["late, before the sweep"] == {loop_cpu}
    assert seen["late, after the sweep"] == others
    restored = seen.pop("restored")
    assert restored.pop("child") == [ALLOWED, ALLOWED]
    assert restored == dict.fromkeys(("loop", "other", "capture", "late"), ALLOWED)
    assert not affinity.active


def _sleep_in_a_thread(seconds):
    """A child process whose second thread sleeps (as the demo's controller streams)."""
    worker = threading.Thread(target=time.sleep, args=(seconds,))
    worker.start()
    worker.join()


@pytest.mark.skipif(len(ALLOWED) < 2, reason="needs two processors to share out")
def test_one_loop_of_a_process_is_pinned_at_a_time():
    first, second = LoopAffinity(), LoopAffinity()

    def loops():
        applied = [first.apply(), second.apply()]
        first.restore()
        applied.append(second.apply())
        second.restore()
        return applied, os.sched_getaffinity(0)

    applied, after = _in_thread(loops)
    assert applied == [True, False, True]
    assert after == ALLOWED and not first.active and not second.active
