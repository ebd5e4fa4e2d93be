"""One pipeline for live tracking, simulation and replay (docs/design.md section 6).

    source (Frame) -> reconstruction (Observation) -> estimator (Estimate) -> sinks

A :class:`Frame` is what every source yields: the time, the joint values and the segmented
image points of every view of the rig (and optionally the images and the ground truth). The
:class:`Reconstructor` turns frames into observations relative to the registered base, with
covariances propagated from the segmentation noise and a finite-difference tip velocity
(:func:`tracker.types.velocity_from_positions`) correlated with the tip it came from.

This is the one Frame -> Observation converter: :meth:`Reconstructor.observe` for one frame
(the live loop) and :meth:`Reconstructor.observe_batch` for many (replay, evaluation), the
first being the second on a batch of one.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from models import _imaging_kernels
from models.catheter import Catheter
from models.imaging import Rig
from models.pose import Pose
from tracker.types import Frame, Observation, ViewMeasurement, velocity_from_positions

Array = np.ndarray

_IDENTITY = np.eye(3)
_IDENTITY.flags.writeable = False
# The frame before the first one: time, tip and its covariance as one-row arrays.
_NO_PREVIOUS = (np.full(1, np.nan), np.full((1, 3), np.nan), _IDENTITY[None])
# The tip before the first frame for the compiled step: its types as a real one's (writable).
_NO_TIP = (np.full(3, np.nan), np.eye(3))
_VELOCITY = ("velocity_b_mm_s", "velocity_cov_b", "velocity_tip_cov_b")


@dataclass
class Reconstructor:
    """Frames -> observations in the base frame {B}.

    Parameters
    ----------
    catheter : Catheter
    rig : Rig
        Two or more views; a frame has one set of image points per view, in ``rig.names``
        order.
    R_w_b, o_b_w_mm : arrays (3, 3), (3,)
        Registered pose of the catheter base in the world frame (see :class:`models.pose.Pose`).
    max_velocity_gap_s : float
        Longest interval over which a finite-difference tip velocity is still formed.
    """

    catheter: Catheter
    rig: Rig
    R_w_b: Array
    o_b_w_mm: Array
    max_velocity_gap_s: float = 0.2

    def __post_init__(self) -> None:
        self.pose = Pose(self.R_w_b, self.o_b_w_mm)
        self.R_w_b, self.o_b_w_mm = self.pose.R_w_b, self.pose.o_b_w_mm
        self.n_points = 1 + len(self.catheter.marker_arclengths_mm)
        self._view_bits = 1 << np.arange(self.rig.n_views)
        self.reset()

    def reset(self) -> None:
        """Forget the previous frame: the next frame has no finite-difference velocity."""
        self._previous: tuple[Array, Array, Array] | None = None  # one-row time, tip, cov

    def rehearse(self, frame: Frame) -> None:
        """:meth:`observe` without its result and without changing anything (the previous
        frame, for the next one's velocity, is kept): the live loop runs it on the last frame
        just before the next one is due (``LiveTracker.prime``). A frame :meth:`observe`
        refuses is ignored."""
        previous = self._previous
        try:
            with contextlib.suppress(ValueError):  # refused: the frame's own step says why
                self.observe(frame)
        finally:
            self._previous = previous

    def observe(self, frame: Frame) -> Observation:
        """Reconstruct one frame. Points missing in one view become single-view measurements.

        Exactly :meth:`observe_batch` of ``[frame]``; the usual live frame (every point in
        every view) takes a shorter path with the same arithmetic, any other the batch one.
        """
        observation = self._observe_usual(frame)
        return self.observe_batch([frame])[0] if observation is None else observation

    def _observe_usual(self, frame: Frame) -> Observation | None:
        """:meth:`observe` of a frame with every point finite in every view, finite joint
        values and covariances that are clearly fine; None for any other frame, with the
        state untouched, for :meth:`observe_batch` to handle (or name what is wrong).

        The live loop's path, one frame at a time, for a pinhole rig without distortion
        (any other goes the batch way): each call to numpy costs cache misses there, so the
        checks, triangulation, propagation, the move to {B} and the velocity are one compiled
        call (:func:`models._imaging_kernels.observe_frame`). Every number is computed by the
        same operations in the same order as on the batch path, so the results are
        identical to the bit.
        """
        P, V = self.n_points, self.rig.n_views
        t = frame.time_s
        if not isinstance(t, float | int) or len(frame.uv) != V:
            return None
        try:
            q = np.array(frame.q, dtype=float)
            uv = np.array(frame.uv, dtype=float)  # (V, P, 2)
            cov = np.array(frame.cov, dtype=float)  # (V, P, 2, 2)
        except (TypeError, ValueError):
            return None
        if q.shape != (3,) or uv.shape != (V, P, 2) or cov.shape != (V, P, 2, 2):
            return None
        q_dot = None if frame.q_dot is None else np.asarray(frame.q_dot, dtype=float)
        t = float(t)
        dt = math.nan  # no velocity
        previous = self._previous
        if previous is not None and q_dot is not None:
            gap = t - float(previous[0][0])
            if 0 < gap <= self.max_velocity_gap_s:
                if gap == math.inf:
                    return None  # the batch path names the interval
                dt = gap
        cams = self.rig._cameras
        if cams is not None and not cams.distorted:
            # One compiled call: the checks, triangulation, propagation, the move to {B} and
            # the velocity.
            before, cov_before = _NO_TIP if previous is None else (previous[1][0], previous[2][0])
            status, points_b, covs_b, *velocity = _imaging_kernels.observe_frame(
                q, uv, cov, cams.principal, cams.focal, cams.R_cam_w, cams.t_cam_w,
                cams.inverse_focal, self.R_w_b, self.o_b_w_mm, before, cov_before, dt,
            )  # fmt: skip
            if status != _imaging_kernels.FRAME_OK:
                return None
        else:
            points_b, covs_b = self._other_rig(q, uv, cov)
            if points_b is None:
                return None
            if dt == dt:
                velocity = velocity_from_positions(
                    points_b[0], covs_b[0], previous[1][0], previous[2][0], dt
                )
        extra = {}
        if dt == dt:  # formed
            extra = dict(zip(_VELOCITY, velocity, strict=True))
        self._previous = (np.array([t]), points_b[:1], covs_b[:1])
        return Observation(
            time_s=t,
            q=q,
            q_dot=q_dot,
            tip_b_mm=points_b[0],
            tip_cov_b=covs_b[0],
            markers_b_mm=points_b[1:],
            markers_cov_b=covs_b[1:],
            **extra,
        )

    def _other_rig(self, q: Array, uv: Array, cov: Array) -> tuple[Array | None, Array | None]:
        """:meth:`_observe_usual`'s points in {B} for a rig other than an undistorted pinhole
        one (None, None for a frame that is not usual), with the rig's own steps."""
        V, P = uv.shape[:2]
        finite = math.isfinite
        if not all(map(finite, q.tolist())) or not all(map(finite, uv.ravel().tolist())):
            return None, None
        for entries in cov.reshape(V, 4 * P).tolist():
            if not all(map(finite, entries)):
                return None, None
            # Rig.reconstruct_with_covariance's check, per view: symmetric to the same
            # tolerance (the same float operations), and positive semi-definite with ten times
            # its margin (math.hypot may differ from numpy's in the last bit).
            scale = max(1e-300, max(map(abs, entries)))
            for a, b, c, d in zip(*[iter(entries)] * 4, strict=True):
                if abs(b - c) > 1e-9 * scale or (
                    0.5 * (a + d) - math.hypot(0.5 * (a - d), c) < -1e-13 * scale
                ):
                    return None, None
        # C-contiguous copies, as the batch path's.
        uv = np.ascontiguousarray(uv.swapaxes(0, 1))  # (P, V, 2)
        cov = np.ascontiguousarray(cov.swapaxes(0, 1))  # (P, V, 2, 2)
        points_w = self.rig._triangulate(uv)
        return self._to_base(points_w, self.rig._propagate(points_w, cov))

    def observations(self, frames: Iterable[Frame]) -> Iterator[Observation]:
        for frame in frames:
            yield self.observe(frame)

    def observe_batch(self, frames: Sequence[Frame]) -> list[Observation]:
        """Reconstruct frames in order, all at once: exactly what :meth:`observe` gives for
        each frame in turn.

        The batch continues from the previous call (the first frame's velocity is formed from
        the last frame seen before) and leaves the state for the next; call :meth:`reset`
        first to start a new sequence.

        Parameters
        ----------
        frames : sequence of Frame
            Rows ``[tip, marker_0, ...]`` of ``1 + n_markers`` points in each view.

        Returns
        -------
        list of Observation
            One per frame, in {B}.
        """
        frames = list(frames)
        if not frames:
            return []
        time_s = np.array([f.time_s for f in frames], dtype=float)
        q = self._joints(frames)
        uv, cov = self._points(frames)  # (F, P, V, 2), (F, P, V, 2, 2)
        points_b, covs_b, seen, views = self._reconstructed(uv, cov)
        q_dot = [None if f.q_dot is None else np.asarray(f.q_dot, dtype=float) for f in frames]
        velocity = self._velocities(time_s, points_b[:, 0], covs_b[:, 0], seen[:, 0], q_dot)
        out = []
        for i in range(len(frames)):
            out.append(
                Observation(
                    time_s=float(time_s[i]),
                    q=q[i],
                    q_dot=q_dot[i],
                    tip_b_mm=points_b[i, 0],
                    tip_cov_b=covs_b[i, 0],
                    markers_b_mm=points_b[i, 1:],
                    markers_cov_b=covs_b[i, 1:],
                    views=views[i],
                    **velocity.get(i, {}),
                )
            )
        return out

    def _reconstructed(
        self, uv: Array, cov: Array
    ) -> tuple[Array, Array, Array, list[tuple[ViewMeasurement, ...]]]:
        """The points of every frame in {B}, from image points (F, P, V, 2) and noise.

        Returns
        -------
        points_b, covs_b : arrays (F, P, 3), (F, P, 3, 3)
            Points seen in two or more views and their covariances, mm, mm^2 (NaN and the
            identity for the others).
        seen : bool array (F, P)
            Which points those are.
        views : list of tuple of ViewMeasurement
            Per frame, the points seen in one view only, each view's as its own update.
        """
        F, P, V = uv.shape[:3]
        if np.isfinite(uv).all() and np.isfinite(cov).all():
            # The usual frames: every point found in every view, all from every view at once.
            points_w, cov_w = self.rig.reconstruct_with_covariance(
                uv.reshape(-1, V, 2), cov.reshape(-1, V, 2, 2)
            )
            points_b, covs_b = self._to_base(points_w, cov_w)
            points_b, covs_b = points_b.reshape(F, P, 3), covs_b.reshape(F, P, 3, 3)
            return points_b, covs_b, np.ones((F, P), dtype=bool), [()] * F
        found = np.isfinite(uv).all(-1) & np.isfinite(cov).all((-2, -1))  # (F, P, V)
        n_found = found.sum(axis=-1)
        seen = n_found >= 2
        points_b = np.full((F, P, 3), np.nan)
        covs_b = np.empty((F, P, 3, 3))
        covs_b[...] = _IDENTITY
        # Points seen in two or more views are triangulated from exactly those views: grouped
        # by their set of views (bit v for view v), each set in one vectorised call.
        view_sets = (found * self._view_bits).sum(axis=-1)  # (F, P)
        for view_set in sorted(set(view_sets[seen].tolist())):
            group = seen & (view_sets == view_set)
            views = [v for v in range(V) if view_set >> v & 1]
            points_w, cov_w = self.rig.subset(views).reconstruct_with_covariance(
                uv[group][:, views], cov[group][:, views]
            )
            points_b[group], covs_b[group] = self._to_base(points_w, cov_w)
        single = found & (n_found == 1)[..., None]  # a point seen in one view only
        single_views = [
            tuple(
                ViewMeasurement(
                    view=view,
                    R_w_b=self.R_w_b,
                    o_b_w_mm=self.o_b_w_mm,
                    uv=uv[i, single[i, :, v], v],
                    cov=cov[i, single[i, :, v], v],
                    point_index=np.flatnonzero(single[i, :, v]) - 1,
                )
                for v, view in enumerate(self.rig.views)
                if has_single[v]
            )
            for i, has_single in enumerate(single.any(axis=1).tolist())
        ]
        return points_b, covs_b, seen, single_views

    def _to_base(self, points_w: Array, cov_w: Array) -> tuple[Array, Array]:
        """Points (N, 3) and covariances (N, 3, 3) in {W} -> {B}, one compiled call with the
        arithmetic of :meth:`observe`'s (the pose's in another order of its sums)."""
        return _imaging_kernels.to_base(
            np.ascontiguousarray(points_w, dtype=float),
            np.ascontiguousarray(cov_w, dtype=float), self.R_w_b, self.o_b_w_mm,
        )  # fmt: skip

    def _velocities(
        self,
        time_s: Array,
        tip_b: Array,
        tip_cov_b: Array,
        has_tip: Array,
        q_dot: Sequence[Array | None],
    ) -> dict[int, dict[str, Array]]:
        """Finite-difference velocities by frame index, and the state for the next call.

        A frame gets one when it and the frame before (the last frame of the previous call,
        for the first) have the tip in two or more views, ``0 < dt <= max_velocity_gap_s``, and the
        frame has joint rates (the velocity is fused with them).
        """
        # Which frames get one, decided on plain floats (numpy's call overhead would outweigh
        # the work for the one frame of the live loop).
        gap_s = self.max_velocity_gap_s
        before_s = math.nan if self._previous is None else float(self._previous[0][0])
        before_known = self._previous is not None
        formed = []
        frames = zip(time_s.tolist(), has_tip.tolist(), q_dot, strict=True)
        for k, (t, known, rate) in enumerate(frames):
            if known and before_known and rate is not None and 0 < t - before_s <= gap_s:
                formed.append(k)
            before_s, before_known = t, known
        if not formed:
            velocity = {}
        else:
            # Row k of [the previous call's last frame, *these frames] is frame k's predecessor.
            previous = self._previous or _NO_PREVIOUS
            k = np.array(formed)
            v, cov_v, cross = velocity_from_positions(
                tip_b[k],
                tip_cov_b[k],
                np.concatenate((previous[1], tip_b))[k],
                np.concatenate((previous[2], tip_cov_b))[k],
                time_s[k] - np.concatenate((previous[0], time_s))[k],
            )
            velocity = {
                k: dict(velocity_b_mm_s=v[j], velocity_cov_b=cov_v[j], velocity_tip_cov_b=cross[j])
                for j, k in enumerate(formed)
            }
        self._previous = (time_s[-1:], tip_b[-1:], tip_cov_b[-1:]) if has_tip[-1] else None
        return velocity

    def _joints(self, frames: Sequence[Frame]) -> Array:
        """Joint values (F, 3), or a ValueError naming the first frame without them."""
        what = "the joint values (q_r [rad], q_p [mm], q_d [mm])"
        q = self._stacked(frames, "q", lambda f: f.q, (3,), what)
        if not np.isfinite(q).all():
            bad = frames[int(np.argmin(np.isfinite(q).all(axis=-1)))]
            raise ValueError(
                f"the frame at {bad.time_s} s has joint values {bad.q}: three finite numbers"
                " are needed"
            )
        return q

    def _points(self, frames: Sequence[Frame]) -> tuple[Array, Array]:
        """Image points (F, P, V, 2) and covariances (F, P, V, 2, 2) of every frame: the
        views of a point side by side, as :meth:`Rig.reconstruct_with_covariance` takes them."""
        n_views = self.rig.n_views
        bad = next((f for f in frames if len(f.uv) != n_views), None)
        if bad is not None:
            raise ValueError(
                f"the frame at {bad.time_s} s has image points of {len(bad.uv)} views, the rig"
                f" has {n_views} ({', '.join(self.rig.names)})"
            )
        # Every view of every frame in one array each, (F, V, P, ...), handed out as
        # (F, P, V, ...); view by view where that fails, to name the first bad one.
        P = self.n_points
        try:
            uv = np.array([f.uv for f in frames], dtype=float)
            cov = np.array([f.cov for f in frames], dtype=float)
        except (TypeError, ValueError):  # ragged (shapes differ) or not numbers
            uv = cov = None
        if (
            uv is not None
            and uv.shape[1:] == (n_views, P, 2)
            and cov.shape[1:] == (n_views, P, 2, 2)
        ):
            return uv.swapaxes(1, 2), cov.swapaxes(1, 2)
        what = "the tip and every marker of the catheter model"
        uv, cov = [], []
        for v, name in enumerate(self.rig.names):
            uv.append(self._stacked(frames, f"uv[{name}]", lambda f, v=v: f.uv[v], (P, 2), what))
            cov.append(
                self._stacked(frames, f"cov[{name}]", lambda f, v=v: f.cov[v], (P, 2, 2), what)
            )
        return np.stack(uv, axis=2), np.stack(cov, axis=2)

    @staticmethod
    def _stacked(frames: Sequence[Frame], name: str, field, shape: tuple, what: str) -> Array:
        """``field(frame)`` of every frame, (F, *shape), or a ValueError naming the first frame
        where it has another shape."""
        try:
            stacked = np.array([field(f) for f in frames], dtype=float)
        except (TypeError, ValueError):  # ragged (shapes differ between frames) or not numbers
            stacked = None
        if stacked is not None and stacked.shape[1:] == shape:
            return stacked
        bad = next((f for f in frames if np.shape(field(f)) != shape), frames[0])
        raise ValueError(
            f"the frame at {bad.time_s} s has {name} of shape {np.shape(field(bad))},"
            f" expected {shape}: {what}"
        )
