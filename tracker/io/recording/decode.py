"""The messages of a recording turned into arrays, every problem counted once per kind.

:class:`tracker.io.recording.reader.Recording` gathers each topic's messages and hands them
here a topic at a time: their JSON parsed (:func:`json_messages`) and kept by time stamp
(:class:`Store`); then the joint blocks become one sorted joint stream, the marker messages
one array per view, ``/truth`` the labels, ``/estimates/<method>`` the estimates. Whatever
does not fit its schema, lies outside the session or beyond the physical ranges of
:mod:`tracker.io.limits` is skipped and counted in :class:`Problems`.

The joint blocks are protobuf in format version 2, taken column by column straight from
their bytes (:mod:`tracker.io.recording.joint_samples`); in version 1 they are JSON, and at
1 kHz (50 samples of 7 JSON numbers per frame, about 6.7 kB) their decompression and parsing
into Python floats were most of the reading time. Everything after the parse works on whole
columns; a version 1 block that does not fit the schema sends the joint stream the slower,
block-by-block way.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import orjson

from tracker.io.limits import MAX_ANGLE_RAD, joints_in_range, points_in_range
from tracker.io.recording import joint_samples
from tracker.io.recording.schema import (
    JOINT_COLUMNS,
    RATE_COLUMNS,
    TOPIC_JOINTS,
    TOPIC_TRUTH,
    FrameLabels,
    MarkerQuality,
    RecordingError,
    decode_json,
    estimate_topic,
)
from tracker.types import Estimate, Flag

Array = np.ndarray

PROBLEMS = {
    "out_of_order": "message(s) out of time order ({where}): sorted by time",
    "duplicate": "message(s) repeat an earlier time stamp ({where}): kept the first of each",
    "nan": "message(s) hold NaN or infinite values ({where}): those points count as missing",
    "nan_joints": "joint sample(s) hold NaN or null values ({where}): skipped",
    "nan_truth": "message(s) hold a NaN truth ({where}): truth unknown for those frames",
    "out_of_session": "message(s) or sample(s) stamped outside the session ({where}): skipped",
    "out_of_range": (
        "value(s) beyond the physical ranges ({where}): skipped (points count as missing,"
        " truth as unknown)"
    ),
    "malformed": "message(s) do not match their schema ({where}): skipped",
    "bad_image": "image(s) cannot be decoded ({where}): those frames have no images",
    "unknown_channel": "message(s) on an undeclared channel ({where}): skipped",
}
"""One warning per kind of problem, whatever the number of topics it touches."""


@dataclass
class Problems:
    """Counts of each kind of problem (:data:`PROBLEMS`) per topic."""

    counts: dict[tuple[str, str], int] = field(default_factory=dict)

    def add(self, kind: str, topic: str, n: int = 1) -> None:
        self.counts[(kind, topic)] = self.counts.get((kind, topic), 0) + n

    def warnings(self) -> list[str]:
        """One warning per kind, naming the count on each topic."""
        by_kind: dict[str, dict[str, int]] = {}
        for (kind, topic), n in self.counts.items():
            by_kind.setdefault(kind, {})[topic] = n
        out = []
        for kind, text in PROBLEMS.items():
            topics = by_kind.get(kind)
            if topics:
                where = ", ".join(f"{n} on {topic}" for topic, n in sorted(topics.items()))
                out.append(f"{sum(topics.values())} " + text.format(where=where))
        return out


# -------------------------------------------------------------------------------- messages
@dataclass(frozen=True)
class Store:
    """The messages of one topic by time stamp: the first message of each log time.

    Parameters
    ----------
    stamps : int array, shape (n,)
        Log times, ns, increasing.
    values : list of length n
        The parsed message (or image reference) of each.
    """

    stamps: Array
    values: list

    @classmethod
    def first_of(cls, stamps: Array, values: Sequence, topic: str, problems: Problems) -> Store:
        """The first of the messages (in file order) at each log time; the others counted as
        duplicates on ``topic``."""
        unique, first = np.unique(stamps, return_index=True)  # first: where each first occurs
        if unique.size < len(values):
            problems.add("duplicate", topic, len(values) - unique.size)
        return cls(unique, [values[i] for i in first.tolist()])

    def where(self, keep: Array) -> Store:
        """The messages where ``keep`` (bool, one per message) is true."""
        values = [v for v, k in zip(self.values, keep.tolist(), strict=True) if k]
        return Store(self.stamps[keep], values)

    def __len__(self) -> int:
        return len(self.values)

    def get(self, stamp: int) -> Any:
        """The message at ``stamp`` (None: none)."""
        i = int(self.stamps.searchsorted(stamp))
        return self.values[i] if i < self.stamps.size and self.stamps[i] == stamp else None

    def at(self, stamps: Array) -> list:
        """The message at each of ``stamps`` (sorted log times, ns), None where there is none."""
        out: list = [None] * len(stamps)
        if not self.values:
            return out
        i = np.minimum(self.stamps.searchsorted(stamps), self.stamps.size - 1)
        found = np.flatnonzero(self.stamps[i] == stamps)
        values = self.values
        for k, j in zip(found.tolist(), i[found].tolist(), strict=True):
            out[k] = values[j]
        return out


def json_messages(data: Sequence[bytes], topic: str, problems: Problems) -> list:
    """The JSON objects of a topic's messages, None (counted as malformed) for a message that
    is not one (:func:`tracker.io.recording.schema.decode_json`, NaN literals accepted)."""
    loads = orjson.loads
    try:
        # One orjson call per message, no wrapper: the common case of well-formed messages.
        payloads = [loads(d) for d in data]
    except orjson.JSONDecodeError:
        payloads = [_json_or_none(d) for d in data]
    bad = 0
    for i, payload in enumerate(payloads):
        if payload.__class__ is not dict and not isinstance(payload, dict):
            payloads[i] = None
            bad += 1
    if bad:
        problems.add("malformed", topic, bad)
    return payloads


def _json_or_none(data: bytes) -> Any:
    try:
        return decode_json(data)
    except (ValueError, UnicodeDecodeError):
        return None


# ---------------------------------------------------------------------------------- joints
def json_joint_columns(
    blocks: list[dict], problems: Problems, source: str
) -> tuple[Array, Array, Array, bool]:
    """The samples of the ``/joints`` blocks of format version 1 (parsed JSON), in block
    order: time stamps, ns, (n,); values (n, 3); rates (n, 3), NaN where not measured; and
    whether any block measured rates. A block that does not fit the schema is counted and
    dropped.

    Raises
    ------
    RecordingError
        No block with samples fits the schema.
    """
    columns = _joint_columns(blocks)
    if columns is None:  # a block that does not fit the schema, or no sample
        columns = _joint_columns_joined(blocks, problems, source)
    return columns


def protobuf_joint_columns(
    messages: list[bytes], problems: Problems, source: str
) -> tuple[Array, Array, Array, bool]:
    """:func:`json_joint_columns` for the protobuf blocks of format version 2
    (:func:`tracker.io.recording.joint_samples.joint_columns`)."""
    t, q, r, any_rates, malformed = joint_samples.joint_columns(messages)
    if malformed:
        problems.add("malformed", TOPIC_JOINTS, malformed)
    if t.size == 0 and malformed == len(messages):
        raise RecordingError(f"{source}: channel {TOPIC_JOINTS} holds no valid samples")
    if t.size == 0:
        raise RecordingError(f"{source}: channel {TOPIC_JOINTS} holds no joint samples")
    return t, q, r, any_rates


def joint_stream(
    columns: tuple[Array, Array, Array, bool],
    problems: Problems,
    source: str,
    session_ns: tuple[int, int],
):
    """The joint samples of the ``/joints`` blocks, sorted; samples that are NaN, repeated,
    stamped outside ``session_ns`` (log times, ns) or beyond the robot's ranges dropped.

    Parameters
    ----------
    columns : tuple
        The blocks' samples in block order (:func:`json_joint_columns`,
        :func:`protobuf_joint_columns`): time stamps, ns, (n,); values (n, 3); rates (n, 3);
        whether any block measured rates.

    Returns
    -------
    time_ns : int array, shape (n,)
    q : array, shape (n, 3)
    q_dot : array, shape (n, 3), or None when the recording has no rates

    Raises
    ------
    RecordingError
        No valid joint sample.
    """
    t, q, r, any_rates = columns
    # Each check first looks at the whole array at once (a reduction along rows of three
    # costs ten times more) and picks the bad rows only when there are some.
    if not (np.isfinite(q).all() and (not any_rates or np.isfinite(r).all())):
        bad = ~np.all(np.isfinite(q), axis=1)
        if any_rates:
            bad |= ~np.all(np.isfinite(r), axis=1)
        problems.add("nan_joints", TOPIC_JOINTS, int(np.count_nonzero(bad)))
        t, q, r = t[~bad], q[~bad], r[~bad]
    bad = (t < session_ns[0]) | (t > session_ns[1])
    if bad.any():
        problems.add("out_of_session", TOPIC_JOINTS + " (samples)", int(np.count_nonzero(bad)))
        t, q, r = t[~bad], q[~bad], r[~bad]
    rates = r if any_rates else None
    if not _all_in_range(q, rates):
        bad = ~joints_in_range(q, rates)
        problems.add("out_of_range", TOPIC_JOINTS + " (samples)", int(np.count_nonzero(bad)))
        t, q, r = t[~bad], q[~bad], r[~bad]
    if t.size > 1 and not np.all(t[1:] > t[:-1]):  # else sorted and no time repeated
        if np.any(np.diff(t) < 0):
            problems.add("out_of_order", TOPIC_JOINTS + " (samples)", int(np.sum(np.diff(t) < 0)))
        order = np.argsort(t, kind="stable")
        t, q, r = t[order], q[order], r[order]
        keep = np.ones(t.size, dtype=bool)
        keep[1:] = t[1:] != t[:-1]
        if not keep.all():
            problems.add("duplicate", TOPIC_JOINTS + " (samples)", int(np.count_nonzero(~keep)))
            t, q, r = t[keep], q[keep], r[keep]
    if t.size == 0:
        raise RecordingError(f"{source}: channel {TOPIC_JOINTS} holds no valid joint sample")
    return t, q, r if any_rates else None


def _joint_columns_joined(
    blocks: list[dict], problems: Problems, source: str
) -> tuple[Array, Array, Array, bool]:
    """The samples of the joint blocks, the blocks' columns joined (or, where they do not fit
    the schema, block by block): time stamps, ns, (n,); values (n, 3); rates (n, 3), NaN where
    not measured; and whether any block measured rates."""
    # Gather the blocks' columns and convert each once (one numpy call per block was a
    # third of the reading time at 1 kHz); a block that does not fit the schema is
    # dropped whole.
    stamps: list = []
    q_r, q_p, q_d, r_r, r_p, r_d = ([] for _ in range(6))
    any_rates = False
    consistent = True
    for payload in blocks:
        try:
            t = payload["time_ns"]
            q_r += payload["q_r_rad"]
            q_p += payload["q_p_mm"]
            q_d += payload["q_d_mm"]
            if payload.get("q_r_dot_rad_s") is None:
                r_r += [None] * len(t)
                r_p += [None] * len(t)
                r_d += [None] * len(t)
            else:
                any_rates = True
                r_r += payload["q_r_dot_rad_s"]
                r_p += payload["q_p_dot_mm_s"]
                r_d += payload["q_d_dot_mm_s"]
            stamps += t
        except (KeyError, TypeError):
            consistent = False  # the slow path below names the block
            break
    # Columns of unequal length (a block that does not fit the schema) also go the slow way.
    consistent = consistent and all(len(c) == len(stamps) for c in (q_r, q_p, q_d, r_r, r_p, r_d))
    columns = dict(zip(JOINT_COLUMNS + RATE_COLUMNS, (q_r, q_p, q_d, r_r, r_p, r_d), strict=True))
    if not stamps and consistent:
        raise RecordingError(f"{source}: channel {TOPIC_JOINTS} holds no joint samples")
    try:
        if not consistent:
            raise ValueError
        t = _stamps(stamps)
        # numpy turns null (None) into NaN: such samples are dropped below.
        q = np.column_stack([np.array(columns[n], dtype=float) for n in JOINT_COLUMNS])
        r = np.column_stack([np.array(columns[n], dtype=float) for n in RATE_COLUMNS])
        if t.ndim != 1 or q.shape != (t.size, 3) or r.shape != (t.size, 3):
            raise ValueError
    except (TypeError, ValueError, OverflowError):
        t, q, r = _joint_blocks_one_by_one(blocks, problems, source)
        any_rates = bool(np.isfinite(r).any())
    return t, q, r, any_rates


def _joint_columns(blocks: list[dict]) -> tuple[Array, Array, Array, bool] | None:
    """:func:`_joint_columns_joined` for blocks that all fit the schema and all measure the
    rates, or none does; None otherwise (or without samples).

    Each column is converted straight from the blocks' lists (``np.fromiter`` converts each
    item as ``np.array`` does, and raises where that would make another shape): joining the
    lists first walked every float object once more, and the floats of a 1 kHz stream are
    scattered across memory.
    """
    total = 0
    rated = 0
    for payload in blocks:
        t = payload.get("time_ns")
        if t.__class__ is not list:
            return None
        n = len(t)
        rates = payload.get(RATE_COLUMNS[0]) is not None
        for name in JOINT_COLUMNS + RATE_COLUMNS if rates else JOINT_COLUMNS:
            column = payload.get(name)
            if column.__class__ is not list or len(column) != n:
                return None
        total += n
        rated += rates
    if total == 0 or 0 < rated < len(blocks):
        return None
    chain = itertools.chain.from_iterable
    try:
        t = np.fromiter(chain([p["time_ns"] for p in blocks]), np.int64, total)
        q = np.empty((total, 3))
        r = np.full((total, 3), np.nan)
        for names, out in ((JOINT_COLUMNS, q), (RATE_COLUMNS if rated else (), r)):
            for k, name in enumerate(names):
                out[:, k] = np.fromiter(chain([p[name] for p in blocks]), float, total)
    except (TypeError, ValueError, OverflowError):
        return None
    return t, q, r, rated > 0


def _all_in_range(q: Array, rates: Array | None) -> bool:
    """Whether every sample is within the robot's ranges (:func:`joints_in_range`), from
    each column's extremes (the values hold no NaN here)."""
    if q.shape[0] == 0:
        return True

    def extremes(values: Array) -> Array:
        # Along contiguous columns: reducing a (n, 3) array along its rows is 20 times slower.
        columns = np.ascontiguousarray(values.T)
        return np.vstack([columns.min(axis=1), columns.max(axis=1)])

    return bool(joints_in_range(extremes(q), None if rates is None else extremes(rates)).all())


_OUTSIDE_INT64 = np.iinfo(np.int64).min
"""Stands for a time stamp beyond 64-bit integers: outside every session."""


def _stamps(values: list) -> Array:
    """Integer time stamps, ns; those beyond 64-bit integers become :data:`_OUTSIDE_INT64`."""
    try:
        return np.array(values, dtype=np.int64)
    except OverflowError:
        limit = 2**63
        return np.array(
            [x if -limit < x < limit else _OUTSIDE_INT64 for x in values], dtype=np.int64
        )


def _joint_blocks_one_by_one(
    blocks: list[dict], problems: Problems, source: str
) -> tuple[Array, Array, Array]:
    """The joint blocks converted one at a time, skipping those that do not fit the schema
    (the slow path, taken only when the fast one fails)."""
    stamps, qs, rates = [], [], []
    for payload in blocks:
        try:
            t = _stamps(payload["time_ns"])
            q = np.column_stack([np.array(payload[n], dtype=float) for n in JOINT_COLUMNS])
            if payload.get(RATE_COLUMNS[0]) is None:
                r = np.full((t.size, 3), np.nan)
            else:
                r = np.column_stack([np.array(payload[n], float) for n in RATE_COLUMNS])
            if t.ndim != 1 or q.shape != (t.size, 3) or r.shape != (t.size, 3):
                raise ValueError
        except (KeyError, TypeError, ValueError, OverflowError):
            problems.add("malformed", TOPIC_JOINTS)
            continue
        stamps.append(t)
        qs.append(q)
        rates.append(r)
    if not stamps:
        raise RecordingError(f"{source}: channel {TOPIC_JOINTS} holds no valid samples")
    return np.concatenate(stamps), np.concatenate(qs), np.concatenate(rates)


# --------------------------------------------------------------------------------- markers
def point_count(stores: list[Store]) -> tuple[int | None, list[int]]:
    """The most common number of rows of the marker messages (None without any), and every
    number seen."""
    lengths = [
        len(p["uv"])
        for store in stores
        for p in store.values
        if isinstance(p, dict) and isinstance(p.get("uv"), list)
    ]
    if not lengths:
        return None, []
    return int(np.bincount(lengths).argmax()), sorted(set(lengths))


def marker_arrays(
    payloads: list[dict | None], n_points: int, topic: str, problems: Problems
) -> tuple[Array, Array, list[MarkerQuality | None]]:
    """Every frame's points and covariances of one view, (F, P, 2) and (F, P, 2, 2), and
    their quality; NaN rows for points not found.

    Parameters
    ----------
    payloads : list of length F
        Each frame's marker message (None: no message).

    Frames whose rows are all present (the common case) are converted in one go; the
    others row by row (:func:`_markers`).
    """
    P, F = n_points, len(payloads)
    uv = np.full((F, P, 2), np.nan)
    cov = np.full((F, P, 2, 2), np.nan)
    quality: list[MarkerQuality | None] = [None] * F
    full, full_uv, full_cov = [], [], []
    for i, payload in enumerate(payloads):
        if payload is None:
            continue
        rows, covs = payload.get("uv"), payload.get("cov")
        if (
            isinstance(rows, list)
            and isinstance(covs, list)
            and len(rows) == P
            and len(covs) == P
            and None not in rows
            and None not in covs
        ):
            full.append(i)
            full_uv.append(rows)
            full_cov.append(covs)
            if "quality" in payload:
                quality[i] = marker_quality(payload, topic, problems)
        else:
            uv[i], cov[i], quality[i] = _markers(payload, P, topic, problems)
    if full:
        try:
            points = np.array(full_uv, dtype=float)
            matrices = np.array(full_cov, dtype=float)
            if points.shape != (len(full), P, 2) or matrices.shape != (len(full), P, 2, 2):
                raise ValueError
        except (TypeError, ValueError):
            for i in full:
                uv[i], cov[i], quality[i] = _markers(payloads[i], P, topic, problems)
        else:
            finite = np.isfinite(points).all(axis=2) & np.isfinite(matrices).all(axis=(2, 3))
            bad_frames = int(np.count_nonzero(~finite.all(axis=1)))
            if bad_frames:
                problems.add("nan", topic, bad_frames)
            good = _in_range(points, matrices, finite, topic, problems)
            points[~good] = np.nan
            matrices[~good] = np.nan
            uv[full], cov[full] = points, matrices
    return uv, cov, quality


def _markers(
    payload: dict, P: int, topic: str, problems: Problems
) -> tuple[Array, Array, MarkerQuality | None]:
    """One marker message row by row (a null row is a point not found)."""
    uv = np.full((P, 2), np.nan)
    cov = np.full((P, 2, 2), np.nan)
    try:
        rows, covs = payload["uv"], payload["cov"]
        if len(rows) != P or len(covs) != P:
            raise ValueError
        present = [k for k in range(P) if rows[k] is not None and covs[k] is not None]
        if present:
            points = np.array([rows[k] for k in present], dtype=float)
            matrices = np.array([covs[k] for k in present], dtype=float)
            if points.shape != (len(present), 2) or matrices.shape != (len(present), 2, 2):
                raise ValueError
            finite = np.isfinite(points).all(axis=1) & np.isfinite(matrices).all(axis=(1, 2))
            if not finite.all():
                problems.add("nan", topic)
            good = _in_range(points[None], matrices[None], finite[None], topic, problems)[0]
            index = np.array(present)[good]
            uv[index], cov[index] = points[good], matrices[good]
        quality = marker_quality(payload, topic, problems)
    except (KeyError, TypeError, ValueError):
        problems.add("malformed", topic)
        return np.full((P, 2), np.nan), np.full((P, 2, 2), np.nan), None
    return uv, cov, quality


def _in_range(
    points: Array, matrices: Array, finite: Array, topic: str, problems: Problems
) -> Array:
    """Which of the finite points (frames, P) are within the physical ranges; the frames with
    one beyond are counted."""
    good = finite & points_in_range(points, matrices)
    beyond = int(np.count_nonzero((finite & ~good).any(axis=1)))
    if beyond:
        problems.add("out_of_range", topic, beyond)
    return good


def marker_quality(payload: dict, topic: str, problems: Problems) -> MarkerQuality | None:
    q = payload.get("quality")
    if not isinstance(q, dict):
        return None
    try:
        sigma = q.get("noise_sigma_gray")
        return MarkerQuality(
            int(q.get("flags", 0)),
            tuple(str(x) for x in q.get("flag_names", [])),
            None if sigma is None else float(sigma),
        )
    except (TypeError, ValueError):
        problems.add("malformed", topic)
        return None


# ------------------------------------------------------------------------- truth, estimates
def all_labels(
    payloads: Sequence[dict | None], problems: Problems
) -> list[tuple[float | None, FrameLabels]]:
    """The true delta_L (None where unknown) and the labels of each frame's ``/truth``
    message (None: no message).

    Frames of one configuration share their labels: equal labels are one (frozen)
    :class:`FrameLabels`, made once.
    """
    made: dict[tuple, FrameLabels] = {}
    none = (None, FrameLabels())
    out: list[tuple[float | None, FrameLabels]] = []
    for payload in payloads:
        if payload is None:
            out.append(none)
            continue
        try:
            delta_L = payload.get("delta_L_rad")
            if delta_L is not None and not math.isfinite(float(delta_L)):
                problems.add("nan_truth", TOPIC_TRUTH)
            key = (
                _index(payload.get("plane")),
                _index(payload.get("configuration")),
                _number(payload.get("deflection_mm")),
                _number(payload.get("noise_level")),
                _angle(payload.get("delta_1_rad"), problems),
            )
            frame_labels = made.get(key)
            if frame_labels is None:
                frame_labels = made[key] = FrameLabels(*key)
            out.append((_angle(delta_L, problems), frame_labels))
        except (TypeError, ValueError, AttributeError, OverflowError):
            # OverflowError: an infinite index (a NaN literal's sibling) is damage, not a crash.
            problems.add("malformed", TOPIC_TRUTH)
            out.append(none)
    return out


def _number(value) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _angle(value, problems: Problems) -> float | None:
    value = _number(value)
    if value is not None and abs(value) > MAX_ANGLE_RAD:
        problems.add("out_of_range", TOPIC_TRUTH)
        return None
    return value


def _index(value) -> int | None:
    return None if value is None else int(value)


def estimates(
    store: Store, name: str, start_ns: int, problems: Problems
) -> list[tuple[float, Estimate]]:
    """``(time_s, estimate)`` of the ``/estimates/<name>`` messages in time order."""
    rows = []
    for stamp, p in zip(store.stamps.tolist(), store.values, strict=True):
        time_s = (stamp - start_ns) / 1e9
        try:
            nis = p.get("nis")
            estimate = Estimate(
                time_s=time_s,
                delta_L_rad=_nan_if_none(p.get("delta_L_rad")),
                std_rad=_nan_if_none(p.get("std_rad")),
                q_r_rad=float(p["q_r_rad"]),
                flags=Flag(int(p.get("flags", 0))),
                informative_radius_mm=float(p.get("informative_radius_mm", 0.0)),
                nis=None if nis is None else float(nis),
                nis_dof=int(p.get("nis_dof", 0)),
            )
        except (KeyError, TypeError, ValueError):
            problems.add("malformed", estimate_topic(name))
            continue
        rows.append((time_s, estimate))
    return rows


def _nan_if_none(value) -> float:
    return float("nan") if value is None else float(value)
