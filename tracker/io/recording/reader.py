"""Reading a recording back (docs/recording.md): :func:`open_recording`.

The reader walks the file record by record (:class:`tracker.io.recording.scan.McapScan`)
and validates as it goes. A file that is not MCAP, is not a cathtrack recording, has an
unknown format version or lacks the joint values raises :class:`RecordingError` with one
clear message naming the file. Everything else that can be read is kept: a damaged or
truncated file gives every intact message before the damage and, where the walk finds its
way, after it (the report names each loss by kind, bytes and seconds); out-of-order messages
are sorted, duplicated time stamps keep the first message, NaN values mark the points (or
joint samples) as missing, messages stamped outside the session and values beyond the
physical ranges (:mod:`tracker.io.limits`) are skipped; each of these is counted once in
:class:`ReadReport`. Frames come
back as :class:`tracker.types.Frame` -- the type the live loop consumes -- with their joint
values interpolated to the frame time (:class:`tracker.io.joints.JointHistory`, as live),
together with the experiment's labels.
"""

from __future__ import annotations

import dataclasses
import gc
import json
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np
from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata

from models.catheter import Catheter
from models.imaging import Rig
from models.model_file import ModelFileError, catheter_from_dict
from models.pose import Pose
from models.rig_file import RigFileError, rig_from_toml, view_names
from tracker.io.joints import JointHistory
from tracker.io.limits import MAX_START_TIME_NS, SESSION_TIME_RANGE_S
from tracker.io.recording import decode
from tracker.io.recording.images import decode_image
from tracker.io.recording.scan import ChunkRecords, Damage, McapScan
from tracker.io.recording.schema import (
    FORMAT,
    READ_VERSIONS,
    TOPIC_JOINTS,
    TOPIC_TRUTH,
    VIEWS,
    FrameLabels,
    MarkerQuality,
    RecordingError,
    background_topic,
    image_topic,
    markers_topic,
)
from tracker.types import Estimate, Frame

Array = np.ndarray

MAX_JOINT_GAP_S = 0.1
"""Frames farther than this from the nearest joint samples get no joint values (skipped)."""
_EMPTY = decode.Store(np.zeros(0, np.int64), [])


@dataclass(frozen=True)
class RecordedFrame:
    """A frame read from a recording, its labels, and each view's segmentation quality."""

    frame: Frame
    labels: FrameLabels
    quality: tuple[MarkerQuality | None, MarkerQuality | None] = (None, None)


@dataclass(frozen=True)
class RecordedEstimate:
    """An estimate read from ``/estimates/<method>``."""

    time_s: float
    estimate: Estimate


@dataclass(frozen=True)
class RecordingMetadata:
    format_version: int
    start_time_ns: int
    writer: str
    model_toml: str
    rig_toml: str
    settings: dict


@dataclass
class ReadReport:
    """What the reader found: message counts, the damaged parts of the file, and every
    problem, counted once per kind."""

    path: str
    messages: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    damage: list[Damage] = field(default_factory=list)
    frames: int = 0
    joint_samples: int = 0
    last_time_s: float | None = None

    @property
    def ok(self) -> bool:
        return not self.warnings

    @property
    def truncated(self) -> bool:
        return any(d.kind == "truncated" for d in self.damage)

    @property
    def lost_seconds(self) -> float:
        """Log time spanned by the lost chunks, s (where their headers say)."""
        spans = [d.end_ns - d.start_ns for d in self.damage if d.lost and d.start_ns is not None]
        return max(sum(spans), 0) / 1e9

    @property
    def lost_bytes(self) -> int:
        return sum(d.end - d.offset for d in self.damage if d.lost)

    def summary(self) -> str:
        """A few lines for the console and the report."""
        lines = [
            f"{self.path}: {self.frames} frames, {self.joint_samples} joint samples, "
            + ", ".join(f"{topic} {n}" for topic, n in sorted(self.messages.items()))
        ]
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


@dataclass
class _ImageRef:
    """Where an image message is: in a chunk (read again when the image is decoded), or,
    outside chunks, its data."""

    chunk_offset: int
    index: int
    data: bytes | None = None


class Recording:
    """A recording read from an MCAP file (see :func:`open_recording`)."""

    def __init__(self, path: str | Path, max_joint_gap_s: float = MAX_JOINT_GAP_S) -> None:
        self.path = Path(path)
        self.max_joint_gap_s = float(max_joint_gap_s)
        self.report = ReadReport(str(self.path))
        self._problems = decode.Problems()
        self._problem_warnings: list[str] = []  # the problems' lines now in the report
        self._metadata_raw: dict[str, dict[str, str]] = {}
        self._max_time: int | None = None
        self._session_ns: tuple[int, int] | None = None  # known once 'cathtrack' is read
        self._raw: dict[str, tuple[list[int], list]] = {}  # topic: log times, data (scan)
        self._sinks: dict[int, tuple] = {}  # channel id: topic and where its messages go
        self._joint_blocks: list = []  # parsed JSON (version 1) or protobuf bytes (2)
        self._per_frame: dict[str, decode.Store] = {}  # markers, truth, images by log time
        self._estimates_raw: dict[str, decode.Store] = {}
        self._chunk_cache: tuple[int, list] | None = None
        self._file: BinaryIO | None = None
        # The scan allocates many small objects and frees none: the cyclic garbage collector
        # would only rescan them (a third of the reading time), so it waits until the end.
        collecting = gc.isenabled()
        gc.disable()
        try:
            damage = self._scan()
            self.metadata = self._check_metadata()
            self._session_ns = self._session(self.metadata.start_time_ns)
            self._drop_out_of_session()
            damage = [(self._in_session_damage(d), *times) for d, *times in damage]
            self.report.damage = [d for d, *_ in damage]
            self.report.warnings += [self._damage_warning(*entry) for entry in damage]
            self._assemble()
        except BaseException:
            self.close()
            raise
        finally:
            if collecting:
                gc.enable()

    # ---------------------------------------------------------------- scanning
    def _scan(self) -> list[tuple[Damage, int | None, int | None]]:
        """Gather the messages; the damage found, each with the latest log time before it and
        the first after it (None: no message there)."""
        try:
            self._file = open(self.path, "rb")  # noqa: SIM115 - kept open for lazy images
        except OSError as exc:
            raise RecordingError(f"cannot read recording {self.path}: {exc.strerror}") from None
        try:
            self._mcap = McapScan(self._file)
        except McapError:
            raise RecordingError(
                f"{self.path} is not an MCAP file (it does not start with the MCAP magic bytes)"
            ) from None
        damage: list[list] = []
        self._awaiting = 0  # how many of the last damages wait for the first message after them
        for item in self._mcap.records():
            if item.__class__ is ChunkRecords:
                self._records(item.records, item.offset, damage)
                continue
            if isinstance(item, Damage):
                self.report.damage.append(item)
                damage.append([item, self._max_time, None])
                self._awaiting += 1
                continue
            record = item.record
            if isinstance(record, Metadata):
                self._metadata_raw[record.name] = dict(record.metadata)
                if record.name == "cathtrack":
                    start_ns = self._start_ns()
                    self._session_ns = None if start_ns is None else self._session(start_ns)
            else:
                self._records([record], -1, damage)
        self._gather()
        return [tuple(entry) for entry in damage]

    def _records(self, records: list, chunk_offset: int, damage: list[list]) -> None:
        """Keep the log time and data of each message in the session on a declared channel
        (per topic, in file order; the JSON is parsed later, a topic at a time), and the
        channels declared. An image message keeps where it is instead of its data (unless it
        is outside chunks): the image is read again when the frame is."""
        sinks, problems = self._sinks, self._problems
        low, high = self._session_ns or (-(2**63), 2**63 - 1)
        newest = -1 if self._max_time is None else self._max_time
        awaiting = self._awaiting
        for index, record in enumerate(records):
            if record.__class__ is not Message:
                if isinstance(record, Channel):
                    self._channel(record)
                continue
            log_time = record.log_time
            inside = low <= log_time <= high
            if awaiting and inside:
                for entry in damage[-awaiting:]:
                    entry[2] = log_time
                awaiting = 0
            sink = sinks.get(record.channel_id)
            if sink is None:
                problems.add("unknown_channel", f"channel {record.channel_id}")
                continue
            topic, add_time, add_data, lazy = sink
            if not inside:
                problems.add("out_of_session", topic)
                continue
            if log_time > newest:
                newest = log_time
            add_time(log_time)
            if lazy:
                inline = chunk_offset < 0
                add_data(_ImageRef(chunk_offset, index, record.data if inline else None))
            else:
                add_data(record.data)
        self._awaiting = awaiting
        if newest >= 0:  # log times are unsigned
            self._max_time = newest

    def _channel(self, channel: Channel) -> None:
        """A channel declared: where its messages go (the lists of its topic)."""
        topic = channel.topic
        self.report.messages.setdefault(topic, 0)
        times, data = self._raw.setdefault(topic, ([], []))
        lazy = topic.startswith("/camera/")
        self._sinks[channel.id] = (topic, times.append, data.append, lazy)

    def _gather(self) -> None:
        """The messages kept by the scan, topic by topic: counted, checked for time order,
        their JSON parsed; each time stamp's first message stored (:class:`decode.Store`)."""
        problems, messages = self._problems, self.report.messages
        for topic, (times, data) in self._raw.items():
            if not times:
                continue
            messages[topic] = messages.get(topic, 0) + len(times)
            stamps = np.array(times, dtype=np.int64)
            if stamps.size > 1:
                # Out of order: earlier than the latest before it (the order check at each
                # message, for all messages at once).
                late = int(np.count_nonzero(stamps[1:] < np.maximum.accumulate(stamps)[:-1]))
                if late:
                    problems.add("out_of_order", topic, late)
            if topic.startswith("/camera/"):
                self._per_frame[topic] = decode.Store.first_of(stamps, data, topic, problems)
                continue
            if topic == TOPIC_JOINTS and self._joints_in_protobuf():
                self._joint_blocks += data  # decoded with the other checks (_assemble)
                continue
            payloads = decode.json_messages(data, topic, problems)
            parsed = [i for i, payload in enumerate(payloads) if payload is not None]
            payloads = [payloads[i] for i in parsed]
            if topic == TOPIC_JOINTS:
                self._joint_blocks += payloads
                continue
            if not (
                topic.startswith("/estimates/")
                or topic == TOPIC_TRUTH
                or topic.startswith("/markers/")
            ):
                continue  # another channel: read (its malformed messages counted), not kept
            store = decode.Store.first_of(stamps[parsed], payloads, topic, problems)
            if topic.startswith("/estimates/"):
                self._estimates_raw[topic[len("/estimates/") :]] = store
            else:
                self._per_frame[topic] = store
        self._raw = {}

    def _joints_in_protobuf(self) -> bool:
        """Whether ``/joints`` is protobuf (format version 2) rather than JSON (version 1);
        a file of another version is refused later (:meth:`_check_metadata`)."""
        version = self._metadata_raw.get("cathtrack", {}).get("format_version")
        return version is not None and version != "1"

    @staticmethod
    def _session(start_ns: int) -> tuple[int, int]:
        """The log times, ns, of the session that starts at ``start_ns``."""
        low, high = SESSION_TIME_RANGE_S
        return start_ns + int(low * 1e9), start_ns + int(high * 1e9)

    def _in_session(self, log_time: int) -> bool:
        """Whether a log time is within the session (within 64-bit integers before the
        'cathtrack' metadata record gives the start)."""
        low, high = self._session_ns or (-(2**63), 2**63 - 1)
        return low <= log_time <= high

    def _drop_out_of_session(self) -> None:
        """Skip (and count) what was stored before the session was known and lies outside."""
        low, high = self._session_ns
        for stores in (self._per_frame, self._estimates_raw):
            for topic, store in stores.items():
                inside = (store.stamps >= low) & (store.stamps <= high)
                if not inside.all():
                    stores[topic] = store.where(inside)
                    name = topic if topic.startswith("/") else f"/estimates/{topic}"
                    self._problems.add("out_of_session", name, int(np.count_nonzero(~inside)))
        if self._max_time is not None and not self._in_session(self._max_time):
            stamps = [int(store.stamps.max()) for store in self._per_frame.values() if store]
            self._max_time = max(stamps, default=None)

    def _in_session_damage(self, damage: Damage) -> Damage:
        """The damage with its span of log times forgotten where the (damaged) chunk header
        gives times outside the session."""
        if damage.start_ns is None or damage.end_ns is None:
            return damage
        if self._in_session(damage.start_ns) and self._in_session(damage.end_ns):
            return damage
        return dataclasses.replace(damage, start_ns=None, end_ns=None)

    def _seconds(self, time_ns: int) -> float:
        return (time_ns - self.metadata.start_time_ns) / 1e9

    def _damage_warning(self, damage: Damage, before_ns: int | None, after_ns: int | None) -> str:
        """One line naming the loss: kind, bytes, and the session time it spanned (from the
        damaged chunk's header, else between the last message read before the damage and the
        first read after it)."""
        d = damage
        where = f"bytes {d.offset} to {d.end}"
        if d.start_ns is not None and d.end_ns is not None:
            span = (
                f"data from t = {self._seconds(d.start_ns):.3f} to {self._seconds(d.end_ns):.3f} s"
            )
        elif before_ns is not None and after_ns is not None:
            span = (
                f"data between t = {self._seconds(before_ns):.3f} and"
                f" {self._seconds(after_ns):.3f} s"
            )
        elif before_ns is not None:
            span = f"data after t = {self._seconds(before_ns):.3f} s"
        elif after_ns is not None:
            span = f"what came before the first message read (t = {self._seconds(after_ns):.3f} s)"
        else:
            span = "the data there"
        if d.kind == "truncated":
            read_up_to = "" if before_ns is None else f" up to t = {self._seconds(before_ns):.3f} s"
            lost = (
                "" if d.start_ns is None else f"; the incomplete chunk held {span}, which is lost"
            )
            n = d.end - d.offset
            incomplete = f"the last {n} bytes are lost" if n else "no record is incomplete"
            return (
                f"the file is truncated ({d.detail}; no MCAP footer): {incomplete}, read"
                f" everything{read_up_to}{lost}"
            )
        if d.kind in ("bad_crc", "bad_compression"):
            return f"a corrupt chunk ({d.detail}) was skipped ({where}): {span} lost"
        if d.kind == "bad_length" and not d.lost:
            return (
                f"a chunk at byte {d.offset} has a damaged record length ({d.detail}): read by"
                " its content, nothing lost"
            )
        if d.kind == "bad_length":
            return (
                f"a record at byte {d.offset} has a damaged length ({d.detail}): skipped"
                f" ({where}), {span} lost"
            )
        return f"{where} hold no readable record ({d.detail}): skipped, {span} lost"

    def _start_ns(self) -> int | None:
        """The start time of the 'cathtrack' metadata record (None: not a valid one)."""
        text = self._metadata_raw.get("cathtrack", {}).get("start_time_ns", "0")
        try:
            start_ns = int(text)
        except ValueError:
            return None
        return start_ns if 0 <= start_ns <= MAX_START_TIME_NS else None

    # ---------------------------------------------------------------- checks
    def _check_metadata(self) -> RecordingMetadata:
        info = self._metadata_raw.get("cathtrack")
        damaged = ""
        if self.report.damage:
            first = self.report.damage[0]
            damaged = (
                f"; the file is damaged in {len(self.report.damage)} place(s), first at bytes"
                f" {first.offset} to {first.end} ({first.detail})"
            )
        if info is None or info.get("format") != FORMAT:
            raise RecordingError(
                f"{self.path} is an MCAP file but not a cathtrack recording (no 'cathtrack'"
                f' metadata record naming the format "{FORMAT}"{damaged})'
            )
        version = info.get("format_version", "")
        if version not in [str(v) for v in READ_VERSIONS]:
            known = " and ".join(str(v) for v in READ_VERSIONS)
            raise RecordingError(
                f"{self.path}: unknown recording format version {version!r}; this cathtrack"
                f" reads versions {known}"
            )
        for name in ("model", "rig"):
            if "toml" not in self._metadata_raw.get(name, {}):
                raise RecordingError(f"{self.path}: missing the '{name}' metadata record{damaged}")
        start_ns = self._start_ns()
        if start_ns is None:
            text = info.get("start_time_ns", "")
            raise RecordingError(
                f"{self.path}: the 'cathtrack' metadata record's start_time_ns must be an"
                f" integer from 0 to {MAX_START_TIME_NS} ns, got {text[:40]!r}"
            )
        try:
            settings = json.loads(self._metadata_raw.get("settings", {}).get("json", "{}"))
        except (ValueError, RecursionError):
            settings = {}
            self.report.warnings.append("the settings metadata is not valid JSON: ignored")
        return RecordingMetadata(
            format_version=int(version),
            start_time_ns=start_ns,
            writer=info.get("writer", ""),
            model_toml=self._metadata_raw["model"]["toml"],
            rig_toml=self._metadata_raw["rig"]["toml"],
            settings=settings if isinstance(settings, dict) else {},
        )

    # ---------------------------------------------------------------- assembly
    def _assemble(self) -> None:
        start_ns = self.metadata.start_time_ns
        source = str(self.path)
        self.views = self._view_names()
        frame_topics = [f(view) for view in self.views for f in (markers_topic, image_topic)]
        has_frames = any(self._per_frame.get(topic) for topic in frame_topics)
        if self.report.messages.get(TOPIC_JOINTS):
            if self.metadata.format_version == 1:
                columns = decode.json_joint_columns(self._joint_blocks, self._problems, source)
            else:
                columns = decode.protobuf_joint_columns(self._joint_blocks, self._problems, source)
            t_ns, q, q_dot = decode.joint_stream(columns, self._problems, source, self._session_ns)
            self.joints = JointHistory((t_ns - start_ns) / 1e9, q, q_dot)
        elif has_frames:
            raise RecordingError(
                f"{self.path}: missing channel {TOPIC_JOINTS}: a recording needs the joint values"
            )
        else:  # stopped before the first joint sample: an empty recording, still readable
            self.joints = JointHistory(np.zeros(0), np.zeros((0, 3)))
        if not has_frames:
            self.report.warnings.append(
                "the recording holds no frames (no marker or image message of any view)"
            )
        for view in self.views:
            has_images = bool(self._per_frame.get(image_topic(view)))
            if has_frames and not self.report.messages.get(markers_topic(view)):
                self.report.warnings.append(
                    f"missing channel {markers_topic(view)}: frames have no {view} markers"
                    + (" (the images can be segmented)" if has_images else "")
                )
        if has_frames and not self.report.messages.get(TOPIC_TRUTH):
            self.report.warnings.append(f"missing channel {TOPIC_TRUTH}: no ground truth")
        frame_stores = [self._per_frame.get(topic) for topic in frame_topics]
        stamps = np.unique(
            np.concatenate([np.zeros(0, np.int64)] + [s.stamps for s in frame_stores if s])
        )
        times = (stamps - start_ns) / 1e9
        q, q_dot, gap_s = self.joints.interpolate(times)
        ok = gap_s <= self.max_joint_gap_s
        if np.any(~ok):
            self.report.warnings.append(
                f"{int(np.count_nonzero(~ok))} frame(s) have no joint values within"
                f" {self.max_joint_gap_s:g} s: skipped"
            )
        self._stamps, self._times = stamps[ok], times[ok]
        self._q, self._q_dot = q[ok], q_dot[ok]
        self.backgrounds = tuple(self._background(view) for view in self.views)
        self.estimates = {
            name: [
                RecordedEstimate(t, e)
                for t, e in decode.estimates(s, name, start_ns, self._problems)
            ]
            for name, s in self._estimates_raw.items()
        }
        n_points = self._point_count()
        self._uv, self._cov, self._quality = {}, {}, {}
        for view in self.views:
            topic = markers_topic(view)
            store = self._per_frame.get(topic, _EMPTY)
            self._uv[view], self._cov[view], self._quality[view] = decode.marker_arrays(
                store.at(self._stamps), n_points, topic, self._problems
            )
        truth = self._per_frame.get(TOPIC_TRUTH, _EMPTY).at(self._stamps)
        self._truth = decode.all_labels(truth, self._problems)
        # The parsed JSON is now in arrays: drop it (millions of small objects that every
        # later garbage collection would walk). Image references stay, for lazy decoding.
        self._joint_blocks = []
        for topic in (TOPIC_TRUTH, *(markers_topic(view) for view in self.views)):
            self._per_frame.pop(topic, None)
        self._estimates_raw = {}
        self._report_problems()
        self.report.frames = len(self._stamps)
        self.report.joint_samples = int(self.joints.time_s.size)
        if self._max_time is not None:
            self.report.last_time_s = (self._max_time - start_ns) / 1e9

    def _report_problems(self) -> None:
        """Put the problems' warnings (one per kind, with counts) in the report, replacing
        the earlier ones: images that cannot be decoded are found when frames are read."""
        old = set(self._problem_warnings)
        self._problem_warnings = self._problems.warnings()
        self.report.warnings[:] = [w for w in self.report.warnings if w not in old]
        self.report.warnings += self._problem_warnings

    def _view_names(self) -> tuple[str, ...]:
        """The recorded rig's view names (the bi-plane names for a rig that names none)."""
        try:
            return view_names(tomllib.loads(self.metadata.rig_toml), "recorded rig")
        except (tomllib.TOMLDecodeError, RecursionError, RigFileError, AttributeError, TypeError):
            return VIEWS

    def _point_count(self) -> int:
        """Rows per view: the most common in the marker messages, else the catheter's."""
        stores = [self._per_frame.get(markers_topic(view), _EMPTY) for view in self.views]
        n_points, seen = decode.point_count(stores)
        if len(seen) > 1:
            self.report.warnings.append(
                f"marker messages have different numbers of rows {seen}: using the most common"
            )
        if n_points is not None:
            return n_points
        try:
            return 1 + len(self.catheter().marker_arclengths_mm)
        except RecordingError:
            return 1

    # ---------------------------------------------------------------- images
    def _image_data(self, ref: _ImageRef) -> bytes:
        if ref.data is not None:
            return ref.data
        if self._chunk_cache is None or self._chunk_cache[0] != ref.chunk_offset:
            self._chunk_cache = (ref.chunk_offset, self._mcap.chunk_records(ref.chunk_offset))
        return self._chunk_cache[1][ref.index].data

    def _image(self, topic: str, stamp: int) -> Array | None:
        ref = self._per_frame.get(topic, _EMPTY).get(stamp)
        if ref is None:
            return None
        try:
            return decode_image(self._image_data(ref))
        except (ValueError, OSError, McapError):
            self._problems.add("bad_image", topic)
            self._report_problems()
            return None

    def _background(self, view: str) -> Array | None:
        refs = self._per_frame.get(background_topic(view))
        if not refs:
            return None
        return self._image(background_topic(view), int(refs.stamps[0]))

    @property
    def has_images(self) -> bool:
        return all(bool(self._per_frame.get(image_topic(v))) for v in self.views)

    # ---------------------------------------------------------------- public
    def __len__(self) -> int:
        return len(self._stamps)

    def frames(self, images: bool | Callable[[int], bool] = True) -> Iterator[RecordedFrame]:
        """The frames in time order.

        Parameters
        ----------
        images : bool or callable
            Decode the images (one frame at a time); a callable of the frame index decodes
            them only for the frames it accepts.
        """
        has_images = self.has_images
        # Each call hands out fresh arrays: one copy of each array per call, and every frame
        # a row of it (a copy per frame and array cost more than the rest of the frame).
        q, q_dot = list(self._q.copy()), list(self._q_dot.copy())
        uv = list(zip(*(list(self._uv[v].copy()) for v in self.views), strict=True))
        cov = list(zip(*(list(self._cov[v].copy()) for v in self.views), strict=True))
        quality = list(zip(*(self._quality[v] for v in self.views), strict=True))
        times = self._times.tolist()
        for i, stamp in enumerate(self._stamps.tolist()):
            delta_L, labels = self._truth[i]
            decoded = None
            if has_images and (images(i) if callable(images) else images):
                decoded = tuple(self._image(image_topic(v), stamp) for v in self.views)
                decoded = None if any(image is None for image in decoded) else decoded
            frame = Frame(times[i], q[i], q_dot[i], uv[i], cov[i], decoded, delta_L)
            yield RecordedFrame(frame, labels, quality[i])

    def frame_times_s(self) -> Array:
        return self._times.copy()

    def catheter(self) -> Catheter:
        """The catheter model of the ``model`` metadata record."""
        source = f"{self.path} model"
        try:
            data = tomllib.loads(self.metadata.model_toml)
        except (tomllib.TOMLDecodeError, RecursionError) as exc:
            raise RecordingError(f"{source}: malformed TOML: {exc}") from None
        try:
            return catheter_from_dict(data, source)
        except ModelFileError as exc:
            raise RecordingError(str(exc)) from None

    def rig(self) -> tuple[Rig, Pose]:
        """The rig and the registered base pose of the ``rig`` metadata record."""
        source = f"{self.path} rig"
        try:
            rig, base = rig_from_toml(self.metadata.rig_toml, source)
        except RigFileError as exc:
            raise RecordingError(str(exc)) from None
        if base is None:
            raise RecordingError(f"{source}: missing table [base] (registered base pose)")
        return rig, base

    def close(self) -> None:
        if self._file is not None:
            self._file.close()

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_recording(path: str | Path, max_joint_gap_s: float = MAX_JOINT_GAP_S) -> Recording:
    """Read and validate a recording (images are decoded later, frame by frame).

    Raises
    ------
    RecordingError
        Not an MCAP file, not a cathtrack recording, an unknown format version or start
        time, or frames without joint values. Problems that leave something readable are
        warnings in ``recording.report`` instead (a recording stopped before its first
        frame is an empty one).
    """
    return Recording(path, max_joint_gap_s)
