"""Recordings of bi-plane tracking sessions in MCAP, written and read back (docs/recording.md).

A recording is one MCAP file (the ROS 2 bag format) with

- metadata records ``cathtrack`` (format name and version, start time), ``model`` (the model
  TOML text), ``rig`` (the rig TOML text: views and registered base pose) and ``settings``
  (JSON of whatever made the recording);
- the joint values on ``/joints``: blocks of samples at up to 1 kHz, one packed column per
  quantity, as protobuf ``cathtrack.JointSamples`` (format version 2; JSON in version 1,
  which is still read);
- JSON channels with JSON-schema schemas for the segmented markers of each view with their
  covariances and quality (``/markers/front``, ``/markers/side``), the ground truth and the
  labels of the experiment (``/truth``) and the estimates of any method
  (``/estimates/<method>``);
- the camera frames as Foxglove ``foxglove.RawImage`` (protobuf, ``mono8``) on
  ``/camera/<view>/image``, and the empty-scene prior of each camera, which the segmentation
  subtracts, on ``/camera/<view>/background``: rerun and Foxglove show both as images.

Modules, by role: :mod:`~tracker.io.recording.schema` (topics, JSON schemas, message value
types), :mod:`~tracker.io.recording.joint_samples` (the joint blocks in protobuf),
:mod:`~tracker.io.recording.images` (camera frames), :mod:`~tracker.io.recording.protobuf`
(the protobuf wire format of both), :mod:`~tracker.io.recording.writer`
(:class:`RecordingWriter`), :mod:`~tracker.io.recording.scan` (walking the MCAP records
through damage), :mod:`~tracker.io.recording.decode` (messages to arrays) and
:mod:`~tracker.io.recording.reader` (:func:`open_recording`, :class:`Recording`). The rig
text is written and read by :mod:`models.rig_file`.
"""

from tracker.io.recording.images import decode_image, encode_image
from tracker.io.recording.reader import (
    MAX_JOINT_GAP_S,
    ReadReport,
    RecordedEstimate,
    RecordedFrame,
    Recording,
    RecordingMetadata,
    open_recording,
)
from tracker.io.recording.scan import Damage
from tracker.io.recording.schema import (
    FORMAT,
    FORMAT_VERSION,
    READ_VERSIONS,
    SCHEMAS,
    TOPIC_JOINTS,
    TOPIC_TRUTH,
    VIEWS,
    FrameLabels,
    MarkerQuality,
    RecordingError,
    background_topic,
    encode_json,
    estimate_topic,
    image_topic,
    markers_topic,
    schema_for_topic,
)
from tracker.io.recording.writer import (
    CHUNK_BYTES,
    CHUNK_SECONDS,
    JOINT_BLOCK_SAMPLES,
    RecordingWriter,
)

__all__ = [
    "CHUNK_BYTES",
    "CHUNK_SECONDS",
    "Damage",
    "FORMAT",
    "FORMAT_VERSION",
    "FrameLabels",
    "JOINT_BLOCK_SAMPLES",
    "MAX_JOINT_GAP_S",
    "MarkerQuality",
    "READ_VERSIONS",
    "ReadReport",
    "RecordedEstimate",
    "RecordedFrame",
    "Recording",
    "RecordingError",
    "RecordingMetadata",
    "RecordingWriter",
    "SCHEMAS",
    "TOPIC_JOINTS",
    "TOPIC_TRUTH",
    "VIEWS",
    "background_topic",
    "decode_image",
    "encode_image",
    "encode_json",
    "estimate_topic",
    "image_topic",
    "markers_topic",
    "open_recording",
    "schema_for_topic",
]
