"""When a segmentation worker costs the caller more than doing its views itself
(:class:`tracker.vision.parallel.ParallelPairSegmenter`, docs/live.md).

With the worker, a frame costs the caller its own view plus its wait for the worker's answer
after it; with the worker's views segmented in the caller's process, its own view plus
another view, on every frame. So a wait costs more than the move saves only when it is
longer than a view: a frame whose wait was longer than the caller's own view that frame
(and than :data:`LAG_S`) is *lagged*. A worker that shares its processor with another busy
process, without a real-time priority, lags on most frames (its view stretched to two to
four times its time, measured): moving its views then pays. A worker whose views only have
a tail of their own (a virtual machine's processor taken away for a few ms now and then, a
kernel thread) lags on a few frames in a hundred, at random: moving its views would double
the loop's work on every frame to save a wait on a few. The views move to the caller when
:data:`LAG_COUNT` of the last :data:`LAG_FRAMES` frames lagged (20%: a virtual machine's
interruptions come in bursts too, and one 60 s demo, of three, moved its views with 10%).

An earlier rule counted waits over 2 ms alone, in 4 of 200 frames. On a machine whose view
takes 2.2 ms, where 3% of a quiet demo session's frames lagged, it moved the views to the
caller after a few stray waits, and the rest of the session ran one view after the other:
latency p50 5.4-6.1 ms and p99 16-21 ms, against 4.6-4.8 and 9.5-18 with the worker
(``cathtrack demo``, runs of each).
"""

from __future__ import annotations

import collections

LAG_S = 0.002  # a wait up to this long never counts, s
LAG_FRAMES = 200
LAG_COUNT = 40
# The first GRACE_FRAMES frames with the worker do not count: a first frame loads what it
# needs and searches whole images (100 ms has been seen), and the next few start cold.
GRACE_FRAMES = 10


class LagWatch:
    """The caller's waits for a worker, frame by frame: whether its views should move."""

    def __init__(self) -> None:
        self._lagged: collections.deque[bool] = collections.deque(maxlen=LAG_FRAMES)
        self._grace = GRACE_FRAMES

    def restart(self) -> None:
        """Forget the frames so far, and give the next GRACE_FRAMES frames their grace (a
        worker that has just taken its views back)."""
        self._lagged.clear()
        self._grace = GRACE_FRAMES

    def add(self, own_s: float, wait_s: float) -> bool:
        """One frame: the caller's own view took ``own_s``, then it waited ``wait_s`` for
        the worker, s. True when the worker's views should move to the caller."""
        if self._grace:
            self._grace -= 1
            return False
        lagged = wait_s > LAG_S and wait_s > own_s
        self._lagged.append(lagged)
        return lagged and self.lagged >= LAG_COUNT  # counted only on a frame that lagged

    @property
    def lagged(self) -> int:
        """Frames that lagged among the last LAG_FRAMES counted."""
        return sum(self._lagged)
