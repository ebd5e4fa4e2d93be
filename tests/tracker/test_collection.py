"""Garbage collection between frames (tracker.live.collection): the automatic collection
off and the start-up objects frozen while held, the generations CPython would have
collected run by ``collect()``, and in the live loop none inside a frame."""

from __future__ import annotations

import gc
import weakref

import pytest

from tests.tracker import live_common
from tests.tracker.live_common import reconstructor_of
from tracker.estimators import make_estimator
from tracker.live.collection import FrameCollection
from tracker.live.loop import LiveTracker
from tracker.live.sinks import MemorySink

noisy_session = live_common.noisy_session


class _Node:
    def __init__(self):
        self.other = self


def _cycles(n: int) -> list[weakref.ref]:
    """``n`` objects that only the cyclic collector frees, and weak references to them."""
    refs = []
    for _ in range(n):
        refs.append(weakref.ref(_Node()))
    return refs


@pytest.fixture
def thresholds():
    """Small thresholds for the test, CPython's own after it."""
    saved = gc.get_threshold()
    gc.set_threshold(50, 2, 2)
    yield
    gc.set_threshold(*saved)


def test_hold_turns_the_automatic_collection_off_and_release_puts_it_back():
    assert gc.isenabled() and gc.get_freeze_count() == 0
    outer, inner = FrameCollection(), FrameCollection()
    with outer:
        assert outer.held and not gc.isenabled() and gc.get_freeze_count() > 0
        with inner:  # nested: the last release restores
            assert not gc.isenabled()
        assert not inner.held and not gc.isenabled() and gc.get_freeze_count() > 0
    assert not outer.held and gc.isenabled() and gc.get_freeze_count() == 0
    outer.release()  # twice: nothing to do
    assert gc.isenabled()


def test_a_process_without_automatic_collection_is_left_without_it():
    gc.disable()
    try:
        with FrameCollection() as collection:
            assert collection.held and gc.get_freeze_count() > 0
        assert not gc.isenabled() and gc.get_freeze_count() == 0
    finally:
        gc.enable()


def test_collect_runs_the_generations_cpython_would_have_run(thresholds):
    collection = FrameCollection()
    assert collection.collect() is None  # not held: the automatic collection does it
    with collection:
        gc.collect()  # (not counted: a start from empty counts)
        assert collection.collect() is None  # nothing due
        generations, freed = [], []
        for _ in range(9):
            refs = _cycles(80)  # past the youngest generation's threshold (50)
            assert all(r() is not None for r in refs)  # nothing collected automatically
            generations.append(collection.collect())
            freed.append(all(r() is None for r in refs))
    # The middle generation after two of the youngest (its threshold: 2), the oldest after
    # two of the middle one.
    assert generations == [0, 0, 1, 0, 0, 1, 0, 0, 2]
    assert all(freed)
    assert collection.collections == [6, 2, 1]
    assert collection.took.values().size == 9
    assert "9 (6 / 2 / 1 by generation)" in collection.describe()
    assert FrameCollection().describe() == "none"
    off = FrameCollection(enabled=False)
    with off:
        assert gc.isenabled() and not off.held and off.collect() is None
    assert off.describe() is None


class _Garbage(MemorySink):
    """A sink on the loop's thread that makes cyclic garbage in every frame, and records
    whether a collection ran while a frame was being processed."""

    def __init__(self, per_frame: int):
        super().__init__()
        self.per_frame = per_frame
        self.in_frame = False
        self.collected_in_frame = 0
        self.collected = 0

    def handle(self, frame, observation, estimate, latency_s, status):
        super().handle(frame, observation, estimate, latency_s, status)
        self.in_frame = True
        _cycles(self.per_frame)
        self.in_frame = False

    def callback(self, phase, info):
        if phase == "start":
            self.collected += 1
            self.collected_in_frame += self.in_frame


@pytest.mark.parametrize("between_frames", [True, False])
def test_the_loop_collects_between_its_frames_only(noisy_session, between_frames):
    sink = _Garbage(per_frame=3 * gc.get_threshold()[0])
    tracker = LiveTracker(
        reconstructor_of(noisy_session),
        make_estimator("ukf", noisy_session.scene.catheter),
        [sink],
        collect_between_frames=between_frames,
    )
    gc.callbacks.append(sink.callback)
    try:
        summary = tracker.run(noisy_session.frames, max_frames=20, handle_signals=False)
    finally:
        gc.callbacks.remove(sink.callback)
    assert summary.frames_processed == 20
    assert gc.isenabled() and gc.get_freeze_count() == 0  # as before the run
    assert sink.collected >= 20  # every frame made more garbage than a generation holds
    lines = [line for line in summary.lines() if "garbage collected" in line]
    if between_frames:
        assert sink.collected_in_frame == 0
        assert sum(tracker.collection.collections) >= 20
        assert lines and lines[0].startswith("  garbage collected between frames: ")
    else:
        assert sink.collected_in_frame > 0  # what the collection between frames prevents
        assert not tracker.collection.enabled and not lines
