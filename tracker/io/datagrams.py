"""Fixed-layout UDP datagrams of the live loop: layouts, encoders and decoders.

docs/design.md section 7; the byte tables are in docs/live.md. Three little-endian
datagrams, each with the same 16-byte header ``magic u32, version u16, flags u16,
sequence u32, reserved u32`` (the estimate datagram keeps its 32 flag bits in the last word,
the marker datagram its point count):

- joint values from the robot controller (what a Simulink Real-Time / xPC target sends with a
  Byte Packing block followed by UDP Send): :func:`encode_joints`, :func:`decode_joints`;
- the estimate back to the controller: :func:`encode_estimate`, :func:`decode_estimate`;
- points already segmented by an external segmenter: :func:`encode_markers`,
  :func:`decode_markers`.

Every double starts at a multiple of 8 bytes. Decoders validate the size, magic, version and
values (finite, and within the limits of :mod:`tracker.io.limits`: the robot's joint ranges,
the cameras' coordinates) and raise :class:`DatagramError`, whose ``reason`` is what the
receivers count. The
sockets that send and receive these datagrams are in :mod:`tracker.io.udp`.
"""

from __future__ import annotations

import enum
import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from tracker.io.limits import (
    JOINT_RATE_LIMITS,
    JOINT_VALUE_LIMITS,
    MAX_DATAGRAM_TIME_S,
    MAX_IMAGE_COORDINATE,
    MAX_POINT_SIGMA,
    joint_sample_in_range,
)
from tracker.types import Estimate, Frame

Array = np.ndarray

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
# Header with n_points u16 and n_views u16 (0 means 2: the bi-plane layout of the first senders),
# then time_s; then n_views blocks of n_points rows (u, v, sigma).
_MARKER_HEAD = struct.Struct("<IHHIHHd")
MAX_MARKER_POINTS = 64
MAX_VIEWS = 8
SEQUENCE_MODULUS = 1 << 32
"""Sequence numbers are u32: they wrap at this."""


class JointFlags(enum.IntFlag):
    """Flag bits of a joint datagram."""

    NONE = 0
    NO_RATES = 1  # the rate fields are not measured (may be NaN): rates come from the values


# The decoder runs once per datagram at 1 kHz: it masks the flags with a plain int and picks
# the member from this table, since IntFlag arithmetic costs a microsecond an operation.
_NO_RATES_BIT = int(JointFlags.NO_RATES)
_JOINT_FLAGS = (JointFlags.NONE, JointFlags.NO_RATES)
_NAN3 = (math.nan,) * 3


class DatagramError(ValueError):
    """A datagram that failed validation; ``reason`` is the counter it goes to."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def _check_header(
    data: bytes | memoryview, magic: int, name: str, size: int | None
) -> tuple[int, ...]:
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
class JointPacket(NamedTuple):
    """One decoded joint datagram (a named tuple: a thousand are made a second).

    Parameters
    ----------
    sequence : int
        Sender's counter (u32, wraps).
    time_s : float
        Sample time on the sender's clock, s.
    q : sequence of 3 floats
        q_r [rad], q_p [mm], q_d [mm] (a tuple from :func:`decode_joints`; any sequence or
        array of three when made by hand).
    q_dot : sequence of 3 floats
        Rates (rad/s, mm/s, mm/s); NaN where not measured (:func:`decode_joints` makes all
        three NaN with ``JointFlags.NO_RATES``).
    flags : JointFlags
    """

    sequence: int
    time_s: float
    q: Sequence[float]
    q_dot: Sequence[float]
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
        JOINT_MAGIC, VERSION, int(flags), sequence % SEQUENCE_MODULUS, 0, float(time_s), *q, *q_dot
    )


def decode_joints(data: bytes | memoryview) -> JointPacket:
    """Validate and decode a joint datagram, or raise :class:`DatagramError`.

    Plain ``struct`` and float comparisons (a few microseconds): the receiver decodes up to a
    thousand of these a second on the live loop's thread.
    """
    if len(data) != JOINT_STRUCT.size:
        _check_header(data, JOINT_MAGIC, "joint", JOINT_STRUCT.size)  # raises, by reason
    magic, version, flags, sequence, _, time_s, *values = JOINT_STRUCT.unpack(data)
    if magic != JOINT_MAGIC or version != VERSION:
        _check_header(data, JOINT_MAGIC, "joint", JOINT_STRUCT.size)  # raises, by reason
    no_rates = flags & _NO_RATES_BIT
    q, q_dot = tuple(values[:3]), tuple(values[3:])
    if not all(map(math.isfinite, (time_s, *q) if no_rates else (time_s, *values))):
        raise DatagramError("non-finite", "joint datagram holds a NaN or infinite value")
    _check_time(time_s, "joint")
    if not joint_sample_in_range(q, None if no_rates else q_dot):
        raise DatagramError(
            "range",
            f"joint datagram values {list(q)} or rates {list(q_dot)} are outside the"
            f" robot's ranges (|q| <= {JOINT_VALUE_LIMITS.tolist()},"
            f" |q_dot| <= {JOINT_RATE_LIMITS.tolist()})",
        )
    return JointPacket(sequence, time_s, q, _NAN3 if no_rates else q_dot, _JOINT_FLAGS[no_rates])


def _check_time(time_s: float, name: str) -> None:
    if not abs(time_s) <= MAX_DATAGRAM_TIME_S:
        raise DatagramError(
            "range", f"{name} datagram time {time_s:.6g} s is beyond {MAX_DATAGRAM_TIME_S:g} s"
        )


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


def encode_estimate(sequence: int, estimate: Estimate, latency_s: float, status: int = 0) -> bytes:
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
        sequence % SEQUENCE_MODULUS,
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
    _, _, _, sequence, flags, t, delta_L, std, delta_1, q_r, latency = ESTIMATE_STRUCT.unpack(data)
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


# ----------------------------------------------------------------------------------- markers
@dataclass(frozen=True)
class SegmentedMarkers:
    """Points of every view segmented elsewhere, without joint values.

    ``uv`` and ``cov`` hold one array per view in the rig's order, rows ``[tip, marker_0, ...]``
    as in :class:`tracker.types.Frame`; NaN rows for points not found. The live loop joins
    them with the joint values at ``time_s``.
    """

    time_s: float
    uv: tuple[Array, ...]  # per view (P, 2)
    cov: tuple[Array, ...]  # per view (P, 2, 2)
    sequence: int = 0

    def frame(self, q: Array, q_dot: Array | None, images=None) -> Frame:
        """The pipeline frame with these joint values (and the images, if given)."""
        return Frame(
            time_s=float(self.time_s),
            q=np.asarray(q, dtype=float),
            q_dot=None if q_dot is None else np.asarray(q_dot, dtype=float),
            uv=self.uv,
            cov=self.cov,
            images=None if images is None else tuple(images),
        )


def marker_datagram_size(n_points: int, n_views: int = 2) -> int:
    """Bytes of a marker datagram with ``n_points`` rows per view: 24 + 24 n_views n_points."""
    return _MARKER_HEAD.size + n_views * n_points * 3 * 8


def _sigma_from_covariance(cov: Array) -> Array:
    """Isotropic sigma per row: sqrt of the mean of the two variances (NaN stays NaN)."""
    cov = np.asarray(cov, dtype=float)
    return np.sqrt(0.5 * (cov[..., 0, 0] + cov[..., 1, 1]))


def encode_markers(sequence: int, time_s: float, uv, sigma) -> bytes:
    """A marker datagram: per view ``n_points`` rows of (u, v, sigma); NaN rows for missing.

    Parameters
    ----------
    uv : sequence of arrays (n_points, 2)
        Image points of each view, in the rig's order.
    sigma : sequence of arrays (n_points,) or scalars
        Isotropic segmentation std of each point, in the image unit (px, or mm in an
        orthographic plane); scalars broadcast over the rows.
    """
    uv = [np.asarray(u, float) for u in uv]
    n = uv[0].shape[0] if uv and uv[0].ndim == 2 else 0
    if (
        not 2 <= len(uv) <= MAX_VIEWS
        or len(sigma) != len(uv)
        or any(u.shape != (n, 2) for u in uv)
        or not 1 <= n <= MAX_MARKER_POINTS
    ):
        raise ValueError(
            f"marker rows must have shape (n, 2) in each of 2 to {MAX_VIEWS} views, with one"
            f" sigma per view and 1 <= n <= {MAX_MARKER_POINTS}, got"
            f" {[u.shape for u in uv]} and {len(sigma)} sigmas"
        )
    rows = [
        np.column_stack([u, np.broadcast_to(np.asarray(sg, float), (n,))])
        for u, sg in zip(uv, sigma, strict=True)
    ]
    sequence %= SEQUENCE_MODULUS
    head = _MARKER_HEAD.pack(MARKER_MAGIC, VERSION, 0, sequence, n, len(uv), float(time_s))
    return head + np.concatenate(rows).astype("<f8").tobytes()


def encode_segmented(markers: SegmentedMarkers) -> bytes:
    """:func:`encode_markers` of a :class:`SegmentedMarkers` (covariances -> isotropic sigma)."""
    sigma = [_sigma_from_covariance(c) for c in markers.cov]
    return encode_markers(markers.sequence, markers.time_s, markers.uv, sigma)


def decode_markers(
    data: bytes, n_points: int | None = None, n_views: int | None = None
) -> SegmentedMarkers:
    """Validate and decode a marker datagram, or raise :class:`DatagramError`.

    A row is missing (NaN in the result) when its u or v is NaN; a present row needs finite
    u, v and a positive finite sigma. ``n_points`` and ``n_views`` check the row and view
    counts against the catheter and the rig.
    """
    if len(data) < _MARKER_HEAD.size:
        raise DatagramError("size", f"marker datagram of {len(data)} bytes has no full header")
    _check_header(data, MARKER_MAGIC, "marker", None)
    _, _, _, sequence, n, views, time_s = _MARKER_HEAD.unpack_from(data)
    views = views or 2
    if not 1 <= n <= MAX_MARKER_POINTS:
        raise DatagramError("points", f"marker datagram declares {n} points per view")
    if not 2 <= views <= MAX_VIEWS:
        raise DatagramError("views", f"marker datagram declares {views} views")
    if len(data) != marker_datagram_size(n, views):
        raise DatagramError(
            "size",
            f"marker datagram has {len(data)} bytes, expected {marker_datagram_size(n, views)}",
        )
    if n_points is not None and n != n_points:
        raise DatagramError(
            "points", f"marker datagram has {n} points per view, the catheter has {n_points}"
        )
    if n_views is not None and views != n_views:
        raise DatagramError(
            "views", f"marker datagram has {views} views, the rig has {n_views}"
        )
    if not math.isfinite(time_s):
        raise DatagramError("non-finite", "marker datagram time is not finite")
    _check_time(time_s, "marker")
    rows = np.frombuffer(data, dtype="<f8", offset=_MARKER_HEAD.size).reshape(views, n, 3)
    uvs, covs = [], []
    for view in rows:
        uv, sigma = view[:, :2].astype(float), view[:, 2].astype(float)
        missing = np.isnan(uv).any(axis=1)
        present = ~missing
        if not (np.all(np.isfinite(uv[present])) and np.all(np.isfinite(sigma[present]))):
            raise DatagramError("non-finite", "marker datagram holds an infinite value")
        if np.any(sigma[present] <= 0):
            raise DatagramError("sigma", "marker datagram holds a non-positive sigma")
        if np.any(np.abs(uv[present]) > MAX_IMAGE_COORDINATE) or np.any(
            sigma[present] > MAX_POINT_SIGMA
        ):
            raise DatagramError(
                "range",
                f"marker datagram holds a point beyond {MAX_IMAGE_COORDINATE:g} or a sigma"
                f" beyond {MAX_POINT_SIGMA:g} (px or mm)",
            )
        uv[missing] = np.nan
        cov = (sigma**2)[:, None, None] * np.eye(2)
        cov[missing] = np.nan
        uvs.append(uv)
        covs.append(cov)
    return SegmentedMarkers(float(time_s), tuple(uvs), tuple(covs), sequence)
