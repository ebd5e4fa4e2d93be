"""Frame sources of the live loop (docs/design.md sections 6 and 7).

A source is an iterable of items, each one of

- :class:`ImageSet` ``(time_s, images)``: grayscale images of every view to segment;
- :class:`tracker.io.udp.SegmentedMarkers`: points segmented elsewhere, without joint values;
- :class:`tracker.types.Frame`: a complete frame (simulation, recordings);
- ``None``: nothing arrived within the source's poll interval (lets the loop drain the
  joint socket, honour Ctrl-C and time out while idle).

A source may set ``time_is_monotonic = True`` when its item times are ``time.monotonic()``
stamps of this process (live cameras): the loop then measures latency from the image time
stamp; otherwise from the moment the item left the source. A source may have ``close()``;
the loop calls it on exit.

A source that delivers at its own pace, whether the loop is ready or not (cameras, a video
file played at its frame rate, simulated cameras), sets ``live = True``: the loop then runs it
in its own capture thread (:class:`NewestOnly`) and always takes the newest item, dropping
(and counting) the ones a newer item replaced before the loop was free. Sources without it
(recordings, simulations, markers over UDP) have every item processed, in order.
A source that knows its frame period (the simulated cameras) may give it as ``period_s``,
s: the loop then primes for its second frame too, where it would otherwise wait for two
frames to measure the period (:class:`~tracker.live.pacing.FramePace`).

Sources here: two cameras or video files through OpenCV (:class:`VideoSource`), segmented
markers over UDP (:class:`UdpMarkerSource`), the frames of a recording
(:class:`RecordingSource`), and :class:`PacedSource`, which releases any time-stamped items at
real time. Simulated sessions are in :mod:`replay.simulation.sources`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from models.imaging import default_view_names
from tracker.io.datagrams import SegmentedMarkers
from tracker.io.recording import Recording, open_recording
from tracker.io.udp import MarkerReceiver
from tracker.types import Frame

Array = np.ndarray


class ImageSet(NamedTuple):
    """Synchronised grayscale images (uint8, (h, w)), one per view of the rig in its order,
    and their time stamp, s."""

    time_s: float
    images: tuple[Array, ...]


Item = ImageSet | SegmentedMarkers | Frame | None


def arrivals(source: Iterable, clock: Callable[[], float]) -> Iterator:
    """(item, the time it left the source) of every item of a source the loop takes in
    order; ``None`` as it comes."""
    for item in source:
        yield None if item is None else (item, clock())


# ----------------------------------------------------------------------------- capture
class NewestOnly:
    """A live source run in its own capture thread; the loop takes only the newest item.

    A camera delivers at its own pace whether the loop is ready or not. Here the source is
    iterated in a capture thread that puts every item, stamped with its arrival time, into a
    one-item slot; the loop takes what is in the slot when it is free. An item replaced
    before the loop took it is dropped and counted in ``dropped``: the loop never works
    through a backlog, so a frame waits at most the processing of the one before it.

    Parameters
    ----------
    source : iterable
        Any source of :mod:`tracker.live.sources` (``None`` items are ignored here).
    poll_s : float
        :meth:`items` yields ``None`` after this long without a new item, so that the loop
        can drain the joint socket, honour Ctrl-C and time out while idle.
    monotonic : callable
        Clock of the arrival stamps (the loop's).

    Attributes
    ----------
    captured, dropped : int
        Items the source delivered, and those a newer one replaced before the loop took them.
    stop_reason : str or None
        The source's, once it has ended.
    """

    def __init__(
        self,
        source: Iterable,
        poll_s: float = 0.002,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.source = source
        self.poll_s = float(poll_s)
        self.monotonic = monotonic
        self.time_is_monotonic = bool(getattr(source, "time_is_monotonic", False))
        self.captured = 0
        self.dropped = 0
        self.stop_reason: str | None = None
        self._slot: tuple[object, float] | None = None
        self._ended = False
        self._error: BaseException | None = None
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._capture, name="capture", daemon=True)

    @property
    def counts(self):
        """The source's datagram counts, if it has them."""
        return getattr(self.source, "counts", None)

    @property
    def waiting(self) -> bool:
        """Whether an item is in the slot, not taken yet."""
        return self._slot is not None

    @property
    def thread_id(self) -> int | None:
        """The capture thread's native id (None before it starts)."""
        return self._thread.native_id

    def _capture(self) -> None:
        try:
            for item in self.source:
                if self._stop.is_set():
                    return
                if item is None:
                    continue
                arrival_s = self.monotonic()
                with self._cond:
                    self.captured += 1
                    self.dropped += self._slot is not None
                    self._slot = (item, arrival_s)
                    self._cond.notify()
            self.stop_reason = getattr(self.source, "stop_reason", None)
        except BaseException as exc:  # handed to the loop's thread by items()
            self._error = exc
        finally:
            with self._cond:
                self._ended = True
                self._cond.notify()

    def start(self) -> NewestOnly:
        """Start capturing (:meth:`items` starts it too)."""
        if not self._thread.is_alive() and not self._ended:
            self._thread.start()
        return self

    def take(self, timeout_s: float) -> tuple[object, float] | None:
        """The newest item and its arrival time, or None after ``timeout_s`` without one.

        Raises StopIteration once the source has ended and its last item was taken, and the
        source's own exception if it raised one.
        """
        with self._cond:
            if self._slot is None and not self._ended:
                self._cond.wait(timeout_s)
            newest, self._slot = self._slot, None
            ended = self._ended
        if newest is not None:
            return newest
        if ended:
            if self._error is not None:
                raise self._error
            raise StopIteration
        return None

    def items(
        self, wait_s: Callable[[], float] | None = None
    ) -> Iterator[tuple[object, float] | None]:
        """(item, arrival time) of the newest item whenever the caller asks, ``None`` while
        there is none (after ``poll_s``, or after ``wait_s()`` when given: the caller's own
        deadline); ends with the source."""
        self.start()
        while True:
            try:
                yield self.take(self.poll_s if wait_s is None else wait_s())
            except StopIteration:
                return

    def __iter__(self) -> Iterator:
        for entry in self.items():
            yield None if entry is None else entry[0]

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop capturing (after the item being captured, at most ``timeout_s``), then close
        the source."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        closer = getattr(self.source, "close", None)
        if closer is not None:
            closer()


# ------------------------------------------------------------------------------------ pacing
class PacedSource:
    """Releases time-stamped items at real time (or ``speed`` times faster).

    Works with anything that has ``time_s``: the frames of a simulation or of a recording,
    image pairs, segmented markers. The first item is released at once and item ``k`` at
    ``(time_k - time_0) / speed`` seconds after it; ``speed=None`` releases them as fast as the
    loop takes them.

    Parameters
    ----------
    items : iterable
    speed : float or None
    monotonic, sleep : callables
        Clock and sleep (tests may substitute them).
    """

    time_is_monotonic = False

    def __init__(
        self,
        items: Iterable,
        speed: float | None = 1.0,
        monotonic: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if speed is not None and not speed > 0:
            raise ValueError(f"speed must be positive (None: as fast as possible), got {speed}")
        self.items = items
        self.speed = speed
        self.monotonic = monotonic
        self.sleep = sleep

    def __iter__(self) -> Iterator:
        start = first = None
        for item in self.items:
            if item is not None and self.speed is not None:
                if start is None:
                    start, first = self.monotonic(), float(item.time_s)
                due = start + (float(item.time_s) - first) / self.speed
                wait = due - self.monotonic()
                if wait > 0:
                    self.sleep(wait)
            yield item


# ---------------------------------------------------------------------------------- OpenCV
def _capture_spec(spec: int | str) -> int | str:
    """A camera index (int, or a string of digits) or a file path / URL."""
    if isinstance(spec, str) and spec.strip().isdigit():
        return int(spec)
    return spec


def _describe(name: str, spec: int | str) -> str:
    return f"{name} camera {spec}" if isinstance(spec, int) else f"{name} video {spec!r}"


def open_capture(spec: int | str, name: str = "view"):
    """``cv2.VideoCapture`` of a camera index or a video file, or one clear OSError naming it."""
    spec = _capture_spec(spec)
    if isinstance(spec, str) and "://" not in spec:
        if not Path(spec).is_file():
            raise OSError(f"cannot open the {_describe(name, spec)}: no such file")
    capture = cv2.VideoCapture(spec)
    if not capture.isOpened():
        capture.release()
        hint = " (is it connected, and not in use by another program?)" if isinstance(
            spec, int
        ) else " (unsupported format or codec?)"
        raise OSError(f"cannot open the {_describe(name, spec)}{hint}")
    return capture


def _gray(image: Array) -> Array:
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        return cv2.cvtColor(image, code)
    return image


class VideoSource:
    """One camera or video file per view through OpenCV, as :class:`ImageSet` items.

    All captures are grabbed first and decoded afterwards, so the exposures are as close in
    time as the devices allow. Camera images are stamped with ``time.monotonic()`` at the
    grab; video-file images with the first file's position (``CAP_PROP_POS_MSEC``), paced at
    real time when ``realtime`` is set. Iteration ends when any capture stops delivering.
    Cameras and paced video files are ``live``: the loop grabs them in their own thread and
    takes the newest pair (:class:`NewestOnly`), so the driver's buffer never hands it old
    images.

    Parameters
    ----------
    specs : sequence of int or str
        Per view, in the rig's order: camera index (or its digits as a string), video file or
        stream URL.
    names : sequence of str, optional
        The views' names, for messages (default: the rig's default names).
    realtime : bool
        Pace video files at their frame rate (cameras are paced by themselves).
    monotonic : callable
    """

    def __init__(
        self,
        specs: Sequence[int | str],
        names: Sequence[str] | None = None,
        realtime: bool = False,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.specs = tuple(_capture_spec(spec) for spec in specs)
        self.names = default_view_names(len(self.specs)) if names is None else tuple(names)
        if len(self.names) != len(self.specs) or len(self.specs) < 2:
            raise ValueError(
                f"need one capture per view (two or more), got {len(self.specs)} for"
                f" views {self.names}"
            )
        self.time_is_monotonic = any(isinstance(s, int) for s in self.specs)
        self.realtime = realtime
        self.live = self.time_is_monotonic or realtime
        self.monotonic = monotonic
        self.stop_reason: str | None = None
        self._captures = []
        try:
            for name, spec in zip(self.names, self.specs, strict=True):
                self._captures.append(open_capture(spec, name))
        except OSError:
            self.close()
            raise

    def __iter__(self) -> Iterator[ImageSet]:
        captures = list(self._captures)
        start = first = None
        while self._captures:
            grabbed = [c.grab() for c in captures]
            stamp = self.monotonic()
            if not all(grabbed):
                which = [
                    _describe(n, s)
                    for n, s, ok in zip(self.names, self.specs, grabbed, strict=True)
                    if not ok
                ]
                self.stop_reason = f"{' and '.join(which)} stopped delivering images"
                return
            images = [c.retrieve()[1] for c in captures]
            if any(image is None for image in images):
                self.stop_reason = "a capture returned an empty image"
                return
            if self.time_is_monotonic:
                time_s = stamp
            else:
                time_s = captures[0].get(cv2.CAP_PROP_POS_MSEC) / 1000.0
                if self.realtime:
                    if start is None:
                        start, first = stamp, time_s
                    wait = start + (time_s - first) - self.monotonic()
                    if wait > 0:
                        time.sleep(wait)
            yield ImageSet(time_s, tuple(_gray(image) for image in images))

    def close(self) -> None:
        for capture in self._captures:
            capture.release()
        self._captures = []

    def __enter__(self) -> VideoSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# -------------------------------------------------------------------------------------- UDP
class UdpMarkerSource:
    """Segmented markers over UDP (:class:`~tracker.io.udp.MarkerReceiver`) as loop items.

    Yields ``None`` after every ``poll_s`` without a datagram, so the loop stays responsive and
    can end on its idle timeout, and drains the joint datagrams as they come rather than when
    the frame's markers do.

    Parameters
    ----------
    receiver : MarkerReceiver
    poll_s : float
        How long to wait for a datagram before yielding ``None``, s. 2 ms, as the capture of
        live images: at 1 kHz the loop then has a datagram or two to read when a frame's
        markers come, where after 50 ms it read fifty (0.9 ms of its critical path).
    time_is_monotonic : bool
        Set when the external segmenter runs on this machine and stamps its markers with the
        same monotonic clock (latency is then measured from the image time stamp).
    """

    def __init__(
        self, receiver: MarkerReceiver, poll_s: float = 0.002, time_is_monotonic: bool = False
    ) -> None:
        self.receiver = receiver
        self.poll_s = float(poll_s)
        self.time_is_monotonic = time_is_monotonic

    def __iter__(self) -> Iterator[SegmentedMarkers | None]:
        while True:
            batch = self.receiver.receive(self.poll_s)
            if not batch:
                yield None
            yield from batch

    @property
    def counts(self):
        return self.receiver.counts

    def close(self) -> None:
        self.receiver.close()


# -------------------------------------------------------------------------------- recordings
class RecordingSource(PacedSource):
    """The frames of an MCAP recording (:mod:`tracker.io.recording`), paced at real time.

    Frames come with the recorded markers and joint values (and images with ``images``);
    ``recording`` gives the CLI the recorded catheter model and rig
    (``recording.catheter()``, ``recording.rig()``) to build the reconstructor.

    Parameters
    ----------
    recording : str, Path or Recording
    speed : float or None
    images : bool
        Decode the recorded images (for a viewer); the loop itself uses the recorded markers.

    Raises
    ------
    tracker.io.recording.RecordingError (a ValueError)
        Not a readable cathtrack recording.
    """

    def __init__(
        self,
        recording: str | Path | Recording,
        speed: float | None = 1.0,
        images: bool = False,
        **kwargs,
    ) -> None:
        if not isinstance(recording, Recording):
            recording = open_recording(recording)
        self.recording = recording
        super().__init__((r.frame for r in recording.frames(images=images)), speed, **kwargs)

    def close(self) -> None:
        self.recording.close()
