"""Fixed-layout UDP datagrams of the live loop (DESIGN.md section 7; byte tables in docs/live.md).

Three little-endian datagrams, each with the same 16-byte header
``magic u32, version u16, flags u16, sequence u32, reserved u32`` (the estimate datagram
keeps its 32 flag bits in the last word, the marker datagram its point count):

- joint values from the robot controller (what a Simulink Real-Time / xPC target sends with a
  Byte Packing block followed by UDP Send): :func:`encode_joints`, :func:`decode_joints`,
  :class:`JointReceiver`;
- the estimate back to the controller: :func:`encode_estimate`, :func:`decode_estimate`,
  :class:`EstimateSender`;
- points already segmented by an external segmenter: :func:`encode_markers`,
  :func:`decode_markers`, :class:`MarkerReceiver`.

:class:`JointStreamer` plays the controller (simulations, demos, tests).

Every double starts at a multiple of 8 bytes. Decoders validate the size, magic, version and
values and raise :class:`DatagramError`, whose ``reason`` is what the receivers count.
Listeners bind to 127.0.0.1 unless told otherwise.
"""

from __future__ import annotations

import enum
import math
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from tracker.types import Estimate, Frame

Array = np.ndarray

LOOPBACK = "127.0.0.1"
DEFAULT_JOINT_PORT = 25000
"""Port the loop listens on for joint datagrams."""
DEFAULT_ESTIMATE_PORT = 25001
"""Port estimate datagrams are sent to (on the controller)."""
DEFAULT_MARKER_PORT = 25002
"""Port the loop listens on for segmented-marker datagrams."""

VERSION = 1


def _magic(tag: bytes) -> int:
    """The u32 whose little-endian bytes spell the 4-character tag."""
    return int.from_bytes(tag, "little")


JOINT_MAGIC = _magic(b"CTJV")  # 0x564A5443
ESTIMATE_MAGIC = _magic(b"CTES")  # 0x53455443
MARKER_MAGIC = _magic(b"CTMK")  # 0x4B4D5443

_HEADER = struct.Struct("<IHHII")  # magic, version, flags, sequence, reserved
JOINT_STRUCT = struct.Struct("<IHHII7d")
"""Joint datagram: header, then time_s, q_r, q_p, q_d, q_r_dot, q_p_dot, q_d_dot (72 bytes)."""
ESTIMATE_STRUCT = struct.Struct("<IHHII6d")
"""Estimate datagram: header (the reserved word holds the flags), then time_s, delta_L_rad,
std_rad, delta_1_rad, q_r_rad, latency_s (64 bytes)."""
_MARKER_HEAD = struct.Struct("<IHHIHHd")  # header with n_points u16 + reserved u16, time_s
MAX_MARKER_POINTS = 64

_UINT32 = 1 << 32
_RECEIVE_BUFFER_BYTES = 65536


class JointFlags(enum.IntFlag):
    """Flag bits of a joint datagram."""

    NONE = 0
    NO_RATES = 1  # the rate fields are not measured (may be NaN): rates come from the values


class DatagramError(ValueError):
    """A datagram that failed validation; ``reason`` is the counter it goes to."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def _check_header(data: bytes, magic: int, name: str, size: int | None) -> tuple[int, ...]:
    if len(data) < _HEADER.size:
        raise DatagramError("size", f"{name} datagram of {len(data)} bytes has no full header")
    header = _HEADER.unpack_from(data)
    if header[0] != magic:
        raise DatagramError("magic", f"{name} datagram has magic 0x{header[0]:08X}")
    if header[1] != VERSION:
        raise DatagramError("version", f"{name} datagram has version {header[1]}, not {VERSION}")
    if size is not None and len(data) != size:
        raise DatagramError("size", f"{name} datagram has {len(data)} bytes, expected {size}")
    return header


# ------------------------------------------------------------------------------------ joints
@dataclass(frozen=True)
class JointPacket:
    """One decoded joint datagram.

    Parameters
    ----------
    sequence : int
        Sender's counter (u32, wraps).
    time_s : float
        Sample time on the sender's clock, s.
    q : array, shape (3,)
        q_r [rad], q_p [mm], q_d [mm].
    q_dot : array, shape (3,)
        Rates (rad/s, mm/s, mm/s); NaN allowed only with ``JointFlags.NO_RATES``.
    flags : JointFlags
    """

    sequence: int
    time_s: float
    q: Array
    q_dot: Array
    flags: JointFlags = JointFlags.NONE


def encode_joints(
    sequence: int,
    time_s: float,
    q: Array,
    q_dot: Array | None = None,
    flags: JointFlags = JointFlags.NONE,
) -> bytes:
    """The 72-byte joint datagram (q_dot None sends NaN rates with ``NO_RATES`` set)."""
    if q_dot is None:
        q_dot, flags = (math.nan,) * 3, flags | JointFlags.NO_RATES
    q, q_dot = [float(x) for x in q], [float(x) for x in q_dot]
    if len(q) != 3 or len(q_dot) != 3:
        raise ValueError("joint values and rates must have 3 entries each (q_r, q_p, q_d)")
    return JOINT_STRUCT.pack(
        JOINT_MAGIC, VERSION, int(flags), sequence % _UINT32, 0, float(time_s), *q, *q_dot
    )


def decode_joints(data: bytes) -> JointPacket:
    """Validate and decode a joint datagram, or raise :class:`DatagramError`."""
    _check_header(data, JOINT_MAGIC, "joint", JOINT_STRUCT.size)
    _, _, flags, sequence, _, time_s, *values = JOINT_STRUCT.unpack(data)
    flags = JointFlags(flags & int(JointFlags.NO_RATES))
    checked = [time_s, *values[:3]] if flags & JointFlags.NO_RATES else [time_s, *values]
    if not all(map(math.isfinite, checked)):
        raise DatagramError("non-finite", "joint datagram holds a NaN or infinite value")
    return JointPacket(sequence, time_s, np.array(values[:3]), np.array(values[3:]), flags)


class JointStatus(enum.Enum):
    """How the joint values at an image time were obtained."""

    OK = "ok"  # interpolated between two samples
    HELD = "held"  # after the newest sample by less than the timeout: newest value held
    CLAMPED = "clamped"  # before the oldest kept sample by less than the timeout
    STALE = "stale"  # the stream has stopped (or the history does not reach back): clamped
    NONE = "none"  # no sample received yet


@dataclass(frozen=True)
class JointSample:
    """Joint values and rates at one time, and how they were obtained."""

    time_s: float
    q: Array
    q_dot: Array
    status: JointStatus
    age_s: float  # time since the newest sample (negative when it is newer), s

    @property
    def usable(self) -> bool:
        return self.status in (JointStatus.OK, JointStatus.HELD, JointStatus.CLAMPED)


@dataclass
class StreamCounts:
    """Counters of one datagram stream."""

    received: int = 0
    accepted: int = 0
    stale: int = 0  # older than the newest (sequence behind, or time not increasing)
    duplicate: int = 0  # same sequence as the newest
    restarts: int = 0  # the sender restarted its sequence: history cleared
    malformed: dict[str, int] = field(default_factory=dict)  # by reason

    @property
    def malformed_total(self) -> int:
        return sum(self.malformed.values())

    def count_malformed(self, reason: str) -> None:
        self.malformed[reason] = self.malformed.get(reason, 0) + 1


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
    stale, and both are dropped and counted, as are malformed ones (by reason). A sequence
    more than ``restart_gap`` behind the newest is a restarted sender: the history is cleared.
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
        self.monotonic = monotonic
        self.counts = StreamCounts()
        # Twice the history, compacted when full: the kept samples stay one contiguous,
        # time-ordered slice, so interpolation is one searchsorted.
        self._sender_s = np.empty(2 * self.history)
        self._arrival_s = np.empty(2 * self.history)
        self._values = np.empty((2 * self.history, 6))
        self._start = self._end = 0
        self._newest: JointPacket | None = None
        self._buffer = bytearray(_RECEIVE_BUFFER_BYTES)
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
        view = memoryview(self._buffer)
        while True:
            try:
                n = self._sock.recv_into(self._buffer)
            except (BlockingIOError, InterruptedError):
                return accepted
            except OSError:  # e.g. an ICMP error queued on the socket: not a datagram
                return accepted
            accepted += self.add_datagram(bytes(view[:n]), self.monotonic())

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
    def add_datagram(self, data: bytes, arrival_s: float) -> int:
        """Validate, order and keep one datagram; 1 if accepted, 0 if dropped (counted)."""
        self.counts.received += 1
        try:
            packet = decode_joints(data)
        except DatagramError as exc:
            self.counts.count_malformed(exc.reason)
            return 0
        return self.add(packet, arrival_s)

    def add(self, packet: JointPacket, arrival_s: float) -> int:
        """Keep a decoded sample unless it is a duplicate or stale (both counted)."""
        newest = self._newest
        if newest is not None:
            ahead = (packet.sequence - newest.sequence) % _UINT32
            if ahead == 0:
                self.counts.duplicate += 1
                return 0
            behind = _UINT32 - ahead if ahead >= _UINT32 // 2 else 0
            if behind > self.restart_gap:
                self.counts.restarts += 1
                self._start = self._end = 0
            elif behind or packet.time_s <= newest.time_s:
                self.counts.stale += 1
                return 0
        self._append(packet, arrival_s)
        self._newest = packet
        self.counts.accepted += 1
        return 1

    def _append(self, packet: JointPacket, arrival_s: float) -> None:
        if self._end == self._sender_s.size:
            keep = self.history - 1
            lo = self._end - keep
            for a in (self._sender_s, self._arrival_s, self._values):
                a[:keep] = a[lo : self._end]
            self._start, self._end = 0, keep
        i = self._end
        self._sender_s[i] = packet.time_s
        self._arrival_s[i] = arrival_s
        self._values[i, :3] = packet.q
        self._values[i, 3:] = packet.q_dot
        if packet.flags & JointFlags.NO_RATES:
            self._values[i, 3:] = np.nan
        self._end += 1
        if self._end - self._start > self.history:
            self._start = self._end - self.history

    @property
    def newest(self) -> JointPacket | None:
        """The newest accepted datagram."""
        return self._newest

    def __len__(self) -> int:
        return self._end - self._start

    def sample_times(self) -> Array:
        """Times of the kept samples in this receiver's clock (see ``clock``), s."""
        sender = self._sender_s[self._start : self._end]
        if self.clock == "sender":
            return sender.copy()
        arrival = self._arrival_s[self._start : self._end]
        if self.clock == "arrival":
            return arrival.copy()
        return sender + float(np.min(arrival - sender)) if sender.size else sender.copy()

    def samples_after(self, time_s: float) -> tuple[Array, Array, Array]:
        """Kept samples later than ``time_s`` (receiver clock): times (n,), q, q_dot (n, 3)."""
        times = self.sample_times()
        k = int(np.searchsorted(times, time_s, side="right"))
        values = self._values[self._start + k : self._end]
        return times[k:], values[:, :3].copy(), values[:, 3:].copy()

    def sample(self, time_s: float, rate_window_s: float = 0.02) -> JointSample:
        """Joint values and rates at ``time_s`` (this receiver's clock), linearly interpolated.

        Rates come from the datagrams; where they were not sent (``NO_RATES``) they are the
        slope of the values over ``rate_window_s`` around ``time_s``.
        """
        n = self._end - self._start
        if n == 0:
            nan = np.full(3, np.nan)
            return JointSample(float(time_s), nan, nan.copy(), JointStatus.NONE, math.inf)
        times = self.sample_times()
        values = self._values[self._start : self._end]
        age = float(time_s - times[-1])
        if time_s > times[-1] or n == 1:
            row = values[-1].copy()
            status = JointStatus.HELD if age <= self.stale_after_s else JointStatus.STALE
            if time_s == times[-1]:
                status = JointStatus.OK
            elif time_s < times[-1]:
                status = JointStatus.CLAMPED if -age <= self.stale_after_s else JointStatus.STALE
        elif time_s < times[0]:
            row = values[0].copy()
            early = times[0] - time_s
            status = JointStatus.CLAMPED if early <= self.stale_after_s else JointStatus.STALE
        else:
            # times[k - 1] <= time_s <= times[k]
            k = min(int(np.searchsorted(times, time_s, side="right")), n - 1)
            w = (time_s - times[k - 1]) / (times[k] - times[k - 1])
            row = (1.0 - w) * values[k - 1] + w * values[k]
            status = JointStatus.OK
        q, q_dot = row[:3], row[3:]
        if not np.all(np.isfinite(q_dot)):
            q_dot = self._slope(times, values, time_s, rate_window_s)
        return JointSample(float(time_s), q, q_dot, status, age)

    @staticmethod
    def _slope(times: Array, values: Array, time_s: float, window_s: float) -> Array:
        if times.size < 2:
            return np.zeros(3)
        lo = max(times[0], min(time_s - window_s / 2, times[-1] - window_s))
        hi = min(times[-1], lo + window_s)
        if hi <= lo:
            return np.zeros(3)
        q_lo = [np.interp(lo, times, values[:, j]) for j in range(3)]
        q_hi = [np.interp(hi, times, values[:, j]) for j in range(3)]
        return (np.array(q_hi) - np.array(q_lo)) / (hi - lo)


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


# --------------------------------------------------------------------------------- estimates
ESTIMATE_FLAG_BITS = 16
"""Bits 0-15 of the estimate flags carry ``tracker.types.Flag``; bits 16-30 the live
loop's status (``LiveStatus``) shifted by 16; bit 31 says the estimate is valid."""
VALID_BIT = 1 << 31


@dataclass(frozen=True)
class EstimateMessage:
    """One decoded estimate datagram (angles in rad, times in s)."""

    sequence: int
    time_s: float
    delta_L_rad: float
    std_rad: float
    delta_1_rad: float
    q_r_rad: float
    latency_s: float
    estimator_flags: int
    status: int
    valid: bool


def encode_estimate(
    sequence: int, estimate: Estimate, latency_s: float, status: int = 0
) -> bytes:
    """The 64-byte estimate datagram of one frame."""
    flags = int(estimate.flags.value) & 0xFFFF
    flags |= (int(status) & 0x7FFF) << ESTIMATE_FLAG_BITS
    valid = estimate.valid
    if valid:
        flags |= VALID_BIT
    delta_1 = estimate.delta_1_rad if valid else math.nan
    return ESTIMATE_STRUCT.pack(
        ESTIMATE_MAGIC,
        VERSION,
        0,
        sequence % _UINT32,
        flags,
        float(estimate.time_s),
        float(estimate.delta_L_rad),
        float(estimate.std_rad),
        float(delta_1),
        float(estimate.q_r_rad),
        float(latency_s),
    )


def decode_estimate(data: bytes) -> EstimateMessage:
    """Validate and decode an estimate datagram, or raise :class:`DatagramError`."""
    _check_header(data, ESTIMATE_MAGIC, "estimate", ESTIMATE_STRUCT.size)
    _, _, _, sequence, flags, t, delta_L, std, delta_1, q_r, latency = ESTIMATE_STRUCT.unpack(
        data
    )
    return EstimateMessage(
        sequence=sequence,
        time_s=t,
        delta_L_rad=delta_L,
        std_rad=std,
        delta_1_rad=delta_1,
        q_r_rad=q_r,
        latency_s=latency,
        estimator_flags=flags & 0xFFFF,
        status=(flags >> ESTIMATE_FLAG_BITS) & 0x7FFF,
        valid=bool(flags & VALID_BIT),
    )


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


# ----------------------------------------------------------------------------------- markers
@dataclass(frozen=True)
class SegmentedMarkers:
    """Points of both views segmented elsewhere, without joint values.

    Rows ``[tip, marker_0, ...]`` as in :class:`tracker.types.Frame`; NaN rows for points
    not found. The live loop joins them with the joint values at ``time_s``.
    """

    time_s: float
    uv_front: Array  # (P, 2)
    uv_side: Array  # (P, 2)
    cov_front: Array  # (P, 2, 2)
    cov_side: Array  # (P, 2, 2)
    sequence: int = 0

    def frame(self, q: Array, q_dot: Array | None) -> Frame:
        """The pipeline frame with these joint values."""
        return Frame(
            time_s=float(self.time_s),
            q=np.asarray(q, dtype=float),
            q_dot=None if q_dot is None else np.asarray(q_dot, dtype=float),
            uv_front=self.uv_front,
            uv_side=self.uv_side,
            cov_front=self.cov_front,
            cov_side=self.cov_side,
        )


def marker_datagram_size(n_points: int) -> int:
    """Bytes of a marker datagram with ``n_points`` rows per view: 24 + 48 n_points."""
    return _MARKER_HEAD.size + 2 * n_points * 3 * 8


def _sigma_from_covariance(cov: Array) -> Array:
    """Isotropic sigma per row: sqrt of the mean of the two variances (NaN stays NaN)."""
    cov = np.asarray(cov, dtype=float)
    return np.sqrt(0.5 * (cov[..., 0, 0] + cov[..., 1, 1]))


def encode_markers(
    sequence: int,
    time_s: float,
    uv_front: Array,
    uv_side: Array,
    sigma_front: Array,
    sigma_side: Array,
) -> bytes:
    """A marker datagram: per view ``n_points`` rows of (u, v, sigma); NaN rows for missing.

    ``sigma`` is the isotropic segmentation std of each point, in the image unit (px, or mm
    in an orthographic plane); scalars broadcast over the rows.
    """
    uv_f, uv_s = np.asarray(uv_front, float), np.asarray(uv_side, float)
    n = uv_f.shape[0]
    if uv_f.shape != (n, 2) or uv_s.shape != (n, 2) or not 1 <= n <= MAX_MARKER_POINTS:
        raise ValueError(
            f"marker rows must have shape (n, 2) in both views with 1 <= n <= "
            f"{MAX_MARKER_POINTS}, got {uv_f.shape} and {uv_s.shape}"
        )
    rows = []
    for uv, sigma in ((uv_f, sigma_front), (uv_s, sigma_side)):
        sigma = np.broadcast_to(np.asarray(sigma, float), (n,))
        rows.append(np.column_stack([uv, sigma]))
    head = _MARKER_HEAD.pack(MARKER_MAGIC, VERSION, 0, sequence % _UINT32, n, 0, float(time_s))
    return head + np.concatenate(rows).astype("<f8").tobytes()


def encode_segmented(markers: SegmentedMarkers) -> bytes:
    """:func:`encode_markers` of a :class:`SegmentedMarkers` (covariances -> isotropic sigma)."""
    return encode_markers(
        markers.sequence,
        markers.time_s,
        markers.uv_front,
        markers.uv_side,
        _sigma_from_covariance(markers.cov_front),
        _sigma_from_covariance(markers.cov_side),
    )


def decode_markers(data: bytes, n_points: int | None = None) -> SegmentedMarkers:
    """Validate and decode a marker datagram, or raise :class:`DatagramError`.

    A row is missing (NaN in the result) when its u or v is NaN; a present row needs finite
    u, v and a positive finite sigma. ``n_points`` checks the row count against the catheter.
    """
    if len(data) < _MARKER_HEAD.size:
        raise DatagramError("size", f"marker datagram of {len(data)} bytes has no full header")
    _check_header(data, MARKER_MAGIC, "marker", None)
    _, _, _, sequence, n, _, time_s = _MARKER_HEAD.unpack_from(data)
    if not 1 <= n <= MAX_MARKER_POINTS:
        raise DatagramError("points", f"marker datagram declares {n} points per view")
    if len(data) != marker_datagram_size(n):
        raise DatagramError(
            "size", f"marker datagram has {len(data)} bytes, expected {marker_datagram_size(n)}"
        )
    if n_points is not None and n != n_points:
        raise DatagramError(
            "points", f"marker datagram has {n} points per view, the catheter has {n_points}"
        )
    if not math.isfinite(time_s):
        raise DatagramError("non-finite", "marker datagram time is not finite")
    rows = np.frombuffer(data, dtype="<f8", offset=_MARKER_HEAD.size).reshape(2, n, 3)
    out = []
    for view in rows:
        uv, sigma = view[:, :2].astype(float), view[:, 2].astype(float)
        missing = np.isnan(uv).any(axis=1)
        present = ~missing
        if not (np.all(np.isfinite(uv[present])) and np.all(np.isfinite(sigma[present]))):
            raise DatagramError("non-finite", "marker datagram holds an infinite value")
        if np.any(sigma[present] <= 0):
            raise DatagramError("sigma", "marker datagram holds a non-positive sigma")
        uv[missing] = np.nan
        cov = (sigma**2)[:, None, None] * np.eye(2)
        cov[missing] = np.nan
        out.extend([uv, cov])
    return SegmentedMarkers(float(time_s), out[0], out[2], out[1], out[3], sequence)


class MarkerReceiver:
    """Segmented-marker datagrams in (non-blocking UDP socket, loopback by default).

    Malformed datagrams are dropped and counted by reason in ``counts``; ordering is left to
    the live loop, which drops frames whose time does not increase.

    Parameters
    ----------
    host, port : str, int
    n_points : int, optional
        Rows per view expected (1 + the catheter's markers).
    """

    def __init__(
        self,
        host: str = LOOPBACK,
        port: int = DEFAULT_MARKER_PORT,
        *,
        n_points: int | None = None,
        rcvbuf_bytes: int = 1 << 21,
    ) -> None:
        self.n_points = n_points
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
                out.append(decode_markers(bytes(view[:n]), self.n_points))
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
