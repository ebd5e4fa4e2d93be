"""The views of a frame segmented side by side, on two processors (docs/live.md).

A pair's two views are independent until :func:`tracker.vision.pair.combine_views` puts
them together, and each view's state over time (its background model, its region of
interest) belongs to its camera alone (:class:`tracker.vision.background.CameraSegmenter`).
:class:`ParallelPairSegmenter` therefore segments the first view in the calling process and
the others in a worker process of their own, at the same time, and combines them where the
caller is: on the 2-core development machine a pair then costs the caller its own view, the
copy of the other's image and the combination (about a quarter less than both views, in
``benchmarks/bench_latency.py`` and ``cathtrack demo``; docs/live.md). Python threads would
not do: the views' Python would take turns on the interpreter lock.

Requests, images (two slots per view, used in turn) and answers (the views as a record,
:mod:`tracker.vision.view_record`; anything else pickled) go through shared memory, each
marked done by a sequence number written last; a pipe wakes the side that waits. Every
request but a rehearsal waits for its answer, so that the next can only replace a rehearsal
the worker has not taken up yet (which then does not happen: it changes nothing). The
caller polls for an answer (up to :data:`SPIN_S`) before it blocks: a blocked thread on a
busy machine waits for a time slice of whatever else runs on its processor once woken. The
worker blocks between requests, at a real-time priority where permitted (woken, it runs at
once), else polling for a while after a rehearsal. The results are those of :class:`PairSegmenter`
on the same frames, bit for bit (``tests/tracker/test_parallel.py``). A worker that fails
to start, dies or stops answering is reported once and its views are segmented in the
calling process from then on (their background models started again from the backgrounds
given): the caller never stops for it. A worker that keeps the caller waiting (another
process on its processor) hands its views over between frames, and takes them back later.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import pickle
import signal
import sys
import time
import weakref
from collections.abc import Callable, Sequence
from multiprocessing import shared_memory

import numpy as np

from models.catheter import Catheter
from models.imaging import Rig
from tracker.live.affinity import usable_processors
from tracker.live.collection import FrameCollection
from tracker.live.priority import FramePriority
from tracker.vision.pair import PairSegmentation, PairSegmenter, combine_views
from tracker.vision.segmentation import ViewSegmentation
from tracker.vision.settings import DEFAULT_SETTINGS, SegmentationSettings, check_image
from tracker.vision.view_record import read_views, write_views
from tracker.vision.worker_lag import LagWatch

Array = np.ndarray

START_TIMEOUT_S = 120.0  # a worker's start: imports and kernels loaded (compiled, the first time)
ANSWER_TIMEOUT_S = 2.0  # a worker that takes longer over one request is taken for hung
# How long the caller polls for an answer before it blocks, s: a blocked caller on a busy
# machine waits for its processor again when the answer comes (a time slice of the other
# process there), which costs more than polling.
SPIN_S = 0.02
# How long the worker polls for the frame after a rehearsal before it blocks, s, where it may
# not wait at a real-time priority: the frame is due some 3 ms later, and a worker that blocks
# at the ordinary priority must then wait its turn on a processor that the loop's other
# threads and processes share. Where it may, it blocks at that priority (:func:`_work`).
REHEARSAL_SPIN_S = 0.02
MAX_POINTS = 64  # predicted points per view passed as they are (more: their bounding box)
_SLOTS = 2  # image slots per view: a request never writes the slot of the one before
# The control words in the shared memory (int64), then each worker view's point count. A
# request is one word (request_word): its sequence number, kind and image slot in one store.
_REQUEST, _ANSWER, _ANSWER_BYTES, _ANSWER_VIEWS = range(4)
_COUNTS = 8
_SEGMENT, _REHEARSE, _RESET, _BACKGROUNDS, _STOP, _HAND_OVER, _TAKE_BACK = range(1, 8)
# A worker that keeps the caller waiting longer than a view of its own gives its views back
# (:class:`tracker.vision.worker_lag.LagWatch`). They go to the worker again RETRY_S later,
# twice as long after each move (up to MAX_RETRY_S).
RETRY_S = 30.0
MAX_RETRY_S = 600.0


def _report_stderr(message: str) -> None:
    print(f"segmentation: {message}", file=sys.stderr, flush=True)


def parallel_possible() -> bool:
    """Whether this process may use two processors or more (a worker then has one)."""
    return usable_processors() >= 2


class WorkerStopped(RuntimeError):
    """The segmentation worker did not answer (it died, hung or could not start)."""


class _Shared:
    """The shared memory's parts: control words, predicted points, image slots, answer."""

    def __init__(self, memory: shared_memory.SharedMemory, shapes) -> None:
        n = len(shapes)
        buf = memory.buf
        self.control = np.ndarray(_COUNTS + n, np.int64, buf, 0)
        offset = self.control.nbytes
        self.points = np.ndarray((n, MAX_POINTS, 2), np.float64, buf, offset)
        offset += self.points.nbytes
        self.slots = []
        for h, w in shapes:
            self.slots.append(
                [np.ndarray((h, w), np.uint8, buf, offset + s * h * w) for s in range(_SLOTS)]
            )
            offset += _SLOTS * h * w
        offset += -offset % 8  # the answer's views as float64 (view_record), aligned
        self.answer = np.ndarray(len(buf) - offset, np.uint8, buf, offset)
        self.record = np.ndarray(self.answer.size // 8, np.float64, buf, offset)

    @staticmethod
    def size(shapes) -> int:
        images = sum(h * w for h, w in shapes)
        n = len(shapes)
        return 8 * (_COUNTS + n) + 16 * MAX_POINTS * n + _SLOTS * images + images + (1 << 20) + 8

    def release(self) -> None:
        """Drop the arrays (the memory closes only once none is left)."""
        self.control = self.points = self.answer = self.record = None
        self.slots = []


class ParallelPairSegmenter:
    """:class:`tracker.vision.pair.PairSegmenter`'s work, the views after the first in a
    worker process.

    Same parameters, methods and results as :class:`PairSegmenter` (``segment``,
    ``settle``, ``rehearse``, ``reset``, ``frame``, ``backgrounds``, ``base_px``), plus
    :meth:`close` (also a context manager). Making it starts the worker and waits until it
    has loaded the segmentation's kernels (a second or two).

    Parameters
    ----------
    catheter, rig, R_w_b, o_b_w_mm, backgrounds, settings
        As for :class:`PairSegmenter`.
    report : callable, optional
        Receives one line when the worker fails and its views move to this process
        (default: standard error).
    poll_s, worker_poll_s : float
        How long the caller polls for an answer, and the worker for the frame after a
        rehearsal, before they block, s (:data:`SPIN_S`, :data:`REHEARSAL_SPIN_S`).
    realtime : bool
        The worker segments each frame, from the request to its answer, at a real-time
        priority where permitted (:class:`~tracker.live.priority.FramePriority`).

    Attributes
    ----------
    worker_failure : str or None
        Why the worker's views are segmented in this process, if they are.
    """

    def __init__(
        self,
        catheter: Catheter,
        rig: Rig,
        R_w_b: Array,
        o_b_w_mm: Array,
        backgrounds: Sequence[Array],
        settings: SegmentationSettings = DEFAULT_SETTINGS,
        *,
        report: Callable[[str], None] = _report_stderr,
        poll_s: float = SPIN_S,
        worker_poll_s: float = REHEARSAL_SPIN_S,
        realtime: bool = True,
    ) -> None:
        # Here first: the kernels are compiled and cached (a fresh machine) before the
        # worker loads them. Its cameras after the first are the fallback.
        self.local = PairSegmenter(catheter, rig, R_w_b, o_b_w_mm, backgrounds, settings)
        self.rig = rig
        self.segmenter = self.local.segmenter
        self.report = report
        self.poll_s = float(poll_s)
        self._worker_poll_s = float(worker_poll_s)
        self._realtime = bool(realtime)
        self.worker_failure: str | None = None
        self._remote = tuple(range(1, rig.n_views))  # the worker's views
        self._shapes = tuple(self.local.cameras[v].background.image.shape for v in self._remote)
        self._slot = 0  # the slot of the images last written
        self._written: tuple = ()  # the image arrays last written there
        self._seq = 0  # of the last request
        self._bells = 0  # answers whose wake-up signal may wait in the pipe
        self.here = False  # the worker's views segmented here for now (it kept us waiting)
        self._here_since = 0.0
        self._retry_s = RETRY_S
        self._lag = LagWatch()
        self._move_here = False
        self.moves = 0  # times the views came here
        self.frames = self.frames_here = 0
        self._process = self._bell = self._memory = self._shared = None
        if not self._remote:
            self.worker_failure = "one view only"
        else:
            try:
                self._start(catheter, rig, R_w_b, o_b_w_mm, backgrounds, settings)
            except Exception as exc:  # noqa: BLE001 (any failure: the views are done here)
                self._fail(f"the segmentation worker did not start ({exc})")
        self._finalizer = weakref.finalize(
            self, _shut, self._process, self._bell, self._shared, self._memory
        )

    # ---------------------------------------------------------------- worker's life
    def _start(self, catheter, rig, R_w_b, o_b_w_mm, backgrounds, settings) -> None:
        self._memory = shared_memory.SharedMemory(create=True, size=_Shared.size(self._shapes))
        self._shared = _Shared(self._memory, self._shapes)
        self._shared.control[:] = -1
        context = multiprocessing.get_context("spawn")  # no fork of a process with threads
        wake, self._bell = context.Pipe()  # wakes the worker, and the caller for an answer
        self._process = context.Process(
            target=_serve,
            args=(
                wake,
                self._memory.name,
                self._shapes,
                self._remote,
                catheter,
                rig,
                np.asarray(R_w_b, float),
                np.asarray(o_b_w_mm, float),
                tuple(np.asarray(b) for b in backgrounds),
                settings,
                self._worker_poll_s,
                self._realtime,
            ),
            name="cathtrack-segmentation",
            daemon=True,
        )
        self._process.start()
        wake.close()  # the worker's end
        self._answer(START_TIMEOUT_S)  # its first answer: ready

    def _fail(self, reason: str) -> None:
        """Move the worker's views here for good, and say so once."""
        if self.worker_failure is not None:
            return
        self.worker_failure = reason
        self.report(
            f"{reason}; view{'s' if len(self._remote) > 1 else ''}"
            f" {', '.join(self.rig.names[v] for v in self._remote)}"
            " segmented in this process from now on"
        )
        _shut(self._process, self._bell, None, None, wait_s=0.0)
        self._process = self._bell = None

    def describe(self) -> str:
        """Whether the views were segmented side by side, for the user: "yes", or "yes"
        with the frames the worker's views were segmented here, or "no (why)"."""
        if self.worker_failure is not None:
            return f"no ({self.worker_failure})"
        if not self.moves:
            return "yes"
        return (
            f"yes, but {self.frames_here} of {self.frames} frames in the loop's process (the"
            f" worker held up by other work: {self.moves} times)"
        )

    @property
    def parallel(self) -> bool:
        """Whether the worker segments its views (False once it has failed or closed)."""
        return self.worker_failure is None

    def close(self) -> None:
        """Stop the worker and free the shared memory; any later frame is segmented in
        this process."""
        if self.worker_failure is None:
            self.worker_failure = "closed"
        self._finalizer()
        self._process = self._bell = self._shared = self._memory = None

    def __enter__(self) -> ParallelPairSegmenter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _request(self, kind: int, slot: int = 0, predicted=None) -> bool:
        """Post a request and wake the worker; False (its views then moved here) when it
        has gone."""
        shared = self._shared
        control = shared.control
        if predicted is not None:
            for k, v in enumerate(self._remote):
                control[_COUNTS + k] = _put_points(predicted[v], shared.points[k])
        self._seq += 1
        control[_REQUEST] = request_word(self._seq, kind, slot)  # last: then the points are in
        try:
            self._bell.send_bytes(b"")
        except (OSError, ValueError) as exc:
            self._process.join(1.0)
            code = self._process.exitcode
            ended = exc if code is None else f"it ended with exit code {code}"
            self._fail(f"the segmentation worker stopped ({ended})")
            return False
        return True

    def _answer(self, timeout_s: float | None = None):
        """The worker's answer to the last request (its value; its error raised again),
        waited for up to ``timeout_s`` (default :data:`ANSWER_TIMEOUT_S`)."""
        timeout_s = ANSWER_TIMEOUT_S if timeout_s is None else timeout_s
        control = self._shared.control
        seq = self._seq
        if control[_ANSWER] != seq:
            # Polled at first (see SPIN_S), then waited for.
            started = time.monotonic()
            spin_until = started + self.poll_s
            while control[_ANSWER] != seq:
                now = time.monotonic()
                if now < spin_until:
                    continue
                # A worker that has gone ends the pipe: told below, by its exit code.
                with contextlib.suppress(EOFError, OSError):
                    if self._bell.poll(min(max(started + timeout_s - now, 0.0), 0.1)):
                        self._drain()
                code = self._process.exitcode
                if code is not None and control[_ANSWER] != seq:
                    raise WorkerStopped(f"it ended with exit code {code}")
                if time.monotonic() > started + timeout_s and control[_ANSWER] != seq:
                    raise WorkerStopped(f"no answer within {timeout_s:g} s")
        self._bells += 1
        views = int(control[_ANSWER_VIEWS])
        if views:  # a segmentation's views, as a record
            return read_views(self._shared.record, views)
        n = int(control[_ANSWER_BYTES])
        kind, value = pickle.loads(self._shared.answer[:n])
        if kind == "error":
            raise value
        return value

    def _drain(self) -> None:
        """Read the worker's wake-up signals for the caller (one per answer) that were not
        waited for: off the critical path (:meth:`settle`, :meth:`rehearse`), so that the
        pipe never fills."""
        while self._bell.poll(0):
            self._bell.recv_bytes()
        self._bells = 0

    def _write(self, images: Sequence[Array], reuse: bool) -> int:
        """The slot holding the worker's views of ``images`` (written now unless ``reuse``
        and they are the arrays written last)."""
        remote = tuple(images[v] for v in self._remote)
        if (
            reuse
            and len(remote) == len(self._written)
            and all(a is b for a, b in zip(remote, self._written, strict=True))
        ):
            return self._slot
        slot = (self._slot + 1) % _SLOTS
        for k, image in enumerate(remote):
            np.copyto(self._shared.slots[k][slot], image)
        self._slot, self._written = slot, remote
        return slot

    def _checked(self, images: Sequence[Array], predicted_px) -> tuple[list[Array], Sequence]:
        if len(images) != self.rig.n_views:
            raise ValueError(
                f"need one image per view ({', '.join(self.rig.names)}), got {len(images)}"
            )
        images = list(images)
        for k, v in enumerate(self._remote):
            images[v] = check_image(images[v], f"{self.rig.names[v]} image", self._shapes[k])
        if predicted_px is None:
            predicted_px = (None,) * len(images)
        return images, predicted_px

    # ---------------------------------------------------------------- segmentation
    def segment(
        self,
        images: Sequence[Array],
        predicted_px: Sequence[Array | None] | None = None,
        *,
        settle: bool = True,
        meanwhile: Callable[[], None] | None = None,
    ) -> PairSegmentation:
        """Segment one synchronised frame (:meth:`PairSegmenter.segment`). ``meanwhile`` is
        called once the caller's own view is done and before the worker's answer is
        waited for: the caller's work that needs no segmentation overlaps the worker's."""
        self.frames += 1
        if not self.parallel or self.here:
            self.frames_here += self.here
            pair = self.local.segment(images, predicted_px, settle=settle, meanwhile=meanwhile)
            if settle and self.here:
                self._between_frames()
            return pair
        images, predicted_px = self._checked(images, predicted_px)
        if self._bells > 64:  # a caller that never settles
            self._between_frames()
        sent = self._request(_SEGMENT, self._write(images, False), predicted_px)
        camera = self.local.cameras[0]
        # The worker's answer is taken whatever happens here, so that the next request
        # gets its own.
        started_s = time.monotonic()
        try:
            first = camera.in_camera_frame(
                camera.segment(images[0], predicted_px[0], settle=settle)
            )
            own_s = time.monotonic() - started_s
            if meanwhile is not None:
                meanwhile()
        finally:
            waited_from = time.monotonic()
            others = self._others(sent, images, predicted_px, settle)
        if self._lag.add(own_s, time.monotonic() - waited_from):
            self._move_here = True  # done between frames, off the critical path
        pair = combine_views(self.segmenter, (first, *others), self.rig)
        if settle:  # nothing is deferred: this is between frames
            self._between_frames()
        return pair

    def _others(self, sent: bool, images, predicted_px, settle: bool) -> tuple:
        if sent:
            try:
                return self._answer()
            except WorkerStopped as exc:
                self._fail(f"the segmentation worker stopped ({exc})")
        cameras = self.local.cameras  # the fallback
        return tuple(
            cameras[v].in_camera_frame(
                cameras[v].segment(images[v], predicted_px[v], settle=settle)
            )
            for v in self._remote
        )

    def settle(self) -> None:
        """Average the frame segmented with ``settle=False`` into the background models
        (the worker settles its own as soon as it has answered, on its processor).

        Between frames, too, the worker's views come here when it has kept the caller
        waiting longer than a view of its own too often
        (:class:`~tracker.vision.worker_lag.LagWatch`), and go back to it :data:`RETRY_S`
        later (twice that after each move): each move takes their state along (about 10 ms,
        once). A frame segmented with ``settle=True`` does this itself."""
        self.local.settle()
        self._between_frames()

    def _between_frames(self, move: bool = True) -> None:
        """Read the wake-up signals not waited for; with ``move``, move the views here or
        back if due."""
        if not self.parallel:
            return
        try:
            if self._bells:
                self._drain()
            if not move:
                return
            if self._move_here:
                self._take_views()
            elif self.here and time.monotonic() - self._here_since > self._retry_s:
                self._give_views()
        except (EOFError, OSError, WorkerStopped) as exc:
            self._fail(f"the segmentation worker stopped ({exc})")

    def _take_views(self) -> None:
        """The worker's views, their state included, segmented here from now on."""
        self._move_here = False
        self._lag.restart()
        if not self._request(_HAND_OVER):
            return
        cameras = pickle.loads(self._payload())
        local = list(self.local.cameras)
        for v, camera in zip(self._remote, cameras, strict=True):
            camera.segmenter = self.segmenter
            local[v] = camera
        self.local.cameras = tuple(local)
        self.here, self._here_since = True, time.monotonic()
        if self.moves:
            self._retry_s = min(2.0 * self._retry_s, MAX_RETRY_S)
        self.moves += 1

    def _give_views(self) -> None:
        """The views taken here back to the worker, their state included."""
        self._bell.send_bytes(
            pickle.dumps(
                tuple(self.local.cameras[v] for v in self._remote), pickle.HIGHEST_PROTOCOL
            )
        )
        if self._request(_TAKE_BACK):
            self._answer()
            self.here = False
            self._lag.restart()

    def _payload(self) -> bytes:
        """The next message from the worker that is not a wake-up signal."""
        deadline = time.monotonic() + ANSWER_TIMEOUT_S
        while True:
            if not self._bell.poll(max(deadline - time.monotonic(), 0.0)):
                raise WorkerStopped(f"no answer within {ANSWER_TIMEOUT_S:g} s")
            data = self._bell.recv_bytes()
            if data:
                return data

    def rehearse(self, images: Sequence[Array], predicted_px=None, abandon=None) -> bool:
        """:meth:`PairSegmenter.rehearse`; the worker rehearses its views at the same time
        (and stops when the next request comes)."""
        if not self.parallel or self.here:
            return self.local.rehearse(images, predicted_px, abandon)
        images, predicted_px = self._checked(images, predicted_px)
        self.local.settle()
        self._between_frames(move=False)  # a move waits for settle: this is the priming
        self._request(_REHEARSE, self._write(images, True), predicted_px)
        return self.local.cameras[0].rehearse(images[0], predicted_px[0], abandon)

    def reset(self) -> None:
        """Search the next frame's images whole (the backgrounds are kept)."""
        self.local.reset()
        # Answered: a request not yet taken up is replaced by the next (a rehearsal may be).
        if self.parallel and not self.here and self._request(_RESET):
            try:
                self._answer()
            except WorkerStopped as exc:
                self._fail(f"the segmentation worker stopped ({exc})")

    @property
    def backgrounds(self) -> tuple[Array, ...]:
        """Each camera's current background model (uint8), the last frame averaged in."""
        local = self.local.backgrounds
        if not self.parallel or self.here or not self._request(_BACKGROUNDS):
            return local
        try:
            others = self._answer()
        except WorkerStopped as exc:
            self._fail(f"the segmentation worker stopped ({exc})")
            return local
        return (local[0], *others)

    @property
    def base_px(self) -> tuple[Array, ...]:
        """The registered base projected into each camera, px."""
        return self.local.base_px

    frame = PairSegmenter.frame  # segments with this one's segment()


def pair_segmenter(
    catheter: Catheter,
    rig: Rig,
    R_w_b: Array,
    o_b_w_mm: Array,
    backgrounds: Sequence[Array],
    settings: SegmentationSettings = DEFAULT_SETTINGS,
    *,
    parallel: bool | None = None,
    report: Callable[[str], None] = _report_stderr,
    realtime: bool = True,
) -> PairSegmenter | ParallelPairSegmenter:
    """The live loop's segmenter: :class:`ParallelPairSegmenter` where this process may use
    two processors or more (``parallel=None``) or when asked, else :class:`PairSegmenter`;
    ``realtime``: its worker's frames at a real-time priority where permitted."""
    if parallel is None:
        parallel = parallel_possible() and rig.n_views >= 2
    if parallel:
        return ParallelPairSegmenter(
            catheter, rig, R_w_b, o_b_w_mm, backgrounds, settings, report=report,
            realtime=realtime,
        )
    return PairSegmenter(catheter, rig, R_w_b, o_b_w_mm, backgrounds, settings)


# ------------------------------------------------------------------------- helpers
def _put_points(points: Array | None, out: Array) -> int:
    """Write predicted points into ``out`` (MAX_POINTS, 2); their count, -1 for None.

    More than ``MAX_POINTS`` go as the corners of their finite points' bounding box: the
    segmentation searches the box around them (:func:`tracker.vision.detection.search_box`)
    and nothing else of them.
    """
    if points is None:
        return -1
    points = np.asarray(points, float).reshape(-1, 2)
    if points.shape[0] > MAX_POINTS:
        finite = points[np.isfinite(points).all(axis=1)]
        points = (
            np.stack([finite.min(axis=0), finite.max(axis=0)])
            if finite.size
            else np.full((1, 2), np.nan)
        )
    n = points.shape[0]
    out[:n] = points
    return n


def _taken_points(shared: _Shared, k: int) -> Array | None:
    n = int(shared.control[_COUNTS + k])
    return None if n < 0 else shared.points[k, :n].copy()


def _shut(process, bell, shared, memory, wait_s: float = 2.0) -> None:
    """Stop a worker and free its shared memory (each part that is there); a worker that has
    not stopped within ``wait_s`` is ended (0: at once, one that failed)."""
    if bell is not None:
        if shared is not None and process is not None and process.is_alive():
            seq, _, _ = request_of(int(shared.control[_REQUEST]))
            shared.control[_REQUEST] = request_word(seq + 1, _STOP, 0)
        # The wake-up, or the end of the pipe below: either stops it (a pipe that is already
        # broken, a worker that died, needs neither).
        with contextlib.suppress(OSError, ValueError):
            bell.send_bytes(b"")
        bell.close()
    if process is not None and process.pid is not None:
        process.join(wait_s)
        if process.is_alive():
            process.kill()  # a hung or stopped process too
            process.join(2.0)
    if shared is not None:
        shared.release()
    if memory is not None:
        memory.close()
        memory.unlink()


# --------------------------------------------------------------------------- worker
def _serve(
    wake,
    memory_name,
    shapes,
    remote,
    catheter,
    rig,
    R_w_b,
    o_b_w_mm,
    backgrounds,
    settings,
    poll_s,
    realtime,
) -> None:
    """The worker process: segment its views on request until told to stop, or until the
    caller's end of the pipe closes. Answers ``(kind, value)``: ``("ok", ...)`` or
    ``("error", exception)``. With ``realtime``, from a frame's request to its answer at a
    real-time priority where permitted (:class:`~tracker.live.priority.FramePriority`)."""
    import cv2

    # Ctrl-C reaches the whole process group: the caller stops the worker, not the signal.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    cv2.setNumThreads(1)  # as in the loop's process: one processor each
    memory = shared_memory.SharedMemory(memory_name)
    shared = _Shared(memory, shapes)
    try:
        # The end of the pipe: the caller has gone, and with it anyone to tell.
        with contextlib.suppress(EOFError, OSError):
            try:
                pair = PairSegmenter(catheter, rig, R_w_b, o_b_w_mm, backgrounds, settings)
            except Exception as exc:  # noqa: BLE001 (told to the caller, which goes on)
                error = WorkerStopped(f"{type(exc).__name__}: {exc}")
                _answer_with(shared, 0, ("error", error))
                wake.send_bytes(b"")
                return
            with FrameCollection() as collection:
                _work(
                    wake, shared, [pair.cameras[v] for v in remote], pair.segmenter, poll_s,
                    collection, FramePriority(realtime),
                )
    finally:
        shared.release()
        memory.close()


def _work(wake, shared, cameras, segmenter, poll_s: float, collection, priority) -> None:
    """Answer the caller's requests (see :func:`_serve`) until it says stop; garbage is
    collected after an answer (:class:`~tracker.live.collection.FrameCollection`), a frame
    segmented within ``priority`` (a :class:`~tracker.live.priority.FramePriority`)."""
    control = shared.control
    seen = int(control[_REQUEST])  # none is sent before this answer: ready
    payload: list[bytes] = []
    _answer_with(shared, 0, ("ok", None))
    wake.send_bytes(b"")
    spin_until = 0.0
    while True:
        # Waiting for a request at the frame's priority, blocked: the request's bell then
        # wakes the worker ahead of any ordinary thread on its processor, which it would
        # otherwise wait for (2.5 ms has been seen), and it costs no processor time meanwhile.
        waiting = contextlib.ExitStack()
        waiting.enter_context(priority)
        while control[_REQUEST] == seen:
            # Without that priority: after a rehearsal the frame is due within milliseconds,
            # so poll for it, giving the processor at once to anything else that is ready
            # (the demo's controller shares it: held off by the poll, its joint datagrams
            # came 3-5 ms late).
            if not priority.enabled and time.monotonic() < spin_until:
                _yield()
                continue
            if wake.poll(1.0):
                while wake.poll(0):
                    data = wake.recv_bytes()  # EOFError once the caller has closed its end
                    if data:  # views given back: kept for the request that follows
                        payload.append(data)
        seen = int(control[_REQUEST])  # one read: this request whole, or the next whole
        seq, kind, slot = request_of(seen)
        spin_until = 0.0
        if kind == _SEGMENT:
            with waiting:  # the frame's priority until its answer is out
                try:
                    views = tuple(
                        camera.in_camera_frame(
                            camera.segment(
                                shared.slots[k][slot], _taken_points(shared, k), settle=False
                            )
                        )
                        for k, camera in enumerate(cameras)
                    )
                    answer = ("ok", views)
                except Exception as exc:  # noqa: BLE001 (raised again in the caller)
                    answer = ("error", exc)
                _answer_with(shared, seq, answer)
            wake.send_bytes(b"")
            for camera in cameras:  # the caller's settle, off its critical path
                camera.settle()
            collection.collect()  # and the garbage collection due, as in the loop
            continue
        waiting.close()  # anything but a frame at the ordinary priority
        if kind == _REHEARSE:
            # A rehearsal changes nothing; what is wrong with its images, the frame's own
            # segmentation reports.
            with contextlib.suppress(Exception):
                for k, camera in enumerate(cameras):  # each until the frame's request comes
                    if not camera.rehearse(shared.slots[k][slot], _taken_points(shared, k),
                                           lambda seen=seen: control[_REQUEST] != seen):
                        break
            spin_until = time.monotonic() + poll_s
        elif kind == _RESET:
            for camera in cameras:
                camera.reset()
            _answer_with(shared, seq, ("ok", None))
            wake.send_bytes(b"")
        elif kind == _BACKGROUNDS:
            for camera in cameras:
                camera.settle()
            _answer_with(shared, seq, ("ok", tuple(c.background.image for c in cameras)))
            wake.send_bytes(b"")
        elif kind == _HAND_OVER:
            for camera in cameras:
                camera.settle()
            wake.send_bytes(pickle.dumps(tuple(cameras), pickle.HIGHEST_PROTOCOL))
        elif kind == _TAKE_BACK:
            while not payload:
                data = wake.recv_bytes()
                if data:
                    payload.append(data)
            cameras[:] = pickle.loads(payload.pop(0))
            for camera in cameras:
                camera.segmenter = segmenter
            _answer_with(shared, seq, ("ok", None))
            wake.send_bytes(b"")
        elif kind == _STOP:
            return


_yield = getattr(os, "sched_yield", lambda: None)


def request_word(seq: int, kind: int, slot: int) -> int:
    """A request as one control word (sequence number, kind, image slot), posted in one
    store after its points and read in one load. In three words the worker could read a
    rehearsal's number with the next frame's kind and slot, and segment that frame twice,
    its background model updated twice with it."""
    return (seq << 8) | (kind << 4) | slot


def request_of(word: int) -> tuple[int, int, int]:
    """The sequence number, kind and image slot of a request word (:func:`request_word`)."""
    return word >> 8, (word >> 4) & 0xF, word & 0xF


def _answer_with(shared: _Shared, seq: int, answer: tuple) -> None:
    """Write an answer for the caller: a segmentation's views as a record
    (:mod:`~tracker.vision.view_record`: a fifth of pickle's time), anything else pickled.
    An error that does not pickle goes as a RuntimeError of its text, an answer too large
    as an error."""
    kind, value = answer
    if (
        kind == "ok"
        and isinstance(value, tuple)
        and value
        and all(isinstance(view, ViewSegmentation) for view in value)
        and write_views(shared.record, value) >= 0
    ):
        shared.control[_ANSWER_VIEWS] = len(value)
        shared.control[_ANSWER] = seq  # last: the caller reads the answer once it sees it
        return
    shared.control[_ANSWER_VIEWS] = 0
    try:
        data = pickle.dumps(answer, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception:  # noqa: BLE001
        error = answer[1]
        data = pickle.dumps(("error", RuntimeError(f"{type(error).__name__}: {error}")))
    if len(data) > shared.answer.size:
        data = pickle.dumps(
            (
                "error",
                RuntimeError(f"the segmentation worker's answer is too large ({len(data)} bytes)"),
            )
        )
    shared.answer[: len(data)] = np.frombuffer(data, np.uint8)
    shared.control[_ANSWER_BYTES] = len(data)
    shared.control[_ANSWER] = seq  # last: the caller reads the answer once it sees it
