"""The paper's experimental protocol as a simulated recording (``cathtrack simulate``).

Lawson, Chitale and Simaan (ICRA 2023) rotated the catheter to 11 bending planes around its
axis, actuated it through 94 joint configurations in all, recorded about 100 reconstructed
tip positions at each, and deflected the tip by contact for part of the configurations. The
simulated session does the same:

- ``planes`` bending planes with targets ``delta_1 = 2 pi k / planes``; each has its own true
  torsional loss ``delta_L`` (seeded, uniform over ``torsion_range_deg``, so it can exceed
  180 degrees) and the base is turned to ``q_r = delta_1 - delta_L``;
- ``configurations`` joint configurations ``(q_p, q_d)`` split over the planes, each bent
  enough (horizontal tip radius at least ``min_radius_mm``), fully inside both images and
  nowhere crossing or running along itself in either image (cameras only);
- ``frames_per_configuration`` frames at ``frame_rate_hz`` while the joints move a little
  about the configuration (so that a finite-difference tip velocity exists), joint values at
  ``joint_rate_hz`` throughout; between configurations a move of ``transition_s`` (contact
  released, base turned and torsion changed, catheter bent to the next configuration, contact
  made again) during which the camera keeps recording: those frames carry no configuration
  label, are seen by the estimators and are not scored;
- a segmentation-noise level and a tip deflection per configuration, cycled so that every
  plane sees every combination: markers only, Gaussian noise of ``noise_levels_mm`` (in the
  image plane at the isocentre); with images, the rendered frames at sensor
  noise ``image_noise_levels_gray``, segmented by tracker.vision.segmentation as the live loop does;
- tip deflection by contact as the paper made it: the catheter bends as if its distal joint
  were ``q_d + offset`` while the recording reports the commanded ``q_d``;
- optionally, what else a lab meets (``lab_conditions``,
  :class:`~replay.simulation.simulator.LabConditions`; none by default): a contact deviation
  of q_p and q_d per configuration, a true catheter that bends more or less than the model
  (the recording keeps the model), wrong and missing markers (markers only), and torsion that
  winds up with the base turns within a play (:meth:`Protocol.windup_rad`).

Every configuration draws from its own generator ``default_rng([seed, 2, c])``, so the
recording does not depend on the number of worker processes; the contact deviations come
from ``default_rng([seed, 16])``, so that the session's layout is the same with and without
them.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import tomllib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.catheter import Catheter
from models.imaging import Rig, default_orthographic_rig
from models.model_file import DEFAULT_MODEL_PATH, catheter_from_dict, load_catheter
from models.pose import Pose
from models.rig_file import rig_toml
from models.rotations import wrap_angle
from replay.parallel import single_blas_thread, worker_count
from replay.simulation.render import ImagingNuisance, Renderer, RenderSettings, default_render_rig
from replay.simulation.simulator import (
    JointTrajectory,
    LabConditions,
    Scene,
    contact_joint_offsets,
    image_sigma,
    in_plane_joint_offset,
    simulate_frames,
    torsion_windup,
    truth_catheter,
)
from tracker.io.recording import FrameLabels, MarkerQuality, RecordingWriter
from tracker.types import Frame
from tracker.vision.pair import PairSegmenter

Array = np.ndarray

PROTOCOL_NAME = "paper"
LAB_CONDITIONS_UNITS = {
    "model_scale_error": "relative scale of the modal matrices' bending columns in the truth",
    "contact_joint_std_mm": "mm, q_p and q_d, one draw per configuration",
    "outlier_probability": "per point and view",
    "outlier_magnitude": "mm in the image plane at the isocentre",
    "dropout_probability": "per point and view",
    "windup_play_rad": "rad",
}
"""The units of :attr:`ProtocolSettings.lab_conditions`, recorded with the settings."""


@dataclass(frozen=True)
class ProtocolSettings:
    """The experimental protocol (defaults: the paper's, see the module docstring).

    Parameters
    ----------
    seed : int
    planes, configurations, frames_per_configuration : int
        11, 94 and 100 in the paper.
    frame_rate_hz, joint_rate_hz : float
        Image frames and joint samples per second.
    transition_s : float
        Time between configurations, s: the joints move (the base turns to the next plane,
        where the torsion changes), rounded up to whole frame periods.
    transition_frames : bool
        Record frames during the moves too, as a camera that keeps running does. They carry
        no configuration label and are not scored, but the estimators see them (a filter
        sees the base turn and the torsion change).
    images : bool
        Render and record both camera images and segment them (pinhole rig only).
    rig : {"pinhole", "orthographic"}
        The renderer's two 640x480 cameras (``default_render_rig``), or the paper's
        orthographic planes (markers only).
    noise_levels_mm : tuple of float
        Markers only: segmentation noise sigma per configuration (cycled), mm in the image
        plane at the isocentre (px = mm x magnification for cameras).
    image_noise_levels_gray : tuple of float
        With images: sensor noise of the rendered frames per configuration (cycled), gray.
    deflection_levels_mm : tuple of float
        Tip deflection by contact per configuration (cycled after the noise levels), mm.
    torsion_range_deg : tuple of float
        Range of the per-plane true delta_L, degrees.
    q_p_abs_range_mm, q_d_range_mm : tuple of float
        Ranges of |q_p| (sign random) and of q_d of the configurations, mm.
    min_radius_mm : float
        Smallest horizontal tip radius of a configuration, mm (near-straight configurations
        carry no bending-plane information; the paper's were visibly bent).
    motion_amplitude : tuple of float
        Joint motion about each configuration (q_r rad, q_p mm, q_d mm), sinusoidal...
    motion_period_s : float
        ...with this period.
    image_nuisance : ImagingNuisance
        With images: how each frame differs from the recorded backgrounds (gain drift and
        flicker, offset, gamma, vibration, a moved camera; none by default). A dict of its
        fields is accepted too (settings read back from a recording).
    lab_conditions : LabConditions
        What a lab meets besides segmentation noise (none by default; a dict of its fields
        is accepted too). Units: ``model_scale_error`` relative (0.05: the true catheter bends
        5 % more than the model's modal matrices say); ``contact_joint_std_mm`` mm (per
        configuration, q_p and q_d of the true catheter off by normal deviations of this
        std, on top of the deflection level); ``outlier_probability`` and
        ``dropout_probability`` per point and view (markers only: with images the
        segmentation makes its own); ``outlier_magnitude`` **mm in the image plane at the
        isocentre**, like the noise levels (px = mm x magnification for cameras);
        ``windup_play_rad`` rad (the torsion winds up with the base turns within this play,
        :meth:`Protocol.windup_rad`).
    """

    seed: int = 0
    planes: int = 11
    configurations: int = 94
    frames_per_configuration: int = 100
    frame_rate_hz: float = 20.0
    joint_rate_hz: float = 1000.0
    transition_s: float = 1.0
    transition_frames: bool = True
    images: bool = True
    rig: str = "pinhole"
    noise_levels_mm: tuple[float, ...] = (0.5, 1.0, 1.5)
    image_noise_levels_gray: tuple[float, ...] = (2.0, 3.5, 5.0)
    deflection_levels_mm: tuple[float, ...] = (0.0, 0.0, 1.5, 3.0)
    torsion_range_deg: tuple[float, float] = (-200.0, 200.0)
    q_p_abs_range_mm: tuple[float, float] = (0.35, 0.95)
    q_d_range_mm: tuple[float, float] = (-0.8, 0.8)
    min_radius_mm: float = 6.0
    motion_amplitude: tuple[float, float, float] = (0.05, 0.08, 0.08)
    motion_period_s: float = 2.5
    image_nuisance: ImagingNuisance = ImagingNuisance()
    lab_conditions: LabConditions = LabConditions()

    def __post_init__(self) -> None:
        if isinstance(self.image_nuisance, dict):
            object.__setattr__(self, "image_nuisance", ImagingNuisance(**self.image_nuisance))
        if isinstance(self.lab_conditions, dict):
            object.__setattr__(self, "lab_conditions", LabConditions(**self.lab_conditions))
        for name in ("planes", "configurations", "frames_per_configuration"):
            if int(getattr(self, name)) != getattr(self, name) or getattr(self, name) < 1:
                raise ValueError(f"{name} must be a positive integer, got {getattr(self, name)}")
        if self.configurations < self.planes:
            raise ValueError(
                f"need at least one configuration per plane: {self.configurations} configurations"
                f" for {self.planes} planes"
            )
        for name in ("frame_rate_hz", "joint_rate_hz", "motion_period_s"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not self.transition_s >= 0:
            raise ValueError(f"transition_s must be >= 0, got {self.transition_s}")
        if self.rig not in ("pinhole", "orthographic"):
            raise ValueError(f"rig must be 'pinhole' or 'orthographic', got {self.rig!r}")
        if self.images and self.rig != "pinhole":
            raise ValueError("images need the pinhole rig (cameras); use --no-images for planes")
        lab = self.lab_conditions
        if self.images and (lab.outlier_probability > 0 or lab.dropout_probability > 0):
            raise ValueError(
                "wrong and missing markers are simulated for markers only (--no-images): with"
                " images the segmentation makes its own"
            )
        levels = self.image_noise_levels_gray if self.images else self.noise_levels_mm
        if not levels or any(not (math.isfinite(x) and x >= 0) for x in levels):
            raise ValueError(f"noise levels must be non-empty and >= 0, got {levels}")
        if not self.deflection_levels_mm or any(x < 0 for x in self.deflection_levels_mm):
            raise ValueError(f"deflection levels must be >= 0, got {self.deflection_levels_mm}")
        # Frames and joint samples on one integer-nanosecond grid, so frame times hit samples.
        if self.frame_period_ns % self.joint_period_ns:
            raise ValueError(
                "the frame period must be a whole number of joint periods"
                f" ({self.frame_rate_hz:g} Hz frames, {self.joint_rate_hz:g} Hz joints)"
            )

    @property
    def frame_period_ns(self) -> int:
        return int(round(1e9 / self.frame_rate_hz))

    @property
    def joint_period_ns(self) -> int:
        return int(round(1e9 / self.joint_rate_hz))

    @property
    def noise_levels(self) -> tuple[float, ...]:
        return self.image_noise_levels_gray if self.images else self.noise_levels_mm

    @property
    def noise_unit(self) -> str:
        return (
            "gray (sensor noise of the rendered images)"
            if self.images
            else ("mm (segmentation noise in the image plane at the isocentre)")
        )

    def to_dict(self) -> dict:
        return {
            key: list(value) if isinstance(value, tuple) else value
            for key, value in dataclasses.asdict(self).items()
        }


@dataclass(frozen=True)
class Configuration:
    """One joint configuration of the protocol."""

    index: int
    plane: int
    q0: Array  # (3,) joint values about which the joints move (rad, mm, mm)
    delta_L_rad: float
    deflection_mm: float
    joint_offset: Array  # (3,) deflection and contact deviation of the joints (rad, mm, mm)
    noise_level: float
    start_ns: int  # time of the first frame
    windup_start_rad: float = 0.0  # wound-up torsion (tip - base turn) at start_ns


@dataclass(frozen=True)
class Protocol:
    """The layout of a protocol session: planes, configurations and the joint motion."""

    settings: ProtocolSettings
    delta_1_targets_rad: Array  # (planes,)
    delta_L_rad: Array  # (planes,)
    configurations: tuple[Configuration, ...]

    @property
    def window_ns(self) -> int:
        """Duration of one configuration's frames, ns."""
        return self.settings.frames_per_configuration * self.settings.frame_period_ns

    @property
    def end_ns(self) -> int:
        return self.configurations[-1].start_ns + self.window_ns

    @property
    def n_frames(self) -> int:
        """Frames of the whole session (configurations and, if recorded, the moves)."""
        return sum(self.frame_times_ns(c).size for c in range(len(self.configurations)))

    def frame_times_ns(self, c: int) -> Array:
        """Frame times of configuration c and, if recorded, of the move to the next one."""
        s = self.settings
        start = self.configurations[c].start_ns
        end = start + self.window_ns
        if s.transition_frames and c + 1 < len(self.configurations):
            end = self.configurations[c + 1].start_ns
        return np.arange(start, end, s.frame_period_ns, dtype=np.int64)

    def in_configuration(self, time_ns: Array) -> tuple[Array, Array]:
        """(index of the configuration whose window holds each time or the move after which
        it comes, True where the time is inside that configuration's window)."""
        t_ns = np.asarray(time_ns, dtype=np.int64)
        starts = np.array([c.start_ns for c in self.configurations], dtype=np.int64)
        k = np.clip(np.searchsorted(starts, t_ns, side="right") - 1, 0, len(starts) - 1)
        return k, (t_ns - starts[k]) < self.window_ns

    def truth(self, time_ns: Array) -> tuple[Array, Array]:
        """True delta_L (rad) and the deflection joint offset (rad, mm, mm) at the given times.

        Constant within a configuration, but for the wind-up (:meth:`windup_rad`). A move
        between configurations goes as an experimenter would make it: the contact is released
        (first fifth of the move), the torsion turns the short way to the next plane's (first
        two fifths), the catheter moves free, and the contact is made again at the next
        configuration (last fifth); each change along a smoothstep.
        """
        t_ns = np.asarray(time_ns, dtype=np.int64)
        k, inside = self.in_configuration(t_ns)
        delta_L = np.array([c.delta_L_rad for c in self.configurations])
        offsets = np.array([c.joint_offset for c in self.configurations])
        out_delta, out_offset = delta_L[k].copy(), offsets[k].copy()
        moving = ~inside & (k + 1 < len(self.configurations))
        if np.any(moving):
            kk = k[moving]
            start = np.array([c.start_ns for c in self.configurations])
            x = (t_ns[moving] - start[kk] - self.window_ns) / (
                start[kk + 1] - start[kk] - self.window_ns
            )

            def ramp(lo: float, hi: float) -> Array:
                u = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
                return u * u * (3 - 2 * u)

            step = wrap_angle(delta_L[kk + 1] - delta_L[kk])
            out_delta[moving] = wrap_angle(delta_L[kk] + ramp(0.0, 0.4) * step)
            out_offset[moving] = (1 - ramp(0.0, 0.2))[:, None] * offsets[kk] + ramp(0.8, 1.0)[
                :, None
            ] * offsets[kk + 1]
        if self.settings.lab_conditions.windup_play_rad > 0:
            out_delta = wrap_angle(out_delta + self.windup_rad(t_ns))
        return out_delta, out_offset

    def windup_rad(self, time_ns: Array) -> Array:
        """Torsion wound up by the base's turns, rad, added to the plane's delta_L.

        The tip follows the base only once the base has turned ``windup_play_rad`` beyond it
        (:func:`~replay.simulation.simulator.torsion_windup`, a play operator run over the
        joint samples from the session's start), so the wound-up part stays within +/- the
        play and lags every reversal of ``q_r``. Zero without play.
        """
        t_ns = np.asarray(time_ns, dtype=np.int64)
        play = self.settings.lab_conditions.windup_play_rad
        out = np.zeros(t_ns.shape)
        if play == 0:
            return out
        period = self.settings.joint_period_ns
        k, _ = self.in_configuration(t_ns)
        for c in np.unique(k):
            # From the state stored at the configuration's start, over its joint samples.
            here = k == c
            cfg = self.configurations[c]
            n = (t_ns[here] - cfg.start_ns) // period
            q_r = self.joints(cfg.start_ns + period * np.arange(n.max() + 1))[0][:, 0]
            start = q_r[0] + cfg.windup_start_rad  # the tip's turn: play-operator state
            out[here] = torsion_windup(np.concatenate([[start], q_r]), play)[1:][n]
        return out

    def joints(self, time_ns: Array) -> tuple[Array, Array]:
        """Commanded joint values and rates at the given times (rad, mm; rad/s, mm/s)."""
        t_ns = np.asarray(time_ns, dtype=np.int64)
        starts = np.array([c.start_ns for c in self.configurations], dtype=np.int64)
        k = np.clip(np.searchsorted(starts, t_ns, side="right") - 1, 0, len(starts) - 1)
        tau = (t_ns - starts[k]) / 1e9
        q, q_dot = self._motion(k, tau)
        window_s = self.window_ns / 1e9
        moving = (tau >= window_s) & (k + 1 < len(starts))
        if np.any(moving):
            # Between configurations: a cubic Hermite move, continuous in value and rate.
            kk = k[moving]
            gap_s = (starts[kk + 1] - starts[kk]) / 1e9 - window_s
            a, a_dot = self._motion(kk, np.full(kk.shape, window_s))
            b, b_dot = self._motion(kk + 1, np.zeros(kk.shape))
            x = ((tau[moving] - window_s) / gap_s)[:, None]
            h = gap_s[:, None]
            h00, h10 = 2 * x**3 - 3 * x**2 + 1, x**3 - 2 * x**2 + x
            h01, h11 = -2 * x**3 + 3 * x**2, x**3 - x**2
            q[moving] = h00 * a + h10 * h * a_dot + h01 * b + h11 * h * b_dot
            d00, d10 = 6 * x**2 - 6 * x, 3 * x**2 - 4 * x + 1
            d01, d11 = -6 * x**2 + 6 * x, 3 * x**2 - 2 * x
            q_dot[moving] = (d00 * a + d01 * b) / h + d10 * a_dot + d11 * b_dot
        return q, q_dot

    def _motion(self, k: Array, tau_s: Array) -> tuple[Array, Array]:
        s = self.settings
        q0 = np.array([c.q0 for c in self.configurations])[k]
        amplitude = np.asarray(s.motion_amplitude, dtype=float)
        omega = 2 * np.pi / s.motion_period_s
        phase = np.array([0.0, 0.5 * np.pi, np.pi])
        angle = omega * np.asarray(tau_s, dtype=float)[:, None] + phase
        # Zero motion at tau = 0 relative to the configuration's nominal joints for q_r.
        q = q0 + amplitude * (np.sin(angle) - np.sin(phase))
        return q, amplitude * omega * np.cos(angle)


def _scene(settings: ProtocolSettings, catheter: Catheter) -> Scene:
    if settings.rig == "pinhole":
        rig: Rig = default_render_rig()
    else:
        rig = default_orthographic_rig()
    return Scene(catheter, rig, np.eye(3), np.array([0.0, 0.0, -15.0]))


def _inside_images(scene: Scene, q: Array, delta_L: float, margin_px: float = 12.0) -> bool:
    """The whole catheter projects inside every image (pinhole rigs), with a margin."""
    if scene.rig.kind != "pinhole":
        return True
    s = np.linspace(0.0, scene.catheter.length_mm, 12)
    points_w = scene.catheter.backbone(q, delta_L, s) @ scene.R_w_b.T + scene.o_b_w_mm
    for view in scene.rig.views:
        uv = view.project(points_w)
        width, height = view.image_size
        if np.any(uv < margin_px) or np.any(uv[:, 0] > width - 1 - margin_px):
            return False
        if np.any(uv[:, 1] > height - 1 - margin_px):
            return False
    return True


def _overlaps_in_images(scene: Scene, q: Array, delta_L: float, clearance_px: float = 4.0) -> bool:
    """The catheter's image crosses or runs along itself in a view (pinhole rigs).

    Parts of the backbone more than 5 mm apart along the catheter must stay a tube diameter
    plus ``clearance_px`` apart in every image; otherwise the segmentation cannot tell them
    apart (it withholds the points, as it should) and the configuration is not one an
    experimenter would choose.
    """
    if scene.rig.kind != "pinhole":
        return False
    catheter = scene.catheter
    s = np.linspace(0.0, catheter.length_mm, 59)
    points_w = catheter.backbone(q, delta_L, s) @ scene.R_w_b.T + scene.o_b_w_mm
    apart = np.abs(s[:, None] - s[None, :]) > 5.0
    for view in scene.rig.views:
        uv = view.project(points_w)
        px_per_mm = float(view.K[0, 0] / view.t_cam_w[2])
        distance = np.linalg.norm(uv[:, None, :] - uv[None, :, :], axis=-1)
        if np.any(distance[apart] < 1.2 * px_per_mm + clearance_px):
            return True
    return False


def build_protocol(settings: ProtocolSettings, scene: Scene) -> Protocol:
    """Planes, torsions, configurations, noise and deflection levels of a session (seeded).

    ``scene`` holds the model; with a model error the configurations are chosen so that the
    true catheter (:func:`~replay.simulation.simulator.truth_catheter`) is bent enough and
    inside the images.
    """
    s = settings
    lab = s.lab_conditions
    catheter = scene.catheter
    truth_scene = dataclasses.replace(
        scene, catheter=truth_catheter(catheter, lab.model_scale_error)
    )
    rng = np.random.default_rng([s.seed, 1])
    contact = contact_joint_offsets(
        np.random.default_rng([s.seed, 16]), s.configurations, lab.contact_joint_std_mm
    )
    # The in-image checks hold wherever the wind-up can turn the plane.
    windups = (-lab.windup_play_rad, 0.0, lab.windup_play_rad) if lab.windup_play_rad else (0.0,)
    targets = wrap_angle(2 * np.pi * np.arange(s.planes) / s.planes)
    lo, hi = np.radians(s.torsion_range_deg)
    delta_L = rng.uniform(lo, hi, s.planes)
    plane_of = np.concatenate(
        [
            np.full(len(part), p)
            for p, part in enumerate(np.array_split(np.arange(s.configurations), s.planes))
        ]
    )
    n_noise = len(s.noise_levels)
    amplitude = np.asarray(s.motion_amplitude, dtype=float)
    configurations = []
    q_r_previous = 0.0
    step_ns = s.frames_per_configuration * s.frame_period_ns + int(round(s.transition_s * 1e9))
    step_ns = -(-step_ns // s.frame_period_ns) * s.frame_period_ns
    for c in range(s.configurations):
        p = int(plane_of[c])
        q_r = float(targets[p] - delta_L[p])
        # The base turns the short way from where it was (q_r is not wrapped: it is a joint).
        q_r += 2 * np.pi * np.round((q_r_previous - q_r) / (2 * np.pi))
        q_r_previous = q_r
        deflection = float(s.deflection_levels_mm[(c // n_noise) % len(s.deflection_levels_mm)])
        for _attempt in range(1000):
            q_p = rng.uniform(*s.q_p_abs_range_mm) * rng.choice([-1.0, 1.0])
            q_d = rng.uniform(*s.q_d_range_mm)
            q0 = np.array([q_r, q_p, q_d])
            try:
                offset = in_plane_joint_offset(truth_scene.catheter, q0, deflection) + contact[c]
            except ValueError:
                continue
            # Bent enough as the model sees it (q) and as it is (q + offset), over the motion.
            extremes = [q0 + sign * amplitude for sign in (-1.0, 0.0, 1.0)]
            radius = np.concatenate(
                [
                    np.hypot(*model.shape_vectors(np.array(qs)).c_tip_mm[..., :2].T)
                    for model, qs in (
                        (catheter, extremes),
                        (truth_scene.catheter, [q + offset for q in extremes]),
                    )
                ]
            )
            if radius.min() < s.min_radius_mm:
                continue
            extremes = [q0 + offset + sign * amplitude for sign in (-1.0, 1.0)]
            poses = [(q, float(delta_L[p]) + w) for q in [q0 + offset, *extremes] for w in windups]
            if all(_inside_images(truth_scene, q, d) for q, d in poses) and not any(
                _overlaps_in_images(truth_scene, q, d) for q, d in poses
            ):
                break
        else:
            raise ValueError(
                "cannot find a bent configuration inside both images: widen the joint ranges"
                " or lower min_radius_mm"
            )
        configurations.append(
            Configuration(
                index=c,
                plane=p,
                q0=q0,
                delta_L_rad=float(delta_L[p]),
                deflection_mm=deflection,
                joint_offset=offset,
                noise_level=float(s.noise_levels[c % n_noise]),
                start_ns=c * step_ns,
            )
        )
    protocol = Protocol(s, targets, delta_L, tuple(configurations))
    if not lab.windup_play_rad:
        return protocol
    # The wind-up state at each configuration's start, from one pass over the session.
    t_ns = np.arange(0, protocol.end_ns, s.joint_period_ns, dtype=np.int64)
    windup = torsion_windup(protocol.joints(t_ns)[0][:, 0], lab.windup_play_rad)
    starts = [
        dataclasses.replace(c, windup_start_rad=float(windup[c.start_ns // s.joint_period_ns]))
        for c in configurations
    ]
    return dataclasses.replace(protocol, configurations=tuple(starts))


# ----------------------------------------------------------------------- one configuration
@dataclass(frozen=True)
class _Job:
    settings: ProtocolSettings
    model_toml: str
    configuration: Configuration
    protocol: Protocol


def _catheter_from_text(text: str) -> Catheter:
    return catheter_from_dict(tomllib.loads(text), "model")


def configuration_frames(job: _Job) -> list[tuple[Frame, FrameLabels, tuple]]:
    """The frames of one configuration with their labels and segmentation quality."""

    with single_blas_thread():
        return _configuration_frames(job)


def _configuration_frames(job: _Job) -> list[tuple[Frame, FrameLabels, tuple]]:
    s, cfg, protocol = job.settings, job.configuration, job.protocol
    catheter = _catheter_from_text(job.model_toml)
    # The frames show the true catheter; the segmentation, like the recording, has the model.
    truth = truth_catheter(catheter, s.lab_conditions.model_scale_error)
    scene = _scene(s, truth)
    rng = np.random.default_rng([s.seed, 2, cfg.index])
    t_ns = protocol.frame_times_ns(cfg.index)
    q, q_dot = protocol.joints(t_ns)
    delta_L, offset = protocol.truth(t_ns)
    _, inside = protocol.in_configuration(t_ns)
    labels = [
        FrameLabels(
            plane=cfg.plane,
            configuration=cfg.index,
            deflection_mm=cfg.deflection_mm,
            noise_level=cfg.noise_level,
            delta_1_true_rad=float(wrap_angle(q[k, 0] + delta_L[k])),
        )
        if inside[k]
        else FrameLabels(delta_1_true_rad=float(wrap_angle(q[k, 0] + delta_L[k])))
        for k in range(t_ns.size)
    ]
    if not s.images:
        trajectory = JointTrajectory(t_ns / 1e9, q, q_dot)
        view, lab = scene.rig.views[0], s.lab_conditions
        lab = dataclasses.replace(lab, outlier_magnitude=image_sigma(view, lab.outlier_magnitude))
        frames = simulate_frames(
            scene,
            trajectory,
            delta_L,
            lab.noise(image_sigma(view, cfg.noise_level)),
            rng,
            model_joint_offset=offset,
        )
        return [(f, label, (None, None)) for f, label in zip(frames, labels, strict=True)]

    renderer = Renderer(
        truth,
        scene.rig,
        scene.R_w_b,
        scene.o_b_w_mm,
        RenderSettings(noise_sigma_gray=cfg.noise_level),
        seed=s.seed,
        nuisance=s.image_nuisance,
        nuisance_seed=(s.seed, 15, cfg.index),
    )
    segmenter = PairSegmenter(
        catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, renderer.backgrounds
    )
    out = []
    for k in range(t_ns.size):
        pair = renderer.render(q[k] + offset[k], float(delta_L[k]), rng)
        seg = segmenter.segment(pair.images)
        frame = seg.frame(t_ns[k] / 1e9, q[k], q_dot[k], pair.images, float(delta_L[k]))
        quality = tuple(MarkerQuality.from_segmentation(view) for view in seg.views)
        out.append((frame, labels[k], quality))
    return out


def backgrounds(settings: ProtocolSettings, catheter: Catheter) -> tuple[Array, Array]:
    """The empty-scene priors of both cameras (the same for every noise level)."""

    scene = _scene(settings, catheter)
    renderer = Renderer(catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, seed=settings.seed)
    return renderer.backgrounds


def _ordered(jobs: Sequence[_Job], workers: int) -> Iterator[list]:
    """Results of the jobs in order, at most ``2 workers`` jobs in flight (bounded memory)."""
    if workers <= 1 or len(jobs) <= 1:
        for job in jobs:
            yield configuration_frames(job)
        return
    from collections import deque
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=workers) as pool:
        pending: deque = deque()
        queue = iter(jobs)
        for job in queue:
            pending.append(pool.submit(configuration_frames, job))
            if len(pending) >= 2 * workers:
                break
        while pending:
            result = pending.popleft().result()
            for job in queue:
                pending.append(pool.submit(configuration_frames, job))
                break
            yield result


# ------------------------------------------------------------------------------- simulate
@dataclass(frozen=True)
class SimulationSummary:
    path: Path
    frames: int
    joint_samples: int
    duration_s: float
    bytes: int


def simulate_protocol(
    settings: ProtocolSettings,
    path: str | Path,
    model_path: str | Path | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> SimulationSummary:
    """Write a recording of the protocol to ``path`` (see the module docstring).

    Parameters
    ----------
    settings : ProtocolSettings
    path : str or Path
        The ``.mcap`` file to write.
    model_path : str or Path, optional
        Catheter model file (default: the default model).
    workers : int, optional
        Processes that render and segment the images (default: all CPUs; markers only always
        runs in-process, it is fast).
    progress : bool
        Show a progress bar on stderr.
    """
    from tqdm import tqdm

    model_path = Path(model_path) if model_path is not None else DEFAULT_MODEL_PATH
    catheter = load_catheter(model_path)
    model_text = model_path.read_text(encoding="utf-8")
    scene = _scene(settings, catheter)
    protocol = build_protocol(settings, scene)
    workers = worker_count(workers)
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    recorded_settings = {
        "protocol": PROTOCOL_NAME,
        **settings.to_dict(),
        "noise_unit": settings.noise_unit,
        "model_file": str(model_path),
        "expected_frames": protocol.n_frames,
        "duration_s": protocol.end_ns / 1e9,
        "delta_1_targets_rad": protocol.delta_1_targets_rad.tolist(),
        "delta_L_per_plane_rad": protocol.delta_L_rad.tolist(),
        "lab_conditions_units": LAB_CONDITIONS_UNITS,
        "joint_offset_per_configuration": [
            c.joint_offset.tolist() for c in protocol.configurations
        ],
    }
    jobs = [_Job(settings, model_text, cfg, protocol) for cfg in protocol.configurations]
    unit = "px" if scene.rig.kind == "pinhole" else "mm"
    joint_t_ns = np.arange(0, protocol.end_ns, settings.joint_period_ns, dtype=np.int64)
    q_all, q_dot_all = protocol.joints(joint_t_ns)
    written = 0
    bar = tqdm(
        total=protocol.n_frames,
        desc="simulate",
        unit="frame",
        disable=not progress,
        file=sys.stderr,
        dynamic_ncols=True,
    )
    with RecordingWriter(
        path,
        model_toml=model_text,
        rig_toml=rig_toml(scene.rig, Pose(scene.R_w_b, scene.o_b_w_mm)),
        settings=recorded_settings,
        point_unit=unit,
    ) as writer:
        if settings.images:
            for view, image in zip(scene.rig.names, backgrounds(settings, catheter), strict=True):
                writer.write_background(view, image)
        j = 0
        results = _ordered(jobs, workers if settings.images else 1)
        for frames in results:
            for frame, labels, quality in frames:
                stamp = int(round(frame.time_s * 1e9))
                k = int(np.searchsorted(joint_t_ns, stamp, side="right"))
                if k > j:
                    writer.write_joints(joint_t_ns[j:k] / 1e9, q_all[j:k], q_dot_all[j:k])
                    j = k
                writer.write_frame(frame, labels, quality)
                written += 1
            bar.update(len(frames))
        if j < joint_t_ns.size:
            writer.write_joints(joint_t_ns[j:] / 1e9, q_all[j:], q_dot_all[j:])
    bar.close()
    return SimulationSummary(
        Path(path), written, int(joint_t_ns.size), protocol.end_ns / 1e9, Path(path).stat().st_size
    )
