"""One pipeline for live tracking, simulation and replay (DESIGN.md section 6).

    source (Frame) -> reconstruction (Observation) -> estimator (Estimate) -> sinks

A :class:`Frame` is what every source yields: the time, the joint values and the segmented
image points of both views (and optionally the images and the ground truth). The
:class:`Reconstructor` turns frames into observations relative to the registered base, with
covariances propagated from the segmentation noise and a finite-difference tip velocity
correlated with the tip it came from.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from models.catheter import Catheter, check_joints
from models.imaging import BiplaneRig
from tracker.types import Frame, Observation, ViewMeasurement, velocity_from_positions

Array = np.ndarray




@dataclass
class Reconstructor:
    """Frames -> observations in the base frame {B}.

    Parameters
    ----------
    catheter : Catheter
    rig : BiplaneRig
    R_w_b, o_b_w_mm : arrays (3, 3), (3,)
        Registered pose of the catheter base in the world frame.
    max_velocity_gap_s : float
        Longest interval over which a finite-difference tip velocity is still formed.
    """

    catheter: Catheter
    rig: BiplaneRig
    R_w_b: Array
    o_b_w_mm: Array
    max_velocity_gap_s: float = 0.2

    def __post_init__(self) -> None:
        self.R_w_b = np.asarray(self.R_w_b, dtype=float)
        self.o_b_w_mm = np.asarray(self.o_b_w_mm, dtype=float)
        if self.R_w_b.shape != (3, 3) or not np.allclose(
            self.R_w_b @ self.R_w_b.T, np.eye(3), atol=1e-9
        ):
            raise ValueError("R_w_b must be a 3x3 rotation matrix")
        if self.o_b_w_mm.shape != (3,) or not np.all(np.isfinite(self.o_b_w_mm)):
            raise ValueError("o_b_w_mm must be a finite 3-vector")
        self.n_points = 1 + len(self.catheter.marker_arclengths_mm)
        self.reset()

    def reset(self) -> None:
        self._previous: tuple[float, Array, Array] | None = None

    def _check_frame(self, frame: Frame) -> None:
        for name in ("uv_front", "uv_side"):
            uv = np.asarray(getattr(frame, name))
            if uv.shape != (self.n_points, 2):
                raise ValueError(
                    f"frame {name} has shape {uv.shape}, expected ({self.n_points}, 2): the tip"
                    " and every marker of the catheter model"
                )
        for name in ("cov_front", "cov_side"):
            cov = np.asarray(getattr(frame, name))
            if cov.shape != (self.n_points, 2, 2):
                raise ValueError(
                    f"frame {name} has shape {cov.shape}, expected ({self.n_points}, 2, 2)"
                )

    def observe(self, frame: Frame) -> Observation:
        """Reconstruct one frame. Points missing in one view become single-view measurements."""
        self._check_frame(frame)
        q = check_joints(frame.q)
        uv_f, uv_s = np.asarray(frame.uv_front, float), np.asarray(frame.uv_side, float)
        cov_f, cov_s = np.asarray(frame.cov_front, float), np.asarray(frame.cov_side, float)
        ok_f = np.all(np.isfinite(uv_f), -1) & np.all(np.isfinite(cov_f), (-2, -1))
        ok_s = np.all(np.isfinite(uv_s), -1) & np.all(np.isfinite(cov_s), (-2, -1))
        both = ok_f & ok_s
        points_b = np.full((self.n_points, 3), np.nan)
        covs_b = np.tile(np.eye(3), (self.n_points, 1, 1))
        if both.any():
            points_w = self.rig.reconstruct(uv_f[both], uv_s[both])
            cov_w = self.rig.reconstruction_covariance(points_w, cov_f[both], cov_s[both])
            R_b_w = self.R_w_b.T
            points_b[both] = (points_w - self.o_b_w_mm) @ R_b_w.T
            covs_b[both] = R_b_w @ cov_w @ self.R_w_b
        views = []
        for view, ok, uv, cov in (
            (self.rig.front, ok_f, uv_f, cov_f),
            (self.rig.side, ok_s, uv_s, cov_s),
        ):
            single = ok & ~both
            if single.any():
                views.append(
                    ViewMeasurement(
                        view=view,
                        R_w_b=self.R_w_b,
                        o_b_w_mm=self.o_b_w_mm,
                        uv=uv[single],
                        cov=cov[single],
                        point_index=np.flatnonzero(single) - 1,
                    )
                )
        velocity = {}
        if both[0]:
            if self._previous is not None:
                t0, tip0, cov0 = self._previous
                dt = frame.time_s - t0
                if 0 < dt <= self.max_velocity_gap_s and frame.q_dot is not None:
                    v, cov_v, cross = velocity_from_positions(
                        points_b[0], covs_b[0], tip0, cov0, dt
                    )
                    velocity = dict(
                        velocity_b_mm_s=v, velocity_cov_b=cov_v, velocity_tip_cov_b=cross
                    )
            self._previous = (frame.time_s, points_b[0], covs_b[0])
        else:
            self._previous = None
        return Observation(
            time_s=float(frame.time_s),
            q=q,
            q_dot=None if frame.q_dot is None else np.asarray(frame.q_dot, dtype=float),
            tip_b_mm=points_b[0],
            tip_cov_b=covs_b[0],
            markers_b_mm=points_b[1:],
            markers_cov_b=covs_b[1:],
            views=tuple(views),
            **velocity,
        )

    def observations(self, frames: Iterable[Frame]) -> Iterator[Observation]:
        for frame in frames:
            yield self.observe(frame)
