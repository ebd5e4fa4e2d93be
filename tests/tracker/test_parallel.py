"""The views segmented side by side (tracker.vision.parallel): the same results as one
process, bit for bit, and a worker that fails never stops the caller."""

from __future__ import annotations

import os
import signal
from multiprocessing import shared_memory

import numpy as np
import pytest

from tests.tracker.segmentation_common import (
    assert_same,
    assert_same_views,
    flickering_scene,
)
from tracker.vision import parallel, worker_lag
from tracker.vision.pair import PairSegmenter
from tracker.vision.parallel import MAX_POINTS, ParallelPairSegmenter, pair_segmenter

N_PAIRS = 14


@pytest.fixture(scope="module")
def setup():
    catheter, scene, renderer = flickering_scene(3, 0.3)
    rng = np.random.default_rng(3)
    qs = np.column_stack(
        [np.linspace(0, 1, N_PAIRS), np.linspace(0.8, -0.6, N_PAIRS), np.full(N_PAIRS, 0.7)]
    )
    pairs = [renderer.render(q, 0.4, rng).images for q in qs]
    return catheter, scene, renderer, pairs


def make(setup, kind, **kwargs):
    catheter, scene, renderer, _ = setup
    return kind(catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, renderer.backgrounds, **kwargs)


def regions(setup, k):
    """What the loop passes: none, the last frame's centreline, or many points."""
    _, scene, _, pairs = setup
    if k % 3 == 0:
        return None
    if k % 3 == 1:
        return (None, np.array([[300.0, 200.0], [340.0, 260.0]]))
    # More points than go through the shared memory as they are: their box does.
    rng = np.random.default_rng(k)
    many = rng.uniform([250, 150], [400, 330], size=(MAX_POINTS + 40, 2))
    many[5] = np.nan
    return (many, many + 3.0)


def run_frames(segmenter, setup, rehearse=True, before_settle=None):
    """Segment the pairs as the live loop does; each result's comparable parts."""
    pairs = setup[3]
    out = []
    for k, images in enumerate(pairs):
        if rehearse and k:
            segmenter.rehearse(pairs[k - 1], regions(setup, k))
        if k == 8:
            segmenter.reset()
        seg = segmenter.segment(images, regions(setup, k), settle=k % 2 == 0)
        if before_settle is not None:
            before_settle(segmenter, k)
        segmenter.settle()
        out.append(seg)
    return out


def assert_same_results(expected, got):
    """Frame by frame, the views first (the combined rows follow from them), then the rows;
    a difference names its frame, view and field."""
    for k, (a, b) in enumerate(zip(expected, got, strict=True)):
        for v, (va, vb) in enumerate(zip(a.views, b.views, strict=True)):
            assert_same_views(va, vb, f"frame {k}, view {v}")
        rows = zip((*a.uv, *a.cov, a.rejected), (*b.uv, *b.cov, b.rejected), strict=True)
        names = [f"uv[{v}]" for v in range(len(a.uv))] + [f"cov[{v}]" for v in range(len(a.cov))]
        for name, (x, y) in zip([*names, "rejected"], rows, strict=True):
            assert_same(x, y, f"frame {k}, {name}")
        assert a.tip_refined == b.tip_refined, f"frame {k}"


def test_the_worker_gives_what_one_process_gives_bit_for_bit(setup):
    """Every field of every view, the rows and the epipolar rejections, over frames that
    flicker and vibrate, rehearsed, settled now or later, with a reset midway and regions
    of every kind; and the background models end the same."""
    reference = make(setup, PairSegmenter)
    with make(setup, ParallelPairSegmenter) as worked:
        assert worked.parallel
        expected, got = run_frames(reference, setup), run_frames(worked, setup)
        assert worked.parallel, worked.worker_failure  # the worker did them all
        assert worked.moves == 0 and worked.frames_here == 0
        assert_same_results(expected, got)
        backgrounds = worked.backgrounds
    assert np.isfinite(np.concatenate([np.ravel(s.uv) for s in expected])).mean() > 0.9
    assert not np.array_equal(reference.backgrounds[1], setup[2].backgrounds[1])  # updated
    for a, b in zip(reference.backgrounds, backgrounds, strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_callers_work_runs_once_between_its_own_view_and_the_workers_answer(setup):
    """``meanwhile`` runs once a frame, after this process's view and before the worker's
    answer is taken (in one process, before the views are combined); the results are those
    of a segmentation without it, and work that raises leaves the worker in step."""
    pairs = setup[3]
    reference, alone = make(setup, PairSegmenter), make(setup, PairSegmenter)
    with make(setup, ParallelPairSegmenter) as worked:
        events = []
        answer = worked._answer
        worked._answer = lambda *a: events.append("answer") or answer(*a)
        camera = worked.local.cameras[0]
        own = camera.segment
        camera.segment = lambda *a, **kw: events.append("own view") or own(*a, **kw)
        calls = []
        for k in range(4):
            expected = reference.segment(pairs[k], regions(setup, k))
            got = worked.segment(
                pairs[k], regions(setup, k), meanwhile=lambda: events.append("meanwhile")
            )
            assert_same_results([expected], [got])
            got = alone.segment(pairs[k], regions(setup, k), meanwhile=lambda k=k: calls.append(k))
            assert_same_results([expected], [got])
        assert events == ["own view", "meanwhile", "answer"] * 4
        assert calls == [0, 1, 2, 3]
        assert worked.parallel and worked.frames_here == 0

        def fails():
            raise RuntimeError("the caller's work failed")

        reference.segment(pairs[4])
        with pytest.raises(RuntimeError, match="the caller's work failed"):
            worked.segment(pairs[4], meanwhile=fails)
        assert_same_results([reference.segment(pairs[5])], [worked.segment(pairs[5])])
        assert worked.parallel, worked.worker_failure


def test_a_worker_that_dies_is_reported_once_and_its_views_are_segmented_here(setup):
    pairs = setup[3]
    lines = []
    with make(setup, ParallelPairSegmenter, report=lines.append) as segmenter:
        segmenter.segment(pairs[0])
        os.kill(segmenter._process.pid, signal.SIGKILL)
        segmenter._process.join(5.0)
        results = [segmenter.segment(images) for images in pairs[1:5]]
        assert not segmenter.parallel
    assert len(lines) == 1
    assert "worker stopped" in lines[0] and "exit code -9" in lines[0]
    assert "side segmented in this process from now on" in lines[0]
    for seg in results:  # every frame answered, the dead worker's view included
        assert np.isfinite(seg.views[1].tip_px).all()
        assert np.isfinite(seg.uv[1][0]).all()


class _NoProcesses:
    """A multiprocessing context that cannot start a process."""

    def Pipe(self, duplex=True):  # noqa: N802 (multiprocessing's name)
        import multiprocessing

        return multiprocessing.Pipe(duplex)

    def Process(self, **kwargs):  # noqa: N802
        class Failing:
            pid = None

            def start(self):
                raise OSError("no more processes")

            def is_alive(self):
                return False

        return Failing()


def test_a_worker_that_cannot_start_leaves_every_view_here_with_the_same_results(
    setup, monkeypatch
):
    monkeypatch.setattr(parallel.multiprocessing, "get_context", lambda _: _NoProcesses())
    lines = []
    with make(setup, ParallelPairSegmenter, report=lines.append) as segmenter:
        assert not segmenter.parallel
        got = run_frames(segmenter, setup)
    assert len(lines) == 1 and "did not start (no more processes)" in lines[0]
    expected = run_frames(make(setup, PairSegmenter), setup)
    for a, b in zip(expected, got, strict=True):
        for x, y in zip((*a.uv, *a.cov), (*b.uv, *b.cov), strict=True):
            assert_same(x, y)


def test_bad_input_raises_as_in_one_process_and_the_worker_stays_in_step(setup):
    pairs = setup[3]
    reference = make(setup, PairSegmenter)
    with make(setup, ParallelPairSegmenter) as segmenter:
        for bad in (
            (pairs[0][0],),
            (pairs[0][0], pairs[0][1][:-1]),
            (pairs[0][0][:, 1:], pairs[0][1]),
        ):
            with pytest.raises(ValueError) as expected:
                reference.segment(bad)
            with pytest.raises(ValueError) as got:
                segmenter.segment(bad)
            assert str(got.value) == str(expected.value)
        # The first view failed in this process while the worker segmented the second: its
        # answer was taken then, and the next frame gets its own.
        seg = segmenter.segment(pairs[1])
        assert segmenter.parallel
        assert np.isfinite(seg.views[1].tip_px).all()


def test_an_error_that_does_not_pickle_reaches_the_caller_as_its_text():
    class Unpicklable(ValueError):
        def __reduce__(self):
            raise TypeError("no")

    memory = shared_memory.SharedMemory(create=True, size=parallel._Shared.size([(4, 4)]))
    try:
        shared = parallel._Shared(memory, [(4, 4)])
        parallel._answer_with(shared, 7, ("error", Unpicklable("bad frame")))
        assert shared.control[parallel._ANSWER] == 7
        n = int(shared.control[parallel._ANSWER_BYTES])
        kind, error = parallel.pickle.loads(shared.answer[:n])
        assert kind == "error" and isinstance(error, RuntimeError)
        assert str(error) == "Unpicklable: bad frame"
        shared.release()
    finally:
        memory.close()
        memory.unlink()


def test_close_stops_the_worker_frees_the_memory_and_later_frames_are_done_here(setup):
    pairs = setup[3]
    segmenter = make(setup, ParallelPairSegmenter)
    process, name = segmenter._process, segmenter._memory.name
    segmenter.segment(pairs[0])
    segmenter.close()
    segmenter.close()  # nothing happens twice
    assert not process.is_alive() and process.exitcode == 0  # stopped, not killed
    with pytest.raises(FileNotFoundError):
        shared_memory.SharedMemory(name)
    assert segmenter.worker_failure == "closed"
    seg = segmenter.segment(pairs[1])
    assert np.isfinite(seg.views[1].tip_px).all()


def test_the_loop_gets_a_worker_only_with_two_processors(setup, monkeypatch):
    one = make(setup, pair_segmenter, parallel=False)
    assert type(one) is PairSegmenter
    one.close()  # nothing to release, but there
    monkeypatch.setattr(parallel, "parallel_possible", lambda: False)
    assert type(make(setup, pair_segmenter)) is PairSegmenter
    monkeypatch.setattr(parallel, "parallel_possible", lambda: True)
    with make(setup, pair_segmenter) as two:
        assert type(two) is ParallelPairSegmenter and two.parallel


@pytest.mark.parametrize("n", [0, 3, MAX_POINTS, MAX_POINTS + 1, 500])
def test_predicted_points_reach_the_worker_with_the_search_box_they_make(n):
    """As they are up to MAX_POINTS; beyond, as the corners of their finite points' box,
    which is all the segmentation takes from them (the extremes here are the last points,
    and some points are not finite)."""
    from tracker.vision.detection import search_box

    rng = np.random.default_rng(n)
    points = rng.uniform([200, 100], [300, 200], size=(n, 2))
    if n:
        points[-1] = (20.0, 450.0)
        points[0, 1] = np.inf
    out = np.zeros((MAX_POINTS, 2))
    count = parallel._put_points(points, out)
    taken = out[:count]
    if n <= MAX_POINTS:
        np.testing.assert_array_equal(taken, points)
    assert search_box(taken, 40.0, (480, 640)) == search_box(points, 40.0, (480, 640))
    assert parallel._put_points(None, out) == -1
    nan = np.full((MAX_POINTS + 5, 2), np.nan)
    count = parallel._put_points(nan, out)
    assert search_box(out[:count], 40.0, (480, 640)) == (0, 0, 640, 480)


def test_a_worker_that_hangs_is_ended_after_the_timeout_and_its_views_are_done_here(
    setup, monkeypatch
):
    monkeypatch.setattr(parallel, "ANSWER_TIMEOUT_S", 0.3)
    pairs = setup[3]
    lines = []
    with make(setup, ParallelPairSegmenter, report=lines.append) as segmenter:
        segmenter.segment(pairs[0])
        process = segmenter._process
        os.kill(process.pid, signal.SIGSTOP)
        seg = segmenter.segment(pairs[1])
        assert not segmenter.parallel and not process.is_alive()
        assert np.isfinite(seg.views[1].tip_px).all()
    assert len(lines) == 1 and "no answer within 0.3 s" in lines[0]


def test_a_reset_is_taken_up_by_the_worker_before_the_next_request(setup):
    """A request the worker has not read yet is replaced by the next one: a reset waits for
    the worker's answer, so that a frame right after it cannot replace it."""
    pairs = setup[3]
    with make(setup, ParallelPairSegmenter) as segmenter:
        segmenter.segment(pairs[0])
        segmenter.reset()
        control = segmenter._shared.control
        assert control[parallel._ANSWER] == segmenter._seq
        seq, kind, _ = parallel.request_of(int(control[parallel._REQUEST]))
        assert seq == segmenter._seq and kind == parallel._RESET
        segmenter.segment(pairs[1])
        assert segmenter.parallel


def test_views_moved_here_and_back_with_their_state_give_the_same_results(setup):
    """A worker held up gives its views to the caller between frames, and takes them back
    later: their background models, regions and noise go along, so that every frame is
    segmented as one process would, bit for bit."""

    def move(segmenter, k):
        if k == 4:  # as when the worker kept the caller waiting in half the last frames
            segmenter._move_here = True
        if k == 9:
            assert segmenter.here
            segmenter._here_since = -np.inf  # RETRY_S ago

    reference = make(setup, PairSegmenter)
    with make(setup, ParallelPairSegmenter) as worked:
        expected = run_frames(reference, setup)
        got = run_frames(worked, setup, before_settle=move)
        assert worked.parallel and not worked.here
        assert worked.moves == 1 and worked.frames_here == 5  # frames 5 to 9
        assert_same_results(expected, got)
        backgrounds = worked.backgrounds
    for a, b in zip(reference.backgrounds, backgrounds, strict=True):
        np.testing.assert_array_equal(a, b)


_add_frame = worker_lag.LagWatch.add


def counting_every_wait(self, own_s, wait_s):
    """LagWatch.add with every wait lagged (with LAG_S < 0: longer than a view of no time)."""
    return _add_frame(self, -1.0, wait_s)


@pytest.mark.parametrize("deferred", [True, False])
def test_a_worker_that_keeps_the_caller_waiting_hands_its_views_over(setup, monkeypatch, deferred):
    """Waits that count as lagged (worker_lag.LagWatch; here: every wait) in LAG_COUNT of
    the last LAG_FRAMES frames move the views here between frames: at the next settle, or at
    the end of a frame segmented with settle=True; they go back RETRY_S later, twice as long
    after the next move."""
    monkeypatch.setattr(worker_lag, "LAG_S", -1.0)
    monkeypatch.setattr(worker_lag.LagWatch, "add", counting_every_wait)
    pairs = setup[3]
    with make(setup, ParallelPairSegmenter) as segmenter:

        def frame(k):
            segmenter.segment(pairs[k % len(pairs)], settle=not deferred)
            if deferred:
                segmenter.settle()

        for k in range(worker_lag.GRACE_FRAMES + worker_lag.LAG_COUNT):
            assert not segmenter.here
            frame(k)
        assert segmenter.here and segmenter.moves == 1
        seg = segmenter.segment(pairs[0])
        assert np.isfinite(seg.views[1].tip_px).all() and segmenter.frames_here == 1
        assert segmenter._retry_s == parallel.RETRY_S
        segmenter._here_since -= parallel.RETRY_S + 1.0
        frame(0)  # back to the worker...
        assert not segmenter.here
        for k in range(worker_lag.GRACE_FRAMES + worker_lag.LAG_COUNT):  # ...held up again
            frame(k)
        assert segmenter.here and segmenter.moves == 2
        assert segmenter._retry_s == 2 * parallel.RETRY_S


def test_the_user_is_told_whether_the_views_were_segmented_side_by_side(setup):
    with make(setup, ParallelPairSegmenter) as segmenter:
        assert segmenter.describe() == "yes"
        segmenter.moves, segmenter.frames_here, segmenter.frames = 2, 30, 300
        assert segmenter.describe() == (
            "yes, but 30 of 300 frames in the loop's process (the worker held up by other"
            " work: 2 times)"
        )
    assert segmenter.describe() == "no (closed)"


def test_a_due_move_waits_for_settle_not_for_the_priming(setup):
    """The loop rehearses just before a frame is due: a move (about 10 ms) then would hold the
    frame up, so it waits for settle(), after the estimate has left."""
    pairs = setup[3]
    with make(setup, ParallelPairSegmenter) as segmenter:
        segmenter.segment(pairs[0], settle=False)
        segmenter._move_here = True
        segmenter.rehearse(pairs[0])
        assert not segmenter.here and segmenter.moves == 0
        segmenter.settle()
        assert segmenter.here and segmenter.moves == 1


class _PostingControl:
    """The control words, with the caller posting ``then`` (a request word) just after the
    worker's ``after``-th read of the request ``word``: a frame's request that comes while
    the worker takes up a rehearsal."""

    def __init__(self, control, word: int, after: int, then: int) -> None:
        self.control, self.word, self.after, self.then = control, word, after, then
        self.reads = 0

    def __getitem__(self, index):
        value = self.control[index]
        if index == parallel._REQUEST and int(value) == self.word:
            self.reads += 1
            if self.reads == self.after:
                self.control[parallel._REQUEST] = self.then
        return value

    def __setitem__(self, index, value):
        self.control[index] = value


class _RecordingCamera:
    """A worker's camera that records what it is asked to do (the image's first pixel
    says which frame)."""

    def __init__(self) -> None:
        self.calls = []

    def segment(self, image, points, settle=True):
        self.calls.append(("segment", int(image[0, 0])))
        return int(image[0, 0])

    def rehearse(self, image, points, abandon=None):
        # Whether the frame has come, asked twice (as the stages of a view would).
        self.calls.append(("rehearse", int(image[0, 0])))
        self.asked = [abandon(), abandon()]
        return not self.asked[-1]

    def in_camera_frame(self, seg):
        return seg

    def settle(self):
        self.calls.append(("settle", None))


def test_a_request_word_holds_every_kind_and_slot_whatever_its_number():
    kinds = (parallel._SEGMENT, parallel._REHEARSE, parallel._RESET, parallel._BACKGROUNDS,
             parallel._STOP, parallel._HAND_OVER, parallel._TAKE_BACK)
    for seq in (0, 1, 255, 256, 2**40 + 3):
        for kind in kinds:
            for slot in range(parallel._SLOTS):
                word = parallel.request_word(seq, kind, slot)
                assert parallel.request_of(word) == (seq, kind, slot)
                assert word < 2**63  # an int64 control word


@pytest.mark.parametrize("after", [1, 2, 3])
def test_a_frame_posted_while_the_worker_takes_up_a_rehearsal_is_segmented_once(after):
    """The caller posts a rehearsal and, without waiting, the frame: whenever the frame's
    request lands while the worker reads the rehearsal's, the worker segments the frame
    once, the frame's image, and answers with the frame's number (the request was three
    words once: read between them, a frame was segmented twice and its background model
    updated twice); a rehearsal under way is told the frame has come."""
    import threading

    from tracker.live.priority import FramePriority

    shapes = [(4, 4)]
    memory = shared_memory.SharedMemory(create=True, size=parallel._Shared.size(shapes))
    caller, worker = parallel.multiprocessing.Pipe()
    try:
        shared = parallel._Shared(memory, shapes)
        shared.slots[0][0][:] = 10  # the rehearsal's image (the last frame's)...
        shared.slots[0][1][:] = 20  # ...and the frame's
        shared.control[parallel._COUNTS] = -1  # no points
        rehearsal = parallel.request_word(1, parallel._REHEARSE, 0)
        frame = parallel.request_word(2, parallel._SEGMENT, 1)
        shared.control = _PostingControl(shared.control, rehearsal, after, frame)
        camera = _RecordingCamera()
        collection = type("Collection", (), {"collect": lambda self: None})()
        thread = threading.Thread(
            target=parallel._work,
            args=(worker, shared, [camera], None, 0.0, collection, FramePriority(False)),
            daemon=True,
        )
        thread.start()
        assert caller.poll(5.0)  # ready
        caller.recv_bytes()
        shared.control[parallel._REQUEST] = rehearsal
        caller.send_bytes(b"")
        deadline = parallel.time.monotonic() + 5.0
        while shared.control[parallel._ANSWER] != 2 and parallel.time.monotonic() < deadline:
            parallel.time.sleep(0.001)
        assert shared.control[parallel._ANSWER] == 2
        segments = [c for c in camera.calls if c[0] == "segment"]
        assert segments == [("segment", 20)]
        assert all(image == 10 for kind, image in camera.calls if kind == "rehearse")
        # A rehearsal taken up is told to stop as soon as the frame's request is there.
        rehearsed = any(kind == "rehearse" for kind, _ in camera.calls)
        assert rehearsed == (after > 1)
        if rehearsed:
            assert camera.asked == ([True, True] if after == 2 else [False, True])
        stop = parallel.request_word(3, parallel._STOP, 0)
        shared.control[parallel._REQUEST] = stop
        caller.send_bytes(b"")
        thread.join(5.0)
        assert not thread.is_alive()
    finally:
        caller.close()
        worker.close()
        shared.control = shared.control.control
        shared.release()
        memory.close()
        memory.unlink()
