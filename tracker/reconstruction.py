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

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from models.catheter import Catheter
from models.imaging import Rig
from models.pose import Pose
from tracker.types import Frame, Observation, ViewMeasurement, velocity_from_positions

Array = np.ndarray



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
        self.reset()

    def reset(self) -> None:
        """Forget the previous frame: the next frame has no finite-difference velocity."""
        self._previous: tuple[float, Array, Array] | None = None

    def observe(self, frame: Frame) -> Observation:
        """Reconstruct one frame. Points missing in one view become single-view measurements."""
        return self.observe_batch([frame])[0]

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
        uv, cov = self._points(frames)  # (V, F, P, 2), (V, F, P, 2, 2)
        found = np.all(np.isfinite(uv), -1) & np.all(np.isfinite(cov), (-2, -1))  # (V, F, P)
        n_found = found.sum(axis=0)
        points_b = np.full(n_found.shape + (3,), np.nan)
        covs_b = np.tile(np.eye(3), n_found.shape + (1, 1))
        # Points seen in two or more views are triangulated from exactly those views: group
        # them by the set of views that found them (one group in the usual complete frame).
        seen = n_found >= 2
        if seen.any():
            patterns, group = np.unique(found[:, seen].T, axis=0, return_inverse=True)
            where = np.argwhere(seen)
            for g, pattern in enumerate(patterns):
                f_idx, p_idx = where[group.ravel() == g].T
                views = np.flatnonzero(pattern)
                rig = self.rig.subset(views)
                points_w = rig.reconstruct(*(uv[v, f_idx, p_idx] for v in views))
                cov_w = rig.reconstruction_covariance(
                    points_w, *(cov[v, f_idx, p_idx] for v in views)
                )
                points_b[f_idx, p_idx] = self.pose.base_from_world(points_w)
                covs_b[f_idx, p_idx] = self.pose.covariance_to_base(cov_w)
        q_dot = [None if f.q_dot is None else np.asarray(f.q_dot, dtype=float) for f in frames]
        velocity = self._velocities(time_s, points_b[:, 0], covs_b[:, 0], seen[:, 0], q_dot)
        single = found & (n_found == 1)  # a point seen in one view only: its own update
        out = []
        for i in range(len(frames)):
            views = tuple(
                ViewMeasurement(
                    view=view,
                    R_w_b=self.R_w_b,
                    o_b_w_mm=self.o_b_w_mm,
                    uv=uv[v, i, single[v, i]],
                    cov=cov[v, i, single[v, i]],
                    point_index=np.flatnonzero(single[v, i]) - 1,
                )
                for v, view in enumerate(self.rig.views)
                if single[v, i].any()
            )
            out.append(
                Observation(
                    time_s=float(time_s[i]),
                    q=q[i],
                    q_dot=q_dot[i],
                    tip_b_mm=points_b[i, 0],
                    tip_cov_b=covs_b[i, 0],
                    markers_b_mm=points_b[i, 1:],
                    markers_cov_b=covs_b[i, 1:],
                    views=views,
                    **velocity.get(i, {}),
                )
            )
        return out

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
        if self._previous is None:
            previous = (np.nan, np.full(3, np.nan), np.eye(3))
        else:
            previous = self._previous
        times = np.concatenate([[previous[0]], time_s])
        tips = np.concatenate([previous[1][None], tip_b])
        covs = np.concatenate([previous[2][None], tip_cov_b])
        tip_known = np.concatenate([[self._previous is not None], has_tip])
        dt = np.diff(times)
        with np.errstate(invalid="ignore"):  # dt is NaN without a previous frame
            formed = tip_known[1:] & tip_known[:-1] & (dt > 0) & (dt <= self.max_velocity_gap_s)
        formed &= np.array([rate is not None for rate in q_dot], dtype=bool)
        i = np.flatnonzero(formed)
        velocity = {}
        if i.size:
            v, cov_v, cross = velocity_from_positions(
                tips[i + 1], covs[i + 1], tips[i], covs[i], dt[i]
            )
            velocity = {
                int(k): dict(
                    velocity_b_mm_s=v[j], velocity_cov_b=cov_v[j], velocity_tip_cov_b=cross[j]
                )
                for j, k in enumerate(i)
            }
        self._previous = (float(time_s[-1]), tip_b[-1], tip_cov_b[-1]) if has_tip[-1] else None
        return velocity

    def _joints(self, frames: Sequence[Frame]) -> Array:
        """Joint values (F, 3), or a ValueError naming the first frame without them."""
        what = "the joint values (q_r [rad], q_p [mm], q_d [mm])"
        q = self._stacked(frames, "q", lambda f: f.q, (3,), what)
        finite = np.all(np.isfinite(q), axis=-1)
        if not finite.all():
            bad = frames[int(np.argmin(finite))]
            raise ValueError(
                f"the frame at {bad.time_s} s has joint values {bad.q}: three finite numbers"
                " are needed"
            )
        return q

    def _points(self, frames: Sequence[Frame]) -> tuple[Array, Array]:
        """Image points (V, F, P, 2) and covariances (V, F, P, 2, 2) of every frame."""
        n_views = self.rig.n_views
        bad = next((f for f in frames if len(f.uv) != n_views), None)
        if bad is not None:
            raise ValueError(
                f"the frame at {bad.time_s} s has image points of {len(bad.uv)} views, the rig"
                f" has {n_views} ({', '.join(self.rig.names)})"
            )
        what = "the tip and every marker of the catheter model"
        uv, cov = [], []
        for v, name in enumerate(self.rig.names):
            uv.append(
                self._stacked(
                    frames, f"uv[{name}]", lambda f, v=v: f.uv[v], (self.n_points, 2), what
                )
            )
            cov.append(
                self._stacked(
                    frames, f"cov[{name}]", lambda f, v=v: f.cov[v], (self.n_points, 2, 2), what
                )
            )
        return np.stack(uv), np.stack(cov)

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
