"""Python's garbage collection moved out of the frames, into the time between them.

CPython frees most objects at once (reference counts); its cyclic collector runs when the
allocations since the last collection pass a threshold, in whichever thread allocates
next, holding the interpreter meanwhile. In the live loop's process (the loop, its
capture, sink and joint threads, and numba, OpenCV, rerun and mcap loaded: some 200,000
tracked objects) that is about 1,000 allocations a frame, and so a collection of the
youngest generation in most frames (0.1-0.2 ms), of the middle one every tenth frame
(0.8-1.4 ms) and, now and then, of all objects (30-60 ms, measured in ``cathtrack
demo``). Falling within a frame, the middle one alone decides its 99th percentile, and
the full one makes it late.

:class:`FrameCollection` freezes what exists when the loop starts (the imported modules,
models and caches: never collected again, and no longer traversed) and turns the
automatic collection off; the loop calls :meth:`FrameCollection.collect` once its
estimate has left, which runs the collection CPython would have run by then, with its own
thresholds. Between frames is where the loop has time to spare (tens of ms at 20-30 fps
against 0.1-2 ms); the youngest generation then holds a frame's allocations, and the
oldest unfrozen one only what the session has kept since it started.
"""

from __future__ import annotations

import gc
import threading
import time

from tracker.live.summary import LatencyRecorder

_LOCK = threading.Lock()
_HOLDERS = 0  # the collections in force in this process (nested loops, tests)
_WAS_ENABLED = True  # the automatic collection before the first hold


class FrameCollection:
    """The cyclic garbage collection of this process, run between frames while held.

    ``hold()`` freezes the objects that exist and disables the automatic collection;
    ``collect()`` runs the youngest generation due by CPython's thresholds (the counts go
    on while it is disabled); ``release()`` puts the frozen objects back and the automatic
    collection as it was. Holds nest: the last release restores. Not ``enabled``, it does
    nothing (the automatic collection goes on).
    """

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = bool(enabled)
        self.took = LatencyRecorder(10_000)  # the last collections, s
        self.collections = [0, 0, 0]  # by generation
        self._held = False
        self._thresholds = gc.get_threshold()

    @property
    def held(self) -> bool:
        return self._held

    def hold(self) -> None:
        """Freeze what exists and turn the automatic collection off (until :meth:`release`).

        Freezing is constant time (a list moved), whatever the process holds: garbage
        already there waits for the release, and is collected after it."""
        global _HOLDERS, _WAS_ENABLED
        if self._held or not self.enabled:
            return
        with _LOCK:
            if _HOLDERS == 0:
                _WAS_ENABLED = gc.isenabled()
                gc.disable()
                gc.freeze()
            _HOLDERS += 1
        self._thresholds = gc.get_threshold()
        self._held = True

    def collect(self) -> int | None:
        """Collect what is due (the generation CPython would have collected by now); the
        generation collected, or None when nothing was due or it is not held."""
        if not self._held:
            return None
        t0, t1, t2 = self._thresholds
        c0, c1, c2 = gc.get_count()
        if t0 <= 0 or c0 < t0:
            return None
        generation = 2 if c2 >= t2 and c1 >= t1 else 1 if c1 >= t1 else 0
        started = time.perf_counter()
        gc.collect(generation)
        self.took.add(time.perf_counter() - started)
        self.collections[generation] += 1
        return generation

    def release(self) -> None:
        """Put the frozen objects back among the others; the automatic collection as it
        was before the first hold (the last release only)."""
        global _HOLDERS
        if not self._held:
            return
        self._held = False
        with _LOCK:
            _HOLDERS -= 1
            if _HOLDERS == 0:
                gc.unfreeze()
                if _WAS_ENABLED:
                    gc.enable()

    def __enter__(self) -> FrameCollection:
        self.hold()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def describe(self) -> str | None:
        """The collections and their times, for a summary ("none" when none ran; None when
        not enabled)."""
        if not self.enabled:
            return None
        n = sum(self.collections)
        if not n:
            return "none"
        ms = self.took.percentiles_ms()
        young, middle, full = self.collections
        return (
            f"{n} ({young} / {middle} / {full} by generation), p50 {ms['p50']:.2f} ms,"
            f" max {ms['max']:.2f} ms"
        )
