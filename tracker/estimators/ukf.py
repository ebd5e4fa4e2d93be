"""Unscented Kalman filter of the torsional loss angle delta_L (docs/design.md section 5).

:class:`BendingPlaneUKF` is the live filter: it turns each :class:`~tracker.types.Observation`
into measurement groups (:mod:`tracker.estimators.measurement`: the tip, each marker and the
tip velocity, each with its noise and model error) and steps a
:class:`~tracker.estimators.ukf_core.FilterBank` of one filter, where the rules (gate,
restart, mismatch, repair) are written once for this filter and the trial-batched one
(:func:`~tracker.estimators.ukf_batch.run_ukf_batch`). Every step returns an
:class:`~tracker.types.Estimate` value.

The state is ``[delta_L]`` (rad), with ``include_rate`` followed by ``delta_L_dot`` (rad/s),
and followed by the joint-equivalent deviation ``(dq_p, dq_d)`` (mm) of the shape unless the
settings turn the model error off. The filter is initialised from the exact global closed
form of the first frame that is informative and unambiguous relative to noise plus model
error, carries a restarted hypothesis beside the held one when a frame rejects the held
estimate as a whole, and reports the moment-matched mean and std of its hypotheses.

When the views are not synchronised, the points of each :class:`~tracker.types.ViewMeasurement`
are used through their projections ``view.project(R_w_b Rz(q_r + delta_L) c + o_b_w)`` (with
the segmentation noise only: the model-error term is defined for 3-D data); a single view
updates a filter but never starts one (it leaves a mirror ambiguity).

Notes
-----
The tip, each marker and the velocity are independent groups: a joint marker covariance
(``markers_cov_b`` of shape (3n, 3n)) contributes its diagonal blocks.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.catheter import Catheter
from tracker.estimators._linalg import (
    COVARIANCE_JITTER,
    COVARIANCE_JITTER_FLOOR,
    CovarianceError,
    sigma_sqrt,
    spd_inverse,
)
from tracker.estimators.deviation import ShapeExpansion
from tracker.estimators.measurement import ViewGroups, assemble_expanded
from tracker.estimators.per_frame import Estimator
from tracker.estimators.ukf_core import FilterBank
from tracker.estimators.ukf_settings import UKFSettings, gate_threshold
from tracker.types import Estimate, Flag, Observation

Array = np.ndarray


def _array(value, shape: tuple[int, ...]) -> Array | None:
    # A copy: the kernels take writable arrays, and recorded ones are often read-only.
    return None if value is None else np.array(value, dtype=float).reshape((1,) + shape)


def observation_groups(
    expansion: ShapeExpansion, observation: Observation, q: Array, velocity: bool = True
) -> tuple[object, bool]:
    """The measurement groups of one observation (B = 1) and whether part of it is missing.

    ``velocity`` False leaves the observation's velocity out (a filter that would not fuse
    it).

    Returns ``(groups, partial)`` with groups a ``FrameGroups`` (3-D data), a ``ViewGroups``
    (single views only) or None (nothing measured).

    Raises
    ------
    ValueError
        For marker arrays that do not match the catheter.
    """
    catheter = expansion.catheter
    n_markers = len(catheter.marker_arclengths_mm)
    markers = observation.markers_b_mm
    markers_cov = observation.markers_cov_b
    partial = False
    if markers is not None and markers_cov is not None:
        markers = np.array(markers, dtype=float)  # a writable copy, as _array
        if markers.shape != (n_markers, 3):
            raise ValueError(
                f"observation has markers of shape {markers.shape}, the catheter model has "
                f"{n_markers} markers"
            )
        markers, markers_cov = markers[None], marker_blocks(markers_cov, n_markers)[None]
    else:
        markers = markers_cov = None
    tip = _array(observation.tip_b_mm, (3,))
    tip_cov = _array(observation.tip_cov_b, (3, 3))
    if not velocity:
        velocity = velocity_cov = None
    else:
        velocity = _array(observation.velocity_b_mm_s, (3,))
        velocity_cov = _array(observation.velocity_cov_b, (3, 3))
    if velocity is None or velocity_cov is None:
        velocity = velocity_cov = None
    cross = observation.velocity_tip_cov_b
    if cross is not None:
        cross = np.array(cross, dtype=float)
        if cross.shape != (3, 3):
            raise ValueError(f"velocity_tip_cov_b must have shape (3, 3), got shape {cross.shape}")
        cross = cross[None]
    q_dot = None if observation.q_dot is None else _array(observation.q_dot, (3,))
    has_3d = tip is not None or markers is not None or velocity is not None
    if has_3d and observation.views and not _any_position(tip, tip_cov, markers, markers_cov):
        # The views carry the frame (a velocity alone is not fused with them): no expansion.
        has_3d = False
        partial = (tip is not None and tip_cov is not None) or (
            markers is not None and n_markers > 0
        )
    if has_3d:
        c, JK = expansion.expanded(q[None])
        groups = assemble_expanded(
            q[None], q_dot, c, JK, tip, tip_cov, markers, markers_cov, velocity,
            velocity_cov, cross,
        )  # fmt: skip
        found = groups.present[0].tolist()
        P = groups.n_positions
        partial = (tip is not None and tip_cov is not None and not found[0]) or (
            markers is not None and not all(found[1:P])
        )
        if any(found[:P]) or (not observation.views and any(found)):
            return groups, partial
    if observation.views:
        views = _view_groups(catheter, observation, q)
        if views is not None:
            return views[0], partial or views[1]
    return None, partial


def _any_position(tip, tip_cov, markers, markers_cov) -> bool:
    """Whether the tip or a marker is present (finite, with a finite covariance), as
    :func:`~tracker.estimators.measurement.assemble_expanded` finds them."""
    if tip is not None and tip_cov is not None:
        if np.isfinite(tip).all() and np.isfinite(tip_cov).all():
            return True
    if markers is None or markers_cov is None or markers.shape[1] == 0:
        return False
    finite = np.isfinite(markers).all(axis=-1) & np.isfinite(markers_cov).all(axis=(-2, -1))
    return bool(finite.any())


def marker_blocks(markers_cov, n_markers: int) -> Array:
    """The markers' covariances as (n, 3, 3) blocks (a copy), from (n, 3, 3) or a joint
    (3n, 3n) covariance (its diagonal blocks: the groups are independent)."""
    markers_cov = np.array(markers_cov, dtype=float)
    if markers_cov.shape == (3 * n_markers, 3 * n_markers):
        blocks = markers_cov.reshape(n_markers, 3, n_markers, 3)
        return blocks[np.arange(n_markers), :, np.arange(n_markers), :]
    if markers_cov.shape != (n_markers, 3, 3):
        raise ValueError(
            f"markers_cov_b must have shape ({n_markers}, 3, 3) or ({3 * n_markers},"
            f" {3 * n_markers}), got {markers_cov.shape}"
        )
    return markers_cov


def _view_groups(catheter: Catheter, observation: Observation, q: Array):
    # The model vectors of the tip, then of each marker: shape_vectors' numbers, in fewer
    # calls (a frame of single views is on the live loop's critical path); the checks on
    # plain Python values where the arrays are a few points long.
    points = catheter.points(q)
    n_markers = points.shape[0] - 1
    parts, zs, covs = [], [], []
    partial = False
    for view in observation.views:
        uv = np.asarray(view.uv, dtype=float).reshape(-1, 2)
        cov = np.asarray(view.cov, dtype=float).reshape(-1, 2, 2)
        index = np.asarray(view.point_index, dtype=int).reshape(-1)
        if not (uv.shape[0] == cov.shape[0] == index.shape[0]):
            raise ValueError(
                f"view measurement has {uv.shape[0]} points, {cov.shape[0]} covariances and "
                f"{index.shape[0]} point indices"
            )
        rows = index.tolist()
        if rows and (min(rows) < -1 or max(rows) >= n_markers):
            raise ValueError(
                f"view point_index must be -1 (tip) or a marker in [0, {n_markers}), got "
                f"{rows}"
            )
        ok = np.isfinite(np.concatenate([uv, cov.reshape(-1, 4)], axis=1)).all(axis=1)
        found = ok.tolist()
        partial |= not all(found)
        if not any(found):
            continue
        if not all(found):
            uv, cov, index = uv[ok], cov[ok], index[ok]
        C = points[index + 1]  # row 0 the tip (index -1), row k + 1 marker k
        R_w_b = np.asarray(view.R_w_b, dtype=float)
        parts.append((view.view, C, R_w_b, np.asarray(view.o_b_w_mm, dtype=float)))
        zs.append(uv)
        covs.append(cov)
    if not parts:
        return None
    z = np.concatenate(zs)[None]
    groups = ViewGroups(
        q=q[None], z=z, R=np.concatenate(covs)[None],
        present=np.ones(z.shape[:2], dtype=bool), parts=tuple(parts),
    )  # fmt: skip
    return groups, partial


@dataclass(frozen=True)
class Frames3D:
    """Observations' 3-D measurement groups assembled at once (N frames), for
    :meth:`~tracker.estimators.ukf_core.FilterBank.run_3d`.

    ``regular`` (N,) marks the frames assembled here (3-D data with a tip and markers, no
    single views, finite time and joints); the others hold placeholders and go through
    :meth:`BendingPlaneUKF.step`. The groups are the positions' (``n_positions``: the tip,
    then the markers) followed by the velocity's, present where ``has_velocity`` (N,): the
    groups :func:`observation_groups` makes of each frame, with or without its velocity.
    """

    regular: Array
    time_s: Array
    q: Array
    partial: Array
    y: Array
    c: Array
    R_bar: Array
    JK: Array
    present: Array
    u_norm_mm_s: Array
    has_velocity: Array
    n_positions: int


def _stack(values, shape: tuple[int, ...], given: Array | None = None) -> Array:
    """The values as one float array (M, *shape), NaN where ``given`` is False; ValueError
    when they are not all of that shape."""
    if given is not None and not given.all():
        missing = np.full(shape, np.nan)
        values = [v if g else missing for v, g in zip(values, given.tolist(), strict=True)]
    stacked = np.array(values, dtype=float)
    if stacked.shape != (len(values),) + shape:
        raise ValueError(f"values of shape {stacked.shape[1:]}, expected {shape}")
    return stacked


def assemble_frames(expansion: ShapeExpansion, observations: Sequence[Observation]
                    ) -> Frames3D | None:  # fmt: skip
    """The 3-D groups of every usual frame of ``observations`` at once (vectorised; the
    same numbers as :func:`observation_groups` frame by frame), or None when none is usual
    or their arrays do not stack (then every frame goes through the step)."""
    N = len(observations)
    n = len(expansion.catheter.marker_arclengths_mm)
    P = n + 1
    try:
        time_s = np.array([o.time_s for o in observations], dtype=float)
        q = _stack([o.q for o in observations], (3,))
    except (TypeError, ValueError):
        return None
    regular = np.array([
        not o.views and o.tip_b_mm is not None and o.tip_cov_b is not None
        and o.markers_b_mm is not None and o.markers_cov_b is not None for o in observations
    ], dtype=bool).reshape(N) & np.isfinite(time_s) & np.isfinite(q).all(axis=1)  # fmt: skip
    index = np.flatnonzero(regular)
    if index.size == 0:
        return None
    chosen = [observations[i] for i in index.tolist()]
    velocity_given = np.array(
        [o.velocity_b_mm_s is not None and o.velocity_cov_b is not None for o in chosen]
    )
    has_v = bool(velocity_given.any())
    try:
        tip = _stack([o.tip_b_mm for o in chosen], (3,))
        tip_cov = _stack([o.tip_cov_b for o in chosen], (3, 3))
        markers = _stack([o.markers_b_mm for o in chosen], (n, 3))
        try:
            markers_cov = _stack([o.markers_cov_b for o in chosen], (n, 3, 3))
        except ValueError:  # joint covariances among them
            markers_cov = np.array([marker_blocks(o.markers_cov_b, n) for o in chosen])
        velocity = velocity_cov = cross = q_dot = None
        if has_v:
            velocity = _stack([o.velocity_b_mm_s for o in chosen], (3,), velocity_given)
            velocity_cov = _stack([o.velocity_cov_b for o in chosen], (3, 3), velocity_given)
            with_cross = np.array([o.velocity_tip_cov_b is not None for o in chosen])
            cross = _stack([o.velocity_tip_cov_b for o in chosen], (3, 3), with_cross)
            with_rate = np.array([o.q_dot is not None for o in chosen])
            q_dot = _stack([o.q_dot for o in chosen], (3,), with_rate)
    except ValueError:
        return None
    q_chosen = q[index]
    c, JK = expansion.expanded(q_chosen)
    # A frame's velocity is decorrelated from its tip where the cross-covariance is usable;
    # elsewhere it is kept as it is: two assemblies, as each frame would have one of them.
    usable = np.zeros(index.size, dtype=bool)
    if has_v:
        usable = (
            np.isfinite(cross).all(axis=(1, 2))
            & np.isfinite(tip).all(axis=1)
            & np.isfinite(tip_cov).all(axis=(1, 2))
        )
    G = P + has_v
    shape = {"y": (G, 3), "c": (G, 3), "R_bar": (G, 3, 3), "JK": (G, 3, 5), "present": (G,)}
    arrays = {name: np.zeros((N,) + dims) for name, dims in shape.items()}
    arrays["present"] = arrays["present"].astype(bool)
    u_norm = np.zeros(N)
    for rows, with_cross in ((np.flatnonzero(usable), True), (np.flatnonzero(~usable), False)):
        if rows.size == 0:
            continue
        groups = assemble_expanded(
            q_chosen[rows], None if q_dot is None else q_dot[rows], c[rows], JK[rows],
            tip[rows], tip_cov[rows], markers[rows], markers_cov[rows],
            None if velocity is None else velocity[rows],
            None if velocity_cov is None else velocity_cov[rows],
            cross[rows] if with_cross else None,
        )  # fmt: skip
        for name in shape:
            arrays[name][index[rows]] = getattr(groups, name)
        u_norm[index[rows]] = groups.u_norm_mm_s
    present = arrays["present"]
    has_velocity = np.zeros(N, dtype=bool)
    has_velocity[index] = velocity_given
    partial = ~present[:, 0] | ~present[:, 1:P].all(axis=1)
    return Frames3D(
        regular=regular, time_s=time_s, q=q, partial=partial & regular, y=arrays["y"],
        c=arrays["c"], R_bar=arrays["R_bar"], JK=arrays["JK"], present=present,
        u_norm_mm_s=u_norm, has_velocity=has_velocity, n_positions=P,
    )  # fmt: skip


_FLAGS_SEEN: dict[int, Flag] = {}


def _flag(value: int) -> Flag:
    """``Flag(value)``, kept: making a flag combination costs more than a filter's report."""
    flag = _FLAGS_SEEN.get(value)
    if flag is None:
        flag = _FLAGS_SEEN[value] = Flag(value)
    return flag


def check_observation(observation: Observation, last_time_s: float) -> tuple[float, Array]:
    """The frame's time and joint values, or a ValueError for a frame no filter can use.

    Raises for a non-finite time, a frame before ``last_time_s`` (NaN: none yet) and joint
    values that are not three finite numbers.
    """
    t = float(observation.time_s)
    if not math.isfinite(t):
        raise ValueError(f"observation time must be finite, got {observation.time_s}")
    if math.isfinite(last_time_s) and t < last_time_s:
        raise ValueError(f"observations must arrive in time order: {t} s after {last_time_s} s")
    q = np.array(observation.q, dtype=float)  # writable, whatever the caller's
    if q.shape != (3,) or not all(map(math.isfinite, q.tolist())):
        raise ValueError(f"observation.q must be three finite numbers, got {observation.q}")
    return t, q


class BendingPlaneUKF(Estimator):
    """Online estimator of delta_L: a bank of one robust UKF (:mod:`ukf_core`).

    Parameters
    ----------
    catheter : Catheter
        Kinematic model (its markers are the rows of ``Observation.markers_b_mm``).
    settings : UKFSettings, optional
    name : str
        Name reported by the estimator interface.
    """

    def __init__(
        self, catheter: Catheter, settings: UKFSettings | None = None, name: str = "ukf"
    ) -> None:
        self.catheter = catheter
        self.settings = UKFSettings() if settings is None else settings
        self.name = name
        self._bank = FilterBank(self.settings, 1)
        self._bank.prepare_rules(1 + len(catheter.marker_arclengths_mm))
        self._expansion = ShapeExpansion(catheter)

    # ------------------------------------------------------------------ public interface
    def reset(self) -> None:
        """Forget everything: the next informative frame initialises the filter again."""
        self._bank.reset()

    def prepare(self, q: Array) -> None:
        """Get ready for a frame at joint values q (3,), mm and rad: what :meth:`step` will
        need of the model there is computed now (:meth:`ShapeExpansion.prepare`); the
        filter's state is unchanged."""
        self._expansion.prepare(q)

    @property
    def initialised(self) -> bool:
        """Whether the filter has a state (after its first informative frame)."""
        return bool(self._bank.initialised[0])

    @property
    def state(self) -> Array:
        """Copy of the leading hypothesis' state: delta_L (rad), [delta_L_dot (rad/s)],
        [dq_p, dq_d (mm)]."""
        bank = self._bank
        return bank.x[0, bank.leading()[0]].copy()

    @property
    def covariance(self) -> Array:
        """Copy of the leading hypothesis' state covariance."""
        bank = self._bank
        return bank.P[0, bank.leading()[0]].copy()

    @property
    def hypotheses(self) -> int:
        """Number of hypotheses carried."""
        return int(self._bank.active[0].sum())

    @property
    def noise_scale(self) -> float:
        """Current scale of the measurement covariances (1 unless ``estimate_noise``)."""
        return float(self._bank.noise_scale[0])

    @property
    def deviation_mm(self) -> Array:
        """The leading hypothesis' joint-equivalent deviation (dq_p, dq_d), mm (zeros when
        the settings do not estimate it)."""
        bank = self._bank
        if bank.deviation is None:
            return np.zeros(2)
        return bank.x[0, bank.leading()[0], bank.deviation : bank.deviation + 2].copy()

    def initialise(self, delta_L_rad: float, std_rad: float, time_s: float | None = None) -> None:
        """Start from a given prior instead of waiting for the first informative frame.

        Parameters
        ----------
        delta_L_rad, std_rad : float
            Prior mean and std of delta_L, rad (the std is capped at ``max_std_rad``).
        time_s : float, optional
            Time of the prior, s; the next step predicts from it.
        """
        if not (math.isfinite(delta_L_rad) and math.isfinite(std_rad) and std_rad > 0):
            raise ValueError(
                f"a prior needs a finite delta_L and a positive finite std, got {delta_L_rad},"
                f" {std_rad}"
            )
        self._bank.start(np.array([0]), np.array([float(delta_L_rad)]), np.array([std_rad]))
        if time_s is not None:
            self._bank.time_s[0] = float(time_s)

    def run(self, observations: Sequence[Observation]) -> list[Estimate]:
        """Consume a sequence of frames in order: the estimates :meth:`step` gives frame by
        frame, to the last bit, at a fraction of the cost for recorded 3-D data.

        The frames' groups are assembled at once (:func:`assemble_frames`) and the usual
        steps run in one compiled loop (:mod:`tracker.estimators.ukf_run`); every other frame
        (before the first estimate, with several hypotheses, single views, a step that needs
        the closed form) goes through :meth:`step`, which raises as it does for one frame.
        """
        observations = list(observations)
        frames = assemble_frames(self._expansion, observations)
        if frames is None:
            return [self.step(o) for o in observations]
        N = len(observations)
        out = (
            np.zeros(N), np.zeros(N), np.zeros(N, dtype=np.int64), np.zeros(N),
            np.zeros(N, dtype=np.int64), np.zeros(N), np.zeros(N, dtype=np.int64),
            np.zeros((N, 3 * frames.y.shape[1])), np.zeros(N, dtype=np.int64),
        )  # fmt: skip
        estimates: list[Estimate] = []
        k = 0
        while k < N:
            if frames.regular[k]:
                stop = self._bank.run_3d(frames, k, out)
                estimates += _estimates(frames, out, k, stop)
                if stop == N:
                    break
                k = stop
            estimates.append(self.step(observations[k]))
            k += 1
        return estimates

    def rehearse(self, observation: Observation) -> None:
        """:meth:`step` on ``observation`` without its result and without changing anything:
        the filter's state and the model prepared by :meth:`prepare` are as they were (the
        live loop runs it on the last frame just before the next one is due, so that the
        step's code and data are back in the processor's caches; ``LiveTracker.prime``). An
        observation the step refuses is ignored."""
        bank, expansion = self._bank, self._expansion
        # The bank's own arrays are put back, their contents copied in: arrays of another
        # layout would make its compiled step compile again (seconds) on the next frame.
        saved = dict(vars(bank))
        contents = {k: v.copy() for k, v in saved.items() if isinstance(v, np.ndarray)}
        prepared = expansion.held
        try:
            # A step that refuses the observation leaves nothing to warm: ignored.
            with contextlib.suppress(ValueError, np.linalg.LinAlgError):
                self.step(observation)
        finally:
            vars(bank).clear()
            vars(bank).update(saved)
            for k, v in contents.items():
                if saved[k].flags.writeable:
                    np.copyto(saved[k], v)
            expansion.held = prepared

    def step(self, observation: Observation) -> Estimate:
        """Consume one frame: predict to its time, then fuse what it measured.

        Raises
        ------
        ValueError
            For frames out of time order, non-finite time or joint values, marker arrays that
            do not match the catheter, or a measurement covariance that is not positive
            definite.
        """
        t, q = check_observation(observation, float(self._bank.time_s[0]))
        groups, partial = observation_groups(
            self._expansion, observation, q, bool(self._bank.velocity_offered()[0])
        )
        r = self._bank.step(np.array([t]), q[None], groups, np.array([partial]))
        nis = float(r.nis[0])
        return Estimate(
            time_s=t,
            delta_L_rad=float(r.delta_L_rad[0]),
            std_rad=float(r.std_rad[0]),
            q_r_rad=float(q[0]),
            flags=_flag(int(r.flags[0])),
            informative_radius_mm=float(r.radius_mm[0]),
            innovation=r.innovation[0],
            nis=nis if math.isfinite(nis) else None,
            nis_dof=int(r.nis_dof[0]),
            rejected_outliers=int(r.rejected[0]),
        )


def _estimates(frames: Frames3D, out: tuple, start: int, stop: int) -> list[Estimate]:
    """The estimates of frames ``start`` to ``stop`` from :meth:`FilterBank.run_3d`'s
    outputs, as :meth:`BendingPlaneUKF.step` makes them."""
    if stop <= start:
        return []
    part = slice(start, stop)
    mean, std, flags, nis, dof, radius, rejected, innovation, shown = out
    estimates = []
    for i, (t, q_r, m, s, f, v, d, r, j, length) in enumerate(zip(
        frames.time_s[part].tolist(), frames.q[part, 0].tolist(), mean[part].tolist(),
        std[part].tolist(), flags[part].tolist(), nis[part].tolist(), dof[part].tolist(),
        radius[part].tolist(), rejected[part].tolist(), shown[part].tolist(), strict=True,
    ), start):  # fmt: skip
        estimates.append(Estimate(
            time_s=t, delta_L_rad=m, std_rad=s, q_r_rad=q_r, flags=_flag(f),
            informative_radius_mm=r, innovation=None if length < 0 else innovation[i, :length],
            nis=v if math.isfinite(v) else None, nis_dof=d, rejected_outliers=j,
        ))  # fmt: skip
    return estimates


__all__ = [
    "COVARIANCE_JITTER",
    "COVARIANCE_JITTER_FLOOR",
    "BendingPlaneUKF",
    "CovarianceError",
    "Frames3D",
    "UKFSettings",
    "assemble_frames",
    "check_observation",
    "gate_threshold",
    "marker_blocks",
    "observation_groups",
    "sigma_sqrt",
    "spd_inverse",
]
