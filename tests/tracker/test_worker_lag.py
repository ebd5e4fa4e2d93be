"""The rule that moves a segmentation worker's views to the caller (worker_lag.LagWatch)."""

from __future__ import annotations

import numpy as np
import pytest

from tracker.vision import worker_lag
from tracker.vision.worker_lag import GRACE_FRAMES, LAG_COUNT, LAG_FRAMES, LAG_S, LagWatch

OWN_S = 0.002  # the caller's own view, s


def frames_until_moved(watch: LagWatch, waits_s) -> int | None:
    """The index of the frame after which the views move, or None."""
    for k, wait in enumerate(waits_s):
        if watch.add(OWN_S, float(wait)):
            return k
    return None


def quiet_waits(n: int, rng) -> np.ndarray:
    return rng.uniform(0.0, 0.5 * OWN_S, n)


def test_a_worker_late_on_a_few_stray_frames_keeps_its_views():
    """A noisy machine's stray interruptions: waits of 1-3 views on 4% of the frames, at
    random (the old rule, 4 of 200 at 2 ms, moved the views) over a long session: the views
    stay (20% of a window lagging by chance is eleven standard deviations out)."""
    rng = np.random.default_rng(0)
    waits = quiet_waits(5000, rng)
    stray = rng.choice(waits.size, 200, replace=False)
    waits[stray] = rng.uniform(1.01 * OWN_S, 3 * OWN_S, stray.size)
    assert frames_until_moved(LagWatch(), waits) is None


def test_a_worker_that_lags_on_one_frame_in_five_hands_its_views_over():
    """Lagged on LAG_COUNT of LAG_FRAMES frames: the views move on the LAG_COUNT-th (a hog
    sharing the worker's processor lags on most frames, far more than this)."""
    rng = np.random.default_rng(1)
    waits = quiet_waits(GRACE_FRAMES + LAG_FRAMES, rng)
    lagged = GRACE_FRAMES + np.arange(LAG_COUNT) * (LAG_FRAMES // LAG_COUNT)
    waits[lagged] = 1.5 * OWN_S
    assert frames_until_moved(LagWatch(), waits) == lagged[-1]


def test_waits_shorter_than_the_callers_own_view_or_lag_s_do_not_count():
    watch = LagWatch()
    for _ in range(GRACE_FRAMES):
        assert not watch.add(OWN_S, 1.0)  # the grace frames do not count at all
    for _ in range(LAG_FRAMES):
        assert not watch.add(0.01, 0.009)  # longer than LAG_S, shorter than the view
        assert not watch.add(0.0001, 0.9 * LAG_S)  # longer than the view, within LAG_S
    assert watch.lagged == 0


def test_only_the_last_lag_frames_count_and_a_restart_forgets_them():
    watch = LagWatch()
    for _ in range(GRACE_FRAMES):
        watch.add(OWN_S, 0.0)
    for _ in range(LAG_COUNT - 1):
        assert not watch.add(OWN_S, 2 * OWN_S)
    assert watch.lagged == LAG_COUNT - 1
    for _ in range(LAG_FRAMES):  # the lagged frames slide out of the window
        assert not watch.add(OWN_S, 0.0)
    assert watch.lagged == 0
    for _ in range(LAG_COUNT - 1):
        watch.add(OWN_S, 2 * OWN_S)
    watch.restart()
    assert watch.lagged == 0
    for _ in range(GRACE_FRAMES):  # grace again after a restart
        assert not watch.add(OWN_S, 2 * OWN_S)
    assert watch.lagged == 0


@pytest.mark.parametrize("lag_s", [0.0, 0.004])
def test_lag_s_is_read_when_a_frame_is_added(monkeypatch, lag_s):
    monkeypatch.setattr(worker_lag, "LAG_S", lag_s)
    watch = LagWatch()
    for _ in range(GRACE_FRAMES):
        watch.add(OWN_S, 0.0)
    watch.add(0.001, 0.003)
    assert watch.lagged == int(0.003 > lag_s)


def test_a_worker_sharing_its_processor_hands_its_views_over_within_a_second_or_two():
    """A busy process on the worker's processor: its view takes two to four times as long
    (measured), so it lags on most frames; the views move after about LAG_COUNT / 0.8 frames
    past the grace (2.6 s at 20 fps)."""
    rng = np.random.default_rng(2)
    own = rng.uniform(0.9, 1.1, 400) * OWN_S
    worker = rng.uniform(2.0, 4.0, 400) * OWN_S  # its view, started with the caller's
    waits = np.maximum(worker - own, 0.0)
    watch = LagWatch()
    moved = next(k for k in range(400) if watch.add(float(own[k]), float(waits[k])))
    assert GRACE_FRAMES + LAG_COUNT - 1 <= moved <= GRACE_FRAMES + 2 * LAG_COUNT  # 0-based
