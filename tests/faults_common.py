"""What the fault tests (``tests/test_faults_*.py``) share: the model and rig files they
start from, the check that an error is one line naming the file and the problem, and the
session the recording tests write (70 frames at 20 fps, joints at 1 kHz) with its reader and
the check that every frame outside the damage reads back unchanged.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from models.catheter import default_catheter
from models.model_file import DEFAULT_MODEL_PATH
from models.pose import Pose
from models.rig_file import rig_toml
from replay.simulation.render import default_render_rig
from tracker.io.recording import open_recording
from tracker.types import Frame

MODEL_TOML = DEFAULT_MODEL_PATH.read_text()
RIG = default_render_rig()
BASE = Pose(np.eye(3), np.array([0.0, 0.0, -15.0]))
RIG_TOML = rig_toml(RIG, BASE)
P = 1 + len(default_catheter().marker_arclengths_mm)  # rows per view: tip, markers
N_FRAMES = 70  # 3.5 s at 20 fps, as in the issue
FRAME_DT_S = 0.05
JOINT_BLOCK = 50  # samples per /joints message at 1 kHz


def assert_one_line(error: BaseException, path, *words: str) -> None:
    """One line that names the file and the problem."""
    text = str(error)
    assert "\n" not in text, text
    assert str(path) in text, text
    for word in words:
        assert word in text, f"{word!r} not in {text!r}"


# ------------------------------------------------------------------------------ recordings
def _joints(t):
    t = np.asarray(t, dtype=float)
    q = np.column_stack([0.3 + 0.2 * np.sin(t), 0.6 + 0.1 * t, -0.4 + 0.05 * np.cos(3 * t)])
    q_dot = np.column_stack([0.2 * np.cos(t), np.full_like(t, 0.1), -0.15 * np.sin(3 * t)])
    return q, q_dot


def _session_frames() -> list[Frame]:
    rng = np.random.default_rng(14)
    frames = []
    for k in range(N_FRAMES):
        t = FRAME_DT_S * k
        q, q_dot = _joints([t])
        uv = tuple(rng.uniform(0.0, 640.0, (P, 2)) for _ in range(2))
        cov = tuple(np.tile(np.diag(rng.uniform(0.1, 2.0, 2)), (P, 1, 1)) for _ in range(2))
        frames.append(Frame(t, q[0], q_dot[0], uv, cov, None, float(rng.uniform(-3.0, 3.0))))
    return frames


FRAMES = _session_frames()
T_JOINTS = np.arange(int(N_FRAMES * FRAME_DT_S * 1000) + JOINT_BLOCK) / 1000.0


def _read(path: Path, images: bool = False):
    """(frames by time, warnings, damage) of a recording."""
    with open_recording(path) as recording:
        frames = {round(r.frame.time_s, 6): r.frame for r in recording.frames(images=images)}
        return frames, recording.report.warnings, recording.report.damage


def assert_frames_intact(frames: dict, lost: Callable[[float], bool] = lambda t: False) -> None:
    """Every written frame not in the lost span is read back unchanged (joints interpolated
    from the 1 kHz samples: the written values)."""
    for written in FRAMES:
        t = round(written.time_s, 6)
        if lost(written.time_s):
            continue
        assert t in frames, f"the frame at t = {t} s was lost"
        got = frames[t]
        for view in range(2):
            np.testing.assert_array_equal(got.uv[view], written.uv[view])
            np.testing.assert_array_equal(got.cov[view], written.cov[view])
        np.testing.assert_allclose(got.q, written.q, atol=1e-12)
        assert got.delta_L_true_rad == written.delta_L_true_rad
