"""What a recording holds: format, topics, JSON schemas and the value types of its messages.

The format is documented in docs/recording.md; :mod:`tracker.io.recording.writer` writes it,
:mod:`tracker.io.recording.reader` reads it back. The joint stream's protobuf schema (format
version 2) is in :mod:`tracker.io.recording.joint_samples`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import orjson

from models.imaging import DEFAULT_VIEW_NAMES

Array = np.ndarray

FORMAT = "cathtrack-recording"
FORMAT_VERSION = 2
"""Version of the recording format that this package writes (by default)."""
READ_VERSIONS = (1, 2)
"""Versions of the recording format that this package reads (and can write).

Version 2 changed only the ``/joints`` channel: protobuf ``cathtrack.JointSamples`` instead
of JSON (:mod:`tracker.io.recording.joint_samples`); everything else is as in version 1.
"""

VIEWS = DEFAULT_VIEW_NAMES
"""Views of a recording whose rig names none (the bi-plane rig); otherwise the rig's names."""
TOPIC_JOINTS = "/joints"
TOPIC_TRUTH = "/truth"


def markers_topic(view: str) -> str:
    return f"/markers/{view}"


def image_topic(view: str) -> str:
    return f"/camera/{view}/image"


def background_topic(view: str) -> str:
    return f"/camera/{view}/background"


def estimate_topic(name: str) -> str:
    return f"/estimates/{name}"


class RecordingError(ValueError):
    """A file that cannot be read as a cathtrack recording (one message says why)."""


# ------------------------------------------------------------------------------- schemas
_NUMBER_OR_NULL = {"type": ["number", "null"]}
_XY = {"type": ["array", "null"], "items": {"type": "number"}, "minItems": 2, "maxItems": 2}
_MATRIX_2X2 = {
    "type": ["array", "null"],
    "items": {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2},
    "minItems": 2,
    "maxItems": 2,
}
_COLUMN = {"type": "array", "items": {"type": ["number", "null"]}}
JOINT_COLUMNS = ("q_r_rad", "q_p_mm", "q_d_mm")
"""Columns of the joint values in /joints (q_r, q_p, q_d)."""
RATE_COLUMNS = ("q_r_dot_rad_s", "q_p_dot_mm_s", "q_d_dot_mm_s")
"""Columns of the joint rates in /joints (optional)."""

JOINT_SAMPLES = "cathtrack.JointSamples"
JSON_JOINT_SAMPLES = {
    "title": JOINT_SAMPLES,
    "description": (
        "A block of joint samples in time order, one column per quantity (all columns of "
        "the same length): sample times on the clock of the MCAP log_time, the joint "
        "values, and their rates when the source measures them (all three rate columns, "
        "or none). null: a value that was not available."
    ),
    "type": "object",
    "properties": {
        "time_ns": {"type": "array", "items": {"type": "integer"}},
        **{name: _COLUMN for name in JOINT_COLUMNS + RATE_COLUMNS},
    },
    "required": ["time_ns", *JOINT_COLUMNS],
}
"""The JSON schema of ``/joints`` in format version 1 (version 2: protobuf)."""

SCHEMAS: dict[str, dict] = {
    "cathtrack.Markers": {
        "title": "cathtrack.Markers",
        "description": (
            "Points segmented in one view at the frame time (= the message log_time). Rows "
            "[tip, marker_0, marker_1, ...] in the order of the model's marker_arclengths_mm; "
            "null rows for points not found. unit: px (pinhole rig) or mm (orthographic planes)."
        ),
        "type": "object",
        "properties": {
            "view": {"type": "string", "pattern": "^[A-Za-z_][A-Za-z0-9_]*$"},
            "unit": {"type": "string", "enum": ["px", "mm"]},
            "uv": {"type": "array", "items": _XY},
            "cov": {"type": "array", "items": _MATRIX_2X2},
            "quality": {
                "type": "object",
                "properties": {
                    "flags": {"type": "integer"},
                    "flag_names": {"type": "array", "items": {"type": "string"}},
                    "noise_sigma_gray": _NUMBER_OR_NULL,
                },
            },
        },
        "required": ["view", "unit", "uv", "cov"],
    },
    "cathtrack.Truth": {
        "title": "cathtrack.Truth",
        "description": (
            "Ground truth and experiment labels of the frame at this log_time. delta_L_rad is "
            "the true torsional loss and delta_1_rad = q_r + delta_L the true bending plane "
            "(wrapped to [-pi, pi)); null where unknown. plane and configuration index the "
            "experimental protocol; deflection_mm is the tip deflection by contact; "
            "noise_level the nominal segmentation noise (unit in the settings metadata)."
        ),
        "type": "object",
        "properties": {
            "delta_L_rad": _NUMBER_OR_NULL,
            "delta_1_rad": _NUMBER_OR_NULL,
            "plane": {"type": ["integer", "null"]},
            "configuration": {"type": ["integer", "null"]},
            "deflection_mm": _NUMBER_OR_NULL,
            "noise_level": _NUMBER_OR_NULL,
        },
        "required": ["delta_L_rad"],
    },
    "cathtrack.Estimate": {
        "title": "cathtrack.Estimate",
        "description": (
            "One estimator step at this log_time: delta_L and its standard deviation (rad), "
            "the bending plane delta_1 = q_r + delta_L, flags (bit set of tracker.Flag, with "
            "their names), and the normalised innovation squared where the method has one."
        ),
        "type": "object",
        "properties": {
            "delta_L_rad": _NUMBER_OR_NULL,
            "std_rad": _NUMBER_OR_NULL,
            "delta_1_rad": _NUMBER_OR_NULL,
            "q_r_rad": {"type": "number"},
            "flags": {"type": "integer"},
            "flag_names": {"type": "array", "items": {"type": "string"}},
            "nis": _NUMBER_OR_NULL,
            "nis_dof": {"type": "integer"},
            "informative_radius_mm": {"type": "number"},
        },
        "required": ["delta_L_rad", "std_rad", "q_r_rad", "flags"],
    },
}
"""The JSON schemas of the JSON channels, by name (the same in format versions 1 and 2)."""
SCHEMAS_V1 = {JOINT_SAMPLES: JSON_JOINT_SAMPLES, **SCHEMAS}
"""The JSON schemas of format version 1, whose ``/joints`` is JSON too."""
_TOPIC_SCHEMA = {
    TOPIC_JOINTS: JOINT_SAMPLES,
    TOPIC_TRUTH: "cathtrack.Truth",
}


def schema_for_topic(topic: str) -> str | None:
    """Name of the schema of a cathtrack topic whose messages are not images: that of a JSON
    schema in :data:`SCHEMAS` or, for ``/joints``, ``cathtrack.JointSamples`` (protobuf; JSON
    in format version 1). None for image topics and unknown ones."""
    if topic.startswith("/estimates/"):
        return "cathtrack.Estimate"
    if topic.startswith("/markers/"):
        return "cathtrack.Markers"
    return _TOPIC_SCHEMA.get(topic)


def finite_or_none(x) -> float | None:
    """A float for JSON: None for None, NaN and infinities (strict JSON has no NaN)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def json_rows(a: Array) -> list:
    """Rows of a float array as nested lists with None for rows that contain a non-finite value."""
    a = np.asarray(a, dtype=float)
    ok = np.all(np.isfinite(a.reshape(a.shape[0], -1)), axis=1)
    return [row if good else None for row, good in zip(a.tolist(), ok.tolist(), strict=True)]


def encode_json(obj: Any) -> bytes:
    """JSON bytes of a message (strict JSON: callers write NaN as null)."""
    return orjson.dumps(obj)


def decode_json(data: bytes) -> Any:
    """Parse JSON (orjson: five times faster than json on the joint blocks); the non-standard
    NaN/Infinity literals of other writers are accepted too.

    Raises
    ------
    ValueError
        Not JSON, or nested too deeply (orjson's limit of 1024 levels; json's recursion
        error is turned into this).
    """
    try:
        return orjson.loads(data)
    except orjson.JSONDecodeError:
        try:
            return json.loads(data)
        except RecursionError:
            raise ValueError("JSON nested too deeply") from None


# ------------------------------------------------------------------------------ labels
@dataclass(frozen=True)
class FrameLabels:
    """What the experiment says about a frame, beyond the Frame itself (from ``/truth``).

    Parameters
    ----------
    plane : int, optional
        Index of the bending plane of the protocol.
    configuration : int, optional
        Index of the joint configuration (over the whole protocol).
    deflection_mm : float, optional
        Tip deflection by contact, mm (0: free).
    noise_level : float, optional
        Nominal segmentation noise of the configuration (unit in the settings metadata).
    delta_1_true_rad : float, optional
        True bending plane q_r + delta_L, wrapped to [-pi, pi).
    """

    plane: int | None = None
    configuration: int | None = None
    deflection_mm: float | None = None
    noise_level: float | None = None
    delta_1_true_rad: float | None = None


@dataclass(frozen=True)
class MarkerQuality:
    """Quality of one view's segmentation: flags (bit set, with names) and its noise estimate."""

    flags: int = 0
    flag_names: tuple[str, ...] = ()
    noise_sigma_gray: float | None = None

    def to_json(self) -> dict:
        sigma = None if self.noise_sigma_gray is None else finite_or_none(self.noise_sigma_gray)
        return {
            "flags": int(self.flags),
            "flag_names": list(self.flag_names),
            "noise_sigma_gray": sigma,
        }

    @classmethod
    def from_segmentation(cls, view_segmentation) -> MarkerQuality:
        """From a :class:`tracker.vision.segmentation.ViewSegmentation`."""
        flags = view_segmentation.flags
        names = tuple(f.name for f in type(flags) if f and f in flags and f.name)
        return cls(int(flags), names, float(view_segmentation.noise_sigma_gray))
