"""UDP sockets of the live loop: joint values and segmented markers in, estimates out.

docs/design.md section 7; the datagrams themselves (layouts, encoders, decoders) are in
:mod:`tracker.io.datagrams`, the byte tables in docs/live.md.

- :class:`JointReceiver`: joint datagrams from the robot controller, kept as a bounded
  history and interpolated to any image time (:class:`tracker.io.joints.JointHistory`);
- :class:`EstimateSender`: one estimate datagram per frame back to the controller;
- :class:`MarkerReceiver`: points already segmented by an external segmenter;
- :class:`JointStreamer` plays the controller (simulations, demos, tests).

Receivers drop and count malformed datagrams by the ``reason`` of their
:class:`~tracker.io.datagrams.DatagramError` (sizes, values beyond the robot's ranges, ...);
the joint receiver also drops, as ``time``, a datagram stamped beyond a window of its own
clock (:data:`~tracker.io.limits.JOINT_TIME_WINDOW_S`), so that one damaged time stamp cannot
make every later datagram look stale. Listeners bind to 127.0.0.1 unless told otherwise.
"""

from __future__ import annotations

import math
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from tracker.io.datagrams import (
    SEQUENCE_MODULUS,
    DatagramError,
    JointPacket,
    SegmentedMarkers,
    decode_joints,
    decode_markers,
    encode_estimate,
    encode_joints,
)
from tracker.io.joints import RATE_WINDOW_S, JointHistory, JointSample, sample_joints
from tracker.io.limits import JOINT_TIME_WINDOW_S
from tracker.types import Estimate, Frame

Array = np.ndarray

LOOPBACK = "127.0.0.1"
DEFAULT_JOINT_PORT = 25000
"""Port the loop listens on for joint datagrams."""
DEFAULT_ESTIMATE_PORT = 25001
"""Port estimate datagrams are sent to (on the controller)."""
DEFAULT_MARKER_PORT = 25002
"""Port the loop listens on for segmented-marker datagrams."""
_RECEIVE_BUFFER_BYTES = 65536
# A kept joint sample: sender time, arrival time, q (3), q_dot (3), arrival - sender (s).
_JOINT_ROW = struct.Struct("=9d")
CLOCK_JUMP_SAMPLES = 20
"""Consecutive datagrams that agree with each other but not with the kept history (their
times jumped while their sequence went on) after which the sender's clock is taken to have
jumped: the history restarts from them."""


@dataclass
class StreamCounts:
    """Counters of one datagram stream."""

    received: int = 0
    accepted: int = 0
    stale: int = 0  # older than the newest (sequence behind, or time not increasing)
    duplicate: int = 0  # same sequence as the newest
    restarts: int = 0  # the sender restarted its sequence or its clock: history cleared
    # Dropped by reason: the decoder's (size, magic, version, non-finite, range, points,
    # views, sigma) and the joint receiver's "time" (stamped beyond its clock's window).
    malformed: dict[str, int] = field(default_factory=dict)

    @property
    def malformed_total(self) -> int:
        return sum(self.malformed.values())

    def count_malformed(self, reason: str, n: int = 1) -> None:
        self.malformed[reason] = self.malformed.get(reason, 0) + n


def _udp_socket(host: str, port: int, rcvbuf_bytes: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        # Room for a burst (the kernel caps this at net.core.rmem_max).
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf_bytes)
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise OSError(f"cannot listen for UDP datagrams on {host}:{port}: {exc.strerror}") from exc
    sock.setblocking(False)
    return sock


class JointReceiver:
    """Joint datagrams in, joint values at any image time out.

    A non-blocking UDP socket; :meth:`poll` drains every pending datagram (the loop calls it
    before each frame and while idle). The newest sample by sequence number wins: datagrams
    with the newest's sequence are duplicates, those behind it (or not later in time) are
    stale, and both are dropped and counted, as are malformed ones (by reason) and, as
    ``time``, those stamped later than the newest by more than the receiver's clock moved
    between their arrivals plus ``time_window_s``. A sequence more than ``restart_gap`` behind
    the newest is a restarted sender, and :data:`CLOCK_JUMP_SAMPLES` consecutive datagrams
    whose times agree with each other but not with the history a sender whose clock jumped:
    either way the history starts again (counted in ``restarts``).
    The kept history is time-ordered and bounded (``history`` samples, 2 s at 1 kHz by
    default) and :meth:`sample` interpolates values and rates linearly to any time.

    Parameters
    ----------
    host, port : str, int
        Address to bind (loopback by default; port 0 picks a free port, see ``address``;
        None: no socket, datagrams are fed with :meth:`add_datagram`).
    history : int
        Samples kept.
    stale_after_s : float
        A time later than the newest sample (or earlier than the oldest) by more than this is
        flagged ``STALE``: the stream has stopped or the history does not cover it.
    clock : {"sender", "arrival", "aligned"}
        Time base of the samples. ``"sender"``: the datagram's ``time_s`` (the controller and
        the images share a clock: simulation, replay, a synchronised clock). ``"arrival"``:
        the local ``time.monotonic()`` at receipt. ``"aligned"``: the sender's time plus the
        smallest (arrival - sender) offset seen in the history, which keeps the sender's
        regular sampling on the local monotonic clock without its network jitter (live
        cameras stamp their images with ``time.monotonic()``).
    restart_gap : int
        Sequence numbers behind the newest beyond which a datagram means a sender restart.
    time_window_s : float
        How much later than the newest sample (plus the arrival time elapsed) a datagram may
        be stamped.
    rcvbuf_bytes : int
        Requested socket receive buffer.
    monotonic : callable
        Local clock (tests may substitute one).
    """

    def __init__(
        self,
        host: str = LOOPBACK,
        port: int | None = DEFAULT_JOINT_PORT,
        *,
        history: int = 2048,
        stale_after_s: float = 0.1,
        clock: str = "aligned",
        restart_gap: int = 1000,
        time_window_s: float = JOINT_TIME_WINDOW_S,
        rcvbuf_bytes: int = 1 << 21,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        if clock not in ("sender", "arrival", "aligned"):
            raise ValueError(f"clock must be 'sender', 'arrival' or 'aligned', got {clock!r}")
        if history < 2:
            raise ValueError(f"history must keep at least 2 samples, got {history}")
        if not stale_after_s > 0:
            raise ValueError(f"stale_after_s must be positive, got {stale_after_s}")
        self.clock = clock
        self.history = int(history)
        self.stale_after_s = float(stale_after_s)
        self.restart_gap = int(restart_gap)
        self.time_window_s = float(time_window_s)
        self.monotonic = monotonic
        self.counts = StreamCounts()
        # Rows (_JOINT_ROW) in twice the history, compacted when full: the kept samples stay
        # one contiguous, time-ordered slice, so interpolation is one search. Each accepted
        # sample is packed straight into the rows' bytes (an item assignment into numpy
        # costs more than the rest of a datagram's handling), so reading the history copies
        # nothing.
        self._rows = np.empty((2 * self.history, _JOINT_ROW.size // 8))
        self._bytes = memoryview(self._rows).cast("B")
        self._start = self._end = 0
        # The aligned clock's offset: no kept row's (arrival - sender) is below it (NaN
        # counting as lowest, as in np.min), and while row ``_offset_row`` is kept it is that
        # row's, hence the minimum; once that row has left, the minimum is taken again.
        self._offset_s = math.inf
        self._offset_row = -1
        self._newest: JointPacket | None = None
        self._newest_arrival_s = 0.0
        # Datagrams dropped for their time, consecutive and consistent among themselves:
        # (packet, arrival, the reason it was counted under).
        self._jumped: list[tuple[JointPacket, float, str]] = []
        self._view = memoryview(bytearray(_RECEIVE_BUFFER_BYTES))  # decoded in place
        self._sock = None if port is None else _udp_socket(host, port, rcvbuf_bytes)

    # ---------------------------------------------------------------- socket side
    @property
    def address(self) -> tuple[str, int]:
        """The bound (host, port)."""
        if self._sock is None:
            raise ValueError("this JointReceiver has no socket")
        return self._sock.getsockname()

    def fileno(self) -> int:
        return -1 if self._sock is None else self._sock.fileno()

    def poll(self) -> int:
        """Drain every pending datagram; returns how many were accepted."""
        if self._sock is None:
            return 0
        accepted = 0
        recv_into, view = self._sock.recv_into, self._view
        while True:
            try:
                n = recv_into(view)
            except (BlockingIOError, InterruptedError):
                return accepted
            except OSError:  # e.g. an ICMP error queued on the socket: not a datagram
                return accepted
            accepted += self.add_datagram(view[:n], self.monotonic())

    def wait(self, timeout_s: float) -> int:
        """Block until a datagram is pending or ``timeout_s`` passes, then :meth:`poll`."""
        if self._sock is not None:
            select.select([self._sock], [], [], max(0.0, timeout_s))
        return self.poll()

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> JointReceiver:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---------------------------------------------------------------- stream logic
    def add_datagram(self, data: bytes | memoryview, arrival_s: float) -> int:
        """Validate, order and keep one datagram; 1 if accepted, 0 if dropped (counted)."""
        self.counts.received += 1
        try:
            packet = decode_joints(data)
        except DatagramError as exc:
            self.counts.count_malformed(exc.reason)
            return 0
        return self.add(packet, arrival_s)

    def add(self, packet: JointPacket, arrival_s: float) -> int:
        """Keep a decoded sample unless it is a duplicate, stale or stamped beyond the time
        window (each counted)."""
        newest = self._newest
        if newest is not None:
            ahead = (packet.sequence - newest.sequence) % SEQUENCE_MODULUS
            if ahead == 0:
                self.counts.duplicate += 1
                return 0
            behind = SEQUENCE_MODULUS - ahead if ahead >= SEQUENCE_MODULUS // 2 else 0
            if behind > self.restart_gap:
                self.counts.restarts += 1
                self._clear()
                self._jumped.clear()
            elif behind:
                self.counts.stale += 1
                return 0
            elif packet.time_s <= newest.time_s:
                self.counts.stale += 1
                return self._jump(packet, arrival_s, "stale")
            elif not self._follows(newest, self._newest_arrival_s, packet, arrival_s):
                self.counts.count_malformed("time")
                return self._jump(packet, arrival_s, "time")
        self._jumped.clear()
        self._keep(packet, arrival_s)
        return 1

    def _follows(self, first: JointPacket, first_arrival_s: float, then, arrival_s) -> bool:
        """Whether ``then`` is stamped after ``first`` by no more than the receiver's clock
        moved between their arrivals plus the window (a datagram is never received before it
        is sent; it may wait in the network or the socket buffer)."""
        elapsed_s = max(arrival_s - first_arrival_s, 0.0)
        return first.time_s < then.time_s <= first.time_s + elapsed_s + self.time_window_s

    def _jump(self, packet: JointPacket, arrival_s: float, reason: str) -> int:
        """A datagram dropped for its time (already counted under ``reason``): if the last
        :data:`CLOCK_JUMP_SAMPLES` such datagrams follow each other, the sender's clock has
        jumped: start the history again from them. Returns how many were kept."""
        if self._jumped:
            last, last_arrival_s, _ = self._jumped[-1]
            ahead = (packet.sequence - last.sequence) % SEQUENCE_MODULUS
            if not (0 < ahead <= self.restart_gap) or not self._follows(
                last, last_arrival_s, packet, arrival_s
            ):
                self._jumped.clear()
        self._jumped.append((packet, arrival_s, reason))
        if len(self._jumped) < CLOCK_JUMP_SAMPLES:
            return 0
        jumped, self._jumped = self._jumped, []
        self.counts.restarts += 1
        self._clear()
        for kept, kept_arrival_s, counted_as in jumped:
            if counted_as == "stale":
                self.counts.stale -= 1
            else:
                self.counts.count_malformed(counted_as, -1)
            self._keep(kept, kept_arrival_s)
        if self.counts.malformed.get("time") == 0:
            del self.counts.malformed["time"]  # every one of them was kept after all
        return len(jumped)

    def _keep(self, packet: JointPacket, arrival_s: float) -> None:
        end = self._end
        if end == len(self._rows):
            self._compact()
            end = self._end
        time_s, arrival_s = float(packet.time_s), float(arrival_s)
        offset_s = arrival_s - time_s
        at = end * _JOINT_ROW.size
        _JOINT_ROW.pack_into(self._bytes, at, time_s, arrival_s, *packet.q, *packet.q_dot, offset_s)
        if offset_s <= self._offset_s or offset_s != offset_s:
            self._offset_s, self._offset_row = offset_s, end
        self._end = end + 1
        if self._end - self._start > self.history:
            self._start += 1
        self._newest = packet
        self._newest_arrival_s = arrival_s
        self.counts.accepted += 1

    def _clear(self) -> None:
        """Forget every kept sample (a restarted sender)."""
        self._start = self._end = 0
        self._offset_s, self._offset_row = math.inf, -1

    def _compact(self) -> None:
        """Move the kept rows to the front (the rows are full)."""
        start, end = self._start, self._end
        self._rows[: end - start] = self._rows[start:end]
        self._start, self._end = 0, end - start
        self._offset_row -= start

    def _kept(self) -> Array:
        """The kept rows (sender time, arrival time, q, q_dot, arrival - sender), oldest
        first: a view."""
        return self._rows[self._start : self._end]

    def _aligned_offset_s(self) -> float:
        """Smallest (arrival - sender) over the kept rows (at least one), s: ``np.min``'s."""
        if self._offset_row < self._start:  # the row of the minimum has left: look again
            offsets = self._rows[self._start : self._end, 8]
            self._offset_s = float(np.min(offsets))
            # The newest row that holds it, to keep it longest (argmin: the first NaN if any).
            self._offset_row = self._end - 1 - int(np.argmin(offsets[::-1]))
        return self._offset_s

    @property
    def newest(self) -> JointPacket | None:
        """The newest accepted datagram."""
        return self._newest

    def __len__(self) -> int:
        return self._end - self._start

    def sample_times(self) -> Array:
        """Times of the kept samples in this receiver's clock (see ``clock``), s."""
        return self._times(self._kept())

    def _times(self, rows: Array) -> Array:
        """Times of ``rows`` in this receiver's clock (a new array)."""
        sender = rows[:, 0]
        if self.clock == "sender":
            return sender.copy()
        if self.clock == "arrival":
            return rows[:, 1].copy()
        return sender + self._aligned_offset_s() if sender.size else sender.copy()

    def samples_after(self, time_s: float) -> tuple[Array, Array, Array]:
        """Kept samples later than ``time_s`` (receiver clock): times (n,), q, q_dot (n, 3)."""
        rows = self._kept()
        times = self._times(rows)
        k = int(np.searchsorted(times, time_s, side="right"))
        return times[k:], rows[k:, 2:5].copy(), rows[k:, 5:8].copy()

    def snapshot(self) -> JointHistory:
        """The kept samples on this receiver's clock (rates NaN where not sent), a copy."""
        history = self._history()
        return JointHistory(history.time_s, history.q.copy(), history.q_dot.copy())

    def _history(self) -> JointHistory:
        """The kept samples, values and rates as views of the rows: for use at once (the
        next sample kept may overwrite them), without copying thousands of rows per frame."""
        rows = self._kept()
        return JointHistory(self._times(rows), rows[:, 2:5], rows[:, 5:8])

    def sample(self, time_s: float, rate_window_s: float = RATE_WINDOW_S) -> JointSample:
        """Joint values and rates at ``time_s`` (this receiver's clock), linearly interpolated.

        Rates come from the datagrams; where they were not sent (``NO_RATES``) they are the
        slope of the values over ``rate_window_s`` around ``time_s``
        (:meth:`tracker.io.joints.JointHistory.interpolate`). What ``snapshot().sample``
        gives, bit for bit, reading only the rows around ``time_s``
        (:func:`tracker.io.joints.sample_joints`).
        """
        rows = self._kept()
        times_s, offset_s = rows[:, 1 if self.clock == "arrival" else 0], None
        if self.clock == "aligned" and len(rows):
            offset_s = self._aligned_offset_s()
            if not math.isfinite(offset_s):  # a hand-fed NaN or infinite time
                times_s, offset_s = self._times(rows), None
        return sample_joints(
            time_s, times_s, rows[:, 2:5], rows[:, 5:8], self.stale_after_s, rate_window_s, offset_s
        )


class JointStreamer:
    """A simulated controller: joint datagrams of a motion at a fixed rate, from a thread.

    Sample ``k`` has time stamp ``start_s + k / rate_hz`` on the local monotonic clock (so a
    :class:`JointReceiver` with ``clock="sender"`` or ``"aligned"`` on this machine shares
    the clock of live camera stamps) and joint values ``joints_at(k / rate_hz)``. After a
    late wake-up the thread catches up, as a real-time target's buffered sends would.

    Parameters
    ----------
    address : (host, port)
        The receiver.
    joints_at : callable
        Seconds since the start -> (q (3,), q_dot (3,)).
    rate_hz : float
    start_s : float, optional
        Monotonic time of sample 0 (default: when :meth:`start` is called).
    """

    def __init__(
        self,
        address: tuple[str, int],
        joints_at: Callable[[float], tuple[Array, Array]],
        rate_hz: float = 1000.0,
        *,
        start_s: float | None = None,
    ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        self.address = (str(address[0]), int(address[1]))
        self.joints_at = joints_at
        self.rate_hz = float(rate_hz)
        self.start_s = start_s
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="joint-streamer", daemon=True)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def start(self) -> JointStreamer:
        if self.start_s is None:
            self.start_s = time.monotonic()
        self._thread.start()
        return self

    def _run(self) -> None:
        k, period = 0, 1.0 / self.rate_hz
        while not self._stop.is_set():
            now = time.monotonic()
            while self.start_s + k * period <= now:
                q, q_dot = self.joints_at(k * period)
                data = encode_joints(k, self.start_s + k * period, q, q_dot)
                try:
                    self._sock.sendto(data, self.address)
                except OSError:
                    pass  # a receiver that is not there yet
                k += 1
            self.sent = k
            self._stop.wait(0.5 * period)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the thread and close the socket."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        self._sock.close()

    def __enter__(self) -> JointStreamer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


class EstimateSender:
    """Sends one estimate datagram per frame to the controller (a live-loop sink).

    Send errors are counted and reported once, never raised: a controller that is not
    listening must not stop the loop.

    Parameters
    ----------
    address : (host, port)
        Where the controller listens (default 127.0.0.1:25001).
    report : callable, optional
        Called once with a message on the first send error.
    """

    name = "udp-estimates"

    def __init__(
        self,
        address: tuple[str, int] = (LOOPBACK, DEFAULT_ESTIMATE_PORT),
        report: Callable[[str], None] | None = None,
    ) -> None:
        self.address = (str(address[0]), int(address[1]))
        self.report = report
        self.sent = 0
        self.errors = 0
        self._sequence = 0
        self._sock: socket.socket | None = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def send(self, estimate: Estimate, latency_s: float, status: int = 0) -> bool:
        if self._sock is None:
            return False
        data = encode_estimate(self._sequence, estimate, latency_s, status)
        self._sequence += 1
        try:
            self._sock.sendto(data, self.address)
        except OSError as exc:
            self.errors += 1
            if self.errors == 1 and self.report is not None:
                host, port = self.address
                self.report(f"estimate datagrams to {host}:{port} fail ({exc}); still trying")
            return False
        self.sent += 1
        return True

    def handle(self, frame, observation, estimate: Estimate, latency_s: float, status: int = 0):
        self.send(estimate, latency_s, status)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> EstimateSender:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class MarkerReceiver:
    """Segmented-marker datagrams in (non-blocking UDP socket, loopback by default).

    Malformed datagrams are dropped and counted by reason in ``counts``; ordering is left to
    the live loop, which drops frames whose time does not increase.

    Parameters
    ----------
    host, port : str, int
    n_points : int, optional
        Rows per view expected (1 + the catheter's markers).
    n_views : int, optional
        Views expected (the rig's).
    """

    def __init__(
        self,
        host: str = LOOPBACK,
        port: int = DEFAULT_MARKER_PORT,
        *,
        n_points: int | None = None,
        n_views: int | None = None,
        rcvbuf_bytes: int = 1 << 21,
    ) -> None:
        self.n_points = n_points
        self.n_views = n_views
        self.counts = StreamCounts()
        self._buffer = bytearray(_RECEIVE_BUFFER_BYTES)
        self._sock: socket.socket | None = _udp_socket(host, port, rcvbuf_bytes)

    @property
    def address(self) -> tuple[str, int]:
        if self._sock is None:
            raise ValueError("the marker receiver is closed")
        return self._sock.getsockname()

    def poll(self) -> list[SegmentedMarkers]:
        """Every pending valid datagram, in arrival order."""
        out: list[SegmentedMarkers] = []
        if self._sock is None:
            return out
        view = memoryview(self._buffer)
        while True:
            try:
                n = self._sock.recv_into(self._buffer)
            except (BlockingIOError, InterruptedError):
                return out
            except OSError:
                return out
            self.counts.received += 1
            try:
                out.append(decode_markers(bytes(view[:n]), self.n_points, self.n_views))
            except DatagramError as exc:
                self.counts.count_malformed(exc.reason)
                continue
            self.counts.accepted += 1

    def receive(self, timeout_s: float) -> list[SegmentedMarkers]:
        """Wait up to ``timeout_s`` for datagrams; the valid ones (maybe none)."""
        if self._sock is None:
            return []
        ready, _, _ = select.select([self._sock], [], [], max(0.0, timeout_s))
        return self.poll() if ready else []

    def frames(self, joints: JointReceiver, idle_timeout_s: float = 1.0) -> Iterator[Frame]:
        """Frames of the markers joined with the joint values at their times.

        Markers whose joint values are not usable (no sample, stream stopped) are skipped; the
        live loop instead keeps them as flagged, predict-only frames. Ends after
        ``idle_timeout_s`` without a datagram.
        """
        while True:
            batch = self.receive(idle_timeout_s)
            if not batch:
                return
            joints.poll()
            for markers in batch:
                sample = joints.sample(markers.time_s)
                if sample.usable:
                    yield markers.frame(sample.q, sample.q_dot)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> MarkerReceiver:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
