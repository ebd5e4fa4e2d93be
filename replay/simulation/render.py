"""Synthetic bi-plane images of the catheter and of a checkerboard fiducial.

The renderer turns the kinematic model into the grayscale images a camera (or a bi-plane
C-arm) would record, so the vision front-end (rig calibration, segmentation) can be exercised
end to end without hardware:

- the catheter is a dark tube of the real outer diameters (1.2 mm proximal, 0.89 mm distal;
  docs/design.md section 1) drawn along the backbone and projected through a
  :class:`models.imaging.PinholeView`, with darker radio-opaque marker bands at the base, at
  every marker arclength of the model (frame {2} by default) and at the tip;
- the scene behind it is a static, seeded, textured background; the catheter attenuates it
  (a transmission model: image = background x transmission), then blur and sensor noise;
- checkerboards at known poses, for calibrating the synthetic rig (Zhang's method);
- what real imaging changes between the capture of the background and a frame
  (:class:`ImagingNuisance`): the gain of an automatic exposure or brightness control, drifting
  and flickering from frame to frame, an offset of the dark level, a gamma of the response
  curve, and a shift of the whole image (a vibrating or bumped camera), drawn per view and
  frame (:class:`ImagingChange`) and applied before the sensor noise.

Anti-aliasing is by supersampling: polygons are filled on a canvas ``supersampling`` times
finer and block-averaged, so edges are accurate to a small fraction of a pixel.

Pinhole views come from a rig file (:func:`models.rig_file.load_rig`) or from
:func:`default_render_rig`; :func:`far_view` makes the near-orthographic view of the same
magnification from far away (the paper's orthographic model is its limit).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from models.catheter import Catheter
from models.imaging import PinholeView, Rig, default_pinhole_rig

Array = np.ndarray

DEFAULT_RENDER_DISTANCE_MM = 400.0
DEFAULT_RENDER_FOCAL_PX = 2500.0
"""The default rendering rig: two 640x480 cameras 400 mm from the origin with f = 2500 px,
6.25 px/mm at the catheter, so the 0.89 mm distal tube is about 5.6 px wide. (The model's
:func:`models.imaging.default_pinhole_rig` has f = 1000 px: 2.5 px/mm, a 2.2 px wide tube.)"""


def default_render_rig() -> Rig:
    """The rig the renderer and the vision tests use by default (f = 2500 px at 400 mm)."""
    return default_pinhole_rig(DEFAULT_RENDER_DISTANCE_MM, DEFAULT_RENDER_FOCAL_PX)


def far_view(view: PinholeView, factor: float) -> PinholeView:
    """The same view from ``factor`` times farther with ``factor`` times the focal length.

    The optical axis and the magnification at the world origin are kept, so the images look
    alike while the projection tends to the orthographic one as ``factor`` grows.
    """
    if not factor >= 1.0:
        raise ValueError(f"factor must be >= 1, got {factor}")
    K = np.array(view.K)
    K[0, 0] *= factor
    K[1, 1] *= factor
    t = np.array(view.t_cam_w)
    # Keep the world origin's lateral position on the image: x_cam = R x + t, move along z.
    t_far = np.array([t[0] * factor, t[1] * factor, t[2] * factor])
    return PinholeView(K, view.R_cam_w, t_far, view.dist, view.image_size)


@dataclass(frozen=True)
class RenderSettings:
    """Appearance of the rendered images.

    Parameters
    ----------
    proximal_diameter_mm, distal_diameter_mm : float
        Outer diameters of the two segments (docs/design.md section 1).
    band_length_mm : float
        Length of each radio-opaque marker band. Bands are centred on their arclength and
        clipped to the catheter, so the base band is [0, b] and the tip band [L - b, L].
        Self-overlaps of the tube do not darken it (an opaque tube seen by a camera).
    band_diameter_extra_mm : float
        How much wider than the tube a band is.
    tube_attenuation, band_attenuation : float
        Fraction of the background light blocked by the tube and by a band, in (0, 1).
    blur_sigma_px : float
        Gaussian blur of the optics, px.
    noise_sigma_gray : float
        Additive Gaussian sensor noise, gray levels (8-bit).
    background_mean_gray, background_texture_gray : float
        Mean brightness of the empty scene and the amplitude of its texture, gray levels.
    supersampling : int
        Anti-aliasing factor of the polygon rasteriser.
    samples_per_mm : float
        Backbone points per mm of arclength.
    """

    proximal_diameter_mm: float = 1.2
    distal_diameter_mm: float = 0.89
    band_length_mm: float = 1.0
    band_diameter_extra_mm: float = 0.0
    tube_attenuation: float = 0.4
    band_attenuation: float = 0.8
    blur_sigma_px: float = 0.7
    noise_sigma_gray: float = 2.0
    background_mean_gray: float = 165.0
    background_texture_gray: float = 30.0
    supersampling: int = 4
    samples_per_mm: float = 8.0

    def __post_init__(self) -> None:
        for name in ("proximal_diameter_mm", "distal_diameter_mm", "band_length_mm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        for name in ("tube_attenuation", "band_attenuation"):
            if not 0 < getattr(self, name) < 1:
                raise ValueError(f"{name} must lie in (0, 1), got {getattr(self, name)}")
        for name in ("blur_sigma_px", "noise_sigma_gray", "band_diameter_extra_mm"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if int(self.supersampling) != self.supersampling or self.supersampling < 1:
            raise ValueError(f"supersampling must be a positive integer, got {self.supersampling}")
        lo = self.background_mean_gray - 2.5 * self.background_texture_gray
        hi = self.background_mean_gray + 2.5 * self.background_texture_gray
        if lo < 20 or hi > 250:
            raise ValueError(
                "background_mean_gray +/- 2.5 background_texture_gray must stay within"
                f" [20, 250] gray levels, got [{lo:.0f}, {hi:.0f}]"
            )


# ------------------------------------------------------------------------------ nuisances
@dataclass(frozen=True)
class ImagingChange:
    """What one frame of one view has changed since its background image was captured.

    The camera records ``255 (gain x / 255)^gamma + offset_gray`` of the light x reaching it
    (an exposure or brightness control, a response curve, a dark level), through a shift of
    the whole image by ``shift_px`` (the camera moved); :func:`render_view` then adds the
    sensor noise and quantises.
    """

    gain: float = 1.0
    offset_gray: float = 0.0
    gamma: float = 1.0
    shift_px: tuple[float, float] = (0.0, 0.0)

    def apply(self, image: Array) -> Array:
        """The changed image (float32 gray levels, shape (h, w)) of the scene's light."""
        out = np.asarray(image, np.float32)
        dx, dy = self.shift_px
        if dx or dy:
            move = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]], np.float32)
            out = cv2.warpAffine(out, move, out.shape[::-1], flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REFLECT)
        if self.gamma != 1.0:
            out = 255.0 * (np.maximum(self.gain * out, 0.0) / 255.0) ** self.gamma
        elif self.gain != 1.0:
            out = self.gain * out
        if self.offset_gray:
            out = out + self.offset_gray
        return out.astype(np.float32)

    def points_px(self, uv: Array) -> Array:
        """Where image points (n, 2) of the unchanged camera land in the changed image, px."""
        return np.asarray(uv, float) + np.asarray(self.shift_px, float)


NO_CHANGE = ImagingChange()


@dataclass(frozen=True)
class ImagingNuisance:
    """How frames differ from the background image, drawn per view and frame.

    Parameters
    ----------
    gain_flicker : float
        Each frame's gain varies uniformly within +/- this (0.15: 0.85 to 1.15), on top of...
    gain_drift : float
        ...a slow change of the gain: a mean-reverting random walk of this standard deviation
        (the drift of a lamp or of an automatic brightness control)...
    drift_frames : float
        ...with this correlation time, frames.
    offset_gray : float
        Each frame's offset (dark level) is uniform within +/- this, gray levels.
    gamma_range : float
        Each frame's gamma is uniform within 1 +/- this.
    vibration_px : float
        Standard deviation of each frame's shift of the whole image along each axis, px.
    shift_px : (float, float)
        A fixed shift of the whole image (a camera moved since the background), px.
    """

    gain_flicker: float = 0.0
    gain_drift: float = 0.0
    drift_frames: float = 100.0
    offset_gray: float = 0.0
    gamma_range: float = 0.0
    vibration_px: float = 0.0
    shift_px: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        for name in ("gain_flicker", "gain_drift", "offset_gray", "gamma_range", "vibration_px"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be >= 0, got {value}")
        if not self.gain_flicker + 3.0 * self.gain_drift < 1.0:
            raise ValueError("gain_flicker + 3 gain_drift must stay below 1 (a positive gain)")
        if not 0 <= self.gamma_range < 1:
            raise ValueError(f"gamma_range must lie in [0, 1), got {self.gamma_range}")
        if not self.drift_frames >= 1:
            raise ValueError(f"drift_frames must be >= 1, got {self.drift_frames}")
        if len(self.shift_px) != 2 or not np.all(np.isfinite(self.shift_px)):
            raise ValueError(f"shift_px must be two finite numbers, got {self.shift_px}")
        object.__setattr__(self, "shift_px", tuple(float(v) for v in self.shift_px))

    @property
    def active(self) -> bool:
        return self != ImagingNuisance(drift_frames=self.drift_frames)

    def drift_step(self, drift: float | None, rng: np.random.Generator) -> float:
        """The next value of the gain drift (the first from its stationary distribution)."""
        if not self.gain_drift:
            return 0.0
        if drift is None:
            return float(self.gain_drift * rng.standard_normal())
        rho = float(np.exp(-1.0 / self.drift_frames))
        step = np.sqrt(1.0 - rho**2) * self.gain_drift * rng.standard_normal()
        return float(np.clip(rho * drift + step, -3.0 * self.gain_drift, 3.0 * self.gain_drift))

    def draw(self, drift: float, rng: np.random.Generator) -> ImagingChange:
        """One frame's change, given the current gain drift (only what is set draws numbers)."""
        gain = 1.0 + drift
        if self.gain_flicker:
            gain += rng.uniform(-self.gain_flicker, self.gain_flicker)
        offset = rng.uniform(-self.offset_gray, self.offset_gray) if self.offset_gray else 0.0
        gamma = 1.0 + rng.uniform(-self.gamma_range, self.gamma_range) if self.gamma_range else 1.0
        shift = np.asarray(self.shift_px, float)
        if self.vibration_px:
            shift = shift + self.vibration_px * rng.standard_normal(2)
        return ImagingChange(
            float(gain), float(offset), float(gamma), (float(shift[0]), float(shift[1]))
        )


# ---------------------------------------------------------------------------- background
def render_background(
    image_size: tuple[int, int], seed: int, settings: RenderSettings = RenderSettings()
) -> Array:
    """A static textured scene without the catheter, noise-free, float32 gray levels.

    Smooth random texture at two scales plus a few soft shapes (a stand-in for the anatomy
    or the bench behind the catheter). The same seed gives the same scene.

    Returns
    -------
    background : array, shape (height, width), float32
    """
    width, height = (int(n) for n in image_size)
    rng = np.random.default_rng(seed)
    field = np.zeros((height, width), np.float32)
    for scale_px, weight in ((60.0, 1.0), (12.0, 0.35)):
        noise = rng.standard_normal((height, width)).astype(np.float32)
        smooth = cv2.GaussianBlur(noise, (0, 0), scale_px)
        field += weight * smooth / max(float(smooth.std()), 1e-6)
    shapes = np.zeros((height, width), np.float32)
    for _ in range(6):
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        axes = (int(rng.integers(20, 120)), int(rng.integers(10, 60)))
        angle = float(rng.uniform(0, 180))
        cv2.ellipse(shapes, centre, axes, angle, 0, 360, float(rng.uniform(-1, 1)), -1)
    field += cv2.GaussianBlur(shapes, (0, 0), 6.0)
    field /= max(float(field.std()), 1e-6)
    bg = settings.background_mean_gray + settings.background_texture_gray * field
    return np.clip(bg, 1.0, 254.0).astype(np.float32)


def quantise(image: Array) -> Array:
    """Round and clip to an 8-bit image."""
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------- catheter
def _band_intervals(catheter: Catheter, band_mm: float) -> list[tuple[float, float]]:
    """Arclength intervals of the bands at the base, every marker and the tip, in [0, L]."""
    L = catheter.length_mm
    out = []
    for s in sorted({0.0, L, *catheter.marker_arclengths_mm}):
        lo = min(max(s - band_mm / 2, 0.0), L - band_mm)
        out.append((lo, lo + band_mm))
    return out


def _diameter_mm(s: Array, catheter: Catheter, settings: RenderSettings) -> Array:
    return np.where(
        s <= catheter.proximal.length_mm,
        settings.proximal_diameter_mm,
        settings.distal_diameter_mm,
    )


@dataclass(frozen=True)
class _Strip:
    """A projected tube piece: centreline pixels, radii and foreshortening."""

    uv: Array  # (n, 2), px
    radius_px: Array  # (n,)
    sin_view: Array  # (n,) |sine| of the angle between the tube axis and the image plane


def _project_tube(view: PinholeView, points_w: Array, radius_mm: Array) -> _Strip:
    uv = view.project(points_w)
    x_cam = points_w @ view.R_cam_w.T + view.t_cam_w
    depth_mm = x_cam[:, 2]
    focal = 0.5 * (view.K[0, 0] + view.K[1, 1])
    tangent = np.gradient(x_cam, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    ray = x_cam / np.linalg.norm(x_cam, axis=1, keepdims=True)
    sin_view = np.abs(np.sum(tangent * ray, axis=1))
    return _Strip(uv, np.broadcast_to(radius_mm * focal / depth_mm, depth_mm.shape), sin_view)


_SHIFT = 4  # fractional bits of the vertex coordinates given to OpenCV's rasteriser


def _fill_strip(
    canvas: Array, strip: _Strip, origin: Array, scale: int, ends: tuple[bool, bool] = (True, True)
) -> None:
    """Fill a projected tube on a supersampled canvas with the value 1.

    The tube is the union of its cross-section discs; each projects to an ellipse with
    semi-axes r (across the projected axis) and r |sin| (along it, the foreshortened disc),
    and quads between neighbouring samples fill the sides. OpenCV fills the pixels whose
    centres lie within half a pixel of a polygon, so every outline is pulled in by half a
    canvas pixel, the flat ends too where ``ends`` says they are ends of the tube (not joints
    with the next piece).
    """
    uv = (strip.uv - origin + 0.5) * scale - 0.5
    radius = strip.radius_px * scale - 0.5
    tangent = np.gradient(uv, axis=0)
    norm = np.linalg.norm(tangent, axis=1, keepdims=True)
    tangent = tangent / np.maximum(norm, 1e-12)
    if ends[0]:
        uv[0] += 0.5 * tangent[0]
    if ends[1]:
        uv[-1] -= 0.5 * tangent[-1]
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    left = uv + radius[:, None] * normal
    right = uv - radius[:, None] * normal
    one = 1 << _SHIFT
    quads = np.stack([left[:-1], left[1:], right[1:], right[:-1]], axis=1)
    quads = np.rint(quads * one).astype(np.int32)
    for quad in quads:
        cv2.fillConvexPoly(canvas, quad, 1, cv2.LINE_8, _SHIFT)
    along = np.maximum(strip.radius_px * scale * strip.sin_view - 0.5, 0.0)
    angles = np.degrees(np.arctan2(tangent[:, 1], tangent[:, 0]))
    centres = np.rint(uv * one).astype(np.int64)
    for c, a, r, ang in zip(centres, along, radius, angles, strict=True):
        if a >= 0.5:
            axes = (int(round(a * one)), int(round(r * one)))
            cv2.ellipse(canvas, (int(c[0]), int(c[1])), axes, float(ang), 0, 360, 1, -1,
                        cv2.LINE_8, _SHIFT)


@dataclass(frozen=True)
class CatheterPose:
    """Where the catheter is: joints, torsional loss and the registered base pose."""

    q: Array  # (3,) q_r [rad], q_p [mm], q_d [mm]
    delta_L_rad: float
    R_w_b: Array  # (3, 3)
    o_b_w_mm: Array  # (3,)


def catheter_points_w(
    catheter: Catheter, pose: CatheterPose, arclength_mm: Array
) -> Array:
    """Backbone points at the given arclengths in {W}, mm, shape (n, 3)."""
    points_b = catheter.backbone(pose.q, pose.delta_L_rad, np.asarray(arclength_mm, float))
    return points_b @ np.asarray(pose.R_w_b, float).T + np.asarray(pose.o_b_w_mm, float)


def transmission(
    view: PinholeView,
    catheter: Catheter,
    pose: CatheterPose,
    settings: RenderSettings = RenderSettings(),
) -> tuple[Array, tuple[int, int, int, int]]:
    """Blurred transmission of the catheter in a region of the image.

    Returns
    -------
    T : array, shape (h, w), float32
        Fraction of the background light that reaches each pixel of the region, in (0, 1].
    roi : tuple (x0, y0, w, h)
        The region in the image, px; empty (w or h = 0) when the catheter is out of view.
    """
    L = catheter.length_mm
    n = max(int(np.ceil(L * settings.samples_per_mm)), 8) + 1
    s = np.linspace(0.0, L, n)
    band_mm = settings.band_length_mm
    strips_tube = []
    L1 = catheter.proximal.length_mm
    # Split at L1 so the step in diameter is sharp.
    for lo, hi in ((0.0, L1), (L1, L)):
        ss = np.concatenate([[lo], s[(s > lo) & (s < hi)], [hi]])
        d = _diameter_mm(np.full_like(ss, 0.5 * (lo + hi)), catheter, settings)
        strips_tube.append(_project_tube(view, catheter_points_w(catheter, pose, ss), d / 2))
    strips_band = []
    for lo, hi in _band_intervals(catheter, band_mm):
        m = max(int(np.ceil((hi - lo) * settings.samples_per_mm)), 2) + 1
        ss = np.linspace(lo, hi, m)
        # A band is a ring of one diameter, that of the tube at its centre.
        d = _diameter_mm(np.full_like(ss, 0.5 * (lo + hi)), catheter, settings)
        d = d + settings.band_diameter_extra_mm
        strips_band.append(_project_tube(view, catheter_points_w(catheter, pose, ss), d / 2))
    width, height = view.image_size
    all_uv = np.concatenate([st.uv for st in strips_tube])
    r_max = max(float(st.radius_px.max()) for st in strips_tube + strips_band)
    margin = r_max + 4.0 * settings.blur_sigma_px + 3.0
    x0 = int(max(np.floor(all_uv[:, 0].min() - margin), 0))
    y0 = int(max(np.floor(all_uv[:, 1].min() - margin), 0))
    x1 = int(min(np.ceil(all_uv[:, 0].max() + margin), width))
    y1 = int(min(np.ceil(all_uv[:, 1].max() + margin), height))
    if x1 <= x0 or y1 <= y0:
        return np.ones((0, 0), np.float32), (0, 0, 0, 0)
    S = int(settings.supersampling)
    origin = np.array([x0, y0], float)
    tube = np.zeros(((y1 - y0) * S, (x1 - x0) * S), np.uint8)
    band = np.zeros_like(tube)
    for k, st in enumerate(strips_tube):
        _fill_strip(tube, st, origin, S, ends=(k == 0, k == len(strips_tube) - 1))
    for st in strips_band:
        _fill_strip(band, st, origin, S)
    size = (x1 - x0, y1 - y0)
    cover_tube = cv2.resize(tube.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    cover_band = cv2.resize(band.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    T = (1.0 - settings.tube_attenuation * cover_tube) * (
        1.0 - settings.band_attenuation * cover_band
    ) / (1.0 - settings.tube_attenuation * cover_band)
    if settings.blur_sigma_px > 0:
        T = cv2.GaussianBlur(T, (0, 0), settings.blur_sigma_px, borderType=cv2.BORDER_REPLICATE)
    return T.astype(np.float32), (x0, y0, x1 - x0, y1 - y0)


def render_view(
    view: PinholeView,
    catheter: Catheter,
    pose: CatheterPose | None,
    background: Array,
    rng: np.random.Generator,
    settings: RenderSettings = RenderSettings(),
    occluders: list[tuple[int, int, int, int]] = (),
    change: ImagingChange = NO_CHANGE,
) -> Array:
    """One grayscale 8-bit image of the catheter (or of the empty scene when pose is None).

    Parameters
    ----------
    view : PinholeView
    catheter : Catheter
    pose : CatheterPose or None
    background : array, shape (height, width)
        The empty scene, :func:`render_background`, gray levels.
    rng : numpy Generator
        Draws the sensor noise.
    settings : RenderSettings
    occluders : list of (x, y, w, h)
        Bright rectangles in front of everything (a tool or a hand hiding part of the
        catheter), px.
    change : ImagingChange
        What the camera changes since the background (applied before the sensor noise).

    Returns
    -------
    image : array, shape (height, width), uint8
    """
    width, height = view.image_size
    bg = np.asarray(background, np.float32)
    if bg.shape != (height, width):
        raise ValueError(f"background has shape {bg.shape}, the view is {width}x{height} px")
    dx, dy = change.shift_px
    if dx or dy:
        # A shifted camera images the scene as sharply as an unshifted one: the catheter is
        # drawn through the camera with its principal point moved by the shift (the whole
        # image moved, distortion included), and only the smooth scene behind it is
        # resampled. Resampling the finished image would blur the catheter's edges by up
        # to half a pixel, differently on every frame.
        K = np.array(view.K, float)
        K[0, 2] += dx
        K[1, 2] += dy
        view = PinholeView(K, view.R_cam_w, view.t_cam_w, view.dist, view.image_size)
        image = ImagingChange(shift_px=(dx, dy)).apply(bg)
        change = replace(change, shift_px=(0.0, 0.0))
    else:
        image = bg.copy()
    if pose is not None:
        T, (x0, y0, w, h) = transmission(view, catheter, pose, settings)
        if w and h:
            image[y0 : y0 + h, x0 : x0 + w] *= T
    # Occluders are in the scene: they move with it (by the shift to the nearest pixel).
    ox, oy = round(dx), round(dy)
    for x, y, w, h in occluders:
        x, y = x + ox, y + oy
        image[max(y, 0) : y + h, max(x, 0) : x + w] = 245.0
    if change != NO_CHANGE:
        image = change.apply(image)
    if settings.noise_sigma_gray > 0:
        image += settings.noise_sigma_gray * rng.standard_normal(image.shape).astype(np.float32)
    return quantise(image)


@dataclass(frozen=True)
class RenderedPair:
    """Images of every view (in the rig's order), the empty-scene priors and the true image
    points.

    ``points_px`` are where the points are in the images as rendered: with a shift of the
    whole image (:class:`ImagingChange`), the projection moved by that shift.
    """

    images: tuple[Array, ...]  # uint8 (h, w) each
    backgrounds: tuple[Array, ...]  # uint8 prior images of the empty scene
    base_px: tuple[Array, ...]  # (2,) projected base per view
    points_px: tuple[Array, ...]  # (1 + n_markers, 2): [tip, marker_0, ...] per view
    points_w: Array  # (1 + n_markers, 3) true points in {W}, mm
    changes: tuple[ImagingChange, ...] = ()  # per view: what changed since the background


def true_points_w(catheter: Catheter, pose: CatheterPose) -> Array:
    """True [tip, marker_0, ...] in {W}, mm, in the row order of tracker.pipeline.Frame."""
    s = (catheter.length_mm,) + tuple(catheter.marker_arclengths_mm)
    return catheter_points_w(catheter, pose, np.asarray(s))


class Renderer:
    """Renders frames of one scene: a catheter in front of a fixed rig and background.

    Parameters
    ----------
    catheter : Catheter
    rig : Rig
        Pinhole views (from a rig file or :func:`default_render_rig`).
    R_w_b, o_b_w_mm : arrays (3, 3), (3,)
        Registered pose of the catheter base in {W}.
    settings : RenderSettings
    seed : int
        Seeds the backgrounds (one per view); sensor noise and the nuisances come from the
        generator given to :meth:`render`.
    nuisance : ImagingNuisance
        How each frame differs from the backgrounds (none by default). The gain drift is the
        renderer's only state: it moves on with every :meth:`render`.
    nuisance_seed : int or sequence of int, optional
        Draw the nuisances from a generator of their own, seeded with this, so that a frame's
        sensor noise is the same with and without them; by default they come from the
        generator given to :meth:`render`.
    """

    def __init__(
        self,
        catheter: Catheter,
        rig: Rig,
        R_w_b: Array,
        o_b_w_mm: Array,
        settings: RenderSettings = RenderSettings(),
        seed: int = 0,
        nuisance: ImagingNuisance = ImagingNuisance(),
        nuisance_seed: int | Sequence[int] | None = None,
    ) -> None:
        if rig.kind != "pinhole":
            raise ValueError("the renderer needs pinhole views (use far_view for orthographic)")
        self.catheter = catheter
        self.rig = rig
        self.R_w_b = np.asarray(R_w_b, float)
        self.o_b_w_mm = np.asarray(o_b_w_mm, float)
        self.settings = settings
        self.views = rig.views
        self.background_float = tuple(
            render_background(v.image_size, seed + 7919 * k, settings)
            for k, v in enumerate(self.views)
        )
        self.backgrounds = tuple(quantise(bg) for bg in self.background_float)
        self.nuisance = nuisance
        self._nuisance_rng = None if nuisance_seed is None else np.random.default_rng(nuisance_seed)
        self._drift: list[float | None] = [None] * len(self.views)

    def pose(self, q: Array, delta_L_rad: float) -> CatheterPose:
        return CatheterPose(np.asarray(q, float), float(delta_L_rad), self.R_w_b, self.o_b_w_mm)

    def base_px(self) -> tuple[Array, ...]:
        """The registered base projected into each view, px."""
        return tuple(v.project(self.o_b_w_mm) for v in self.views)

    def render(
        self,
        q: Array,
        delta_L_rad: float,
        rng: np.random.Generator,
        occluders: Sequence[list] | None = None,
    ) -> RenderedPair:
        """Every view's image of the catheter at joints q and torsional loss delta_L.

        ``occluders``: per view, a list of rectangles (:func:`render_view`), or None.
        """
        if occluders is None:
            occluders = ((),) * len(self.views)
        pose = self.pose(q, delta_L_rad)
        points_w = true_points_w(self.catheter, pose)
        images, points_px, changes = [], [], []
        for k, (view, bg, occ) in enumerate(
            zip(self.views, self.background_float, occluders, strict=True)
        ):
            change = NO_CHANGE
            if self.nuisance.active:
                draws = rng if self._nuisance_rng is None else self._nuisance_rng
                self._drift[k] = self.nuisance.drift_step(self._drift[k], draws)
                change = self.nuisance.draw(self._drift[k], draws)
            images.append(
                render_view(view, self.catheter, pose, bg, rng, self.settings, occ, change)
            )
            points_px.append(change.points_px(view.project(points_w)))
            changes.append(change)
        return RenderedPair(
            images=tuple(images),
            backgrounds=self.backgrounds,
            base_px=self.base_px(),
            points_px=tuple(points_px),
            points_w=points_w,
            changes=tuple(changes),
        )


# ---------------------------------------------------------------------------- checkerboard
def board_corners_board(pattern: tuple[int, int], square_mm: float) -> Array:
    """Inner corners of a checkerboard in its own frame, mm, shape (cols * rows, 3).

    OpenCV's order: row by row, ``cols`` corners per row; x along a row, y down the rows,
    z = 0 on the board (z = x cross y points into the board, away from a camera facing it).
    """
    cols, rows = pattern
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2).astype(float)
    return np.column_stack([grid * square_mm, np.zeros(cols * rows)])


def render_checkerboard(
    view: PinholeView,
    R_w_board: Array,
    o_board_w_mm: Array,
    pattern: tuple[int, int],
    square_mm: float,
    rng: np.random.Generator,
    background: Array | None = None,
    settings: RenderSettings = RenderSettings(),
    texture_px_per_square: int = 32,
) -> Array:
    """A checkerboard at a known pose seen by one undistorted view, uint8.

    Parameters
    ----------
    view : PinholeView
        Must be undistorted (a homography maps the board plane to the image).
    R_w_board, o_board_w_mm : arrays (3, 3), (3,)
        Pose of the board frame (see :func:`board_corners_board`) in {W}.
    pattern : (cols, rows)
        Inner corners, e.g. (9, 6).
    square_mm : float
        Side of one square.
    background : array (height, width), optional
        Scene behind the board; a flat gray one if omitted.

    Notes
    -----
    The board has ``cols + 1`` by ``rows + 1`` squares and a white margin of one square. It is
    drawn by warping a texture with the plane-to-image homography on a supersampled canvas.
    """
    if np.any(np.asarray(view.dist) != 0):
        raise ValueError("render_checkerboard needs an undistorted view (dist = 0)")
    cols, rows = (int(n) for n in pattern)
    width, height = view.image_size
    S = int(settings.supersampling)
    n = int(texture_px_per_square)
    # Texture: squares (cols + 1) x (rows + 1) with one square of white margin all round.
    sq = np.indices((rows + 3, cols + 3)).sum(axis=0) % 2 == 0
    sq[0, :] = sq[-1, :] = False
    sq[:, 0] = sq[:, -1] = False
    texture = np.where(sq, 0.12, 0.92).astype(np.float32)
    texture = np.kron(texture, np.ones((n, n), np.float32))
    # Texture pixel (i, j) covers board [(j - 2n)/n, ...] squares: inner corner (0, 0) is at
    # texture coordinate 2n - 0.5 (pixel-centre convention), i.e. board = (u + 0.5)/n - 2.
    offset = square_mm * (0.5 / n - 2.0)
    A = np.array([[square_mm / n, 0.0, offset], [0.0, square_mm / n, offset], [0.0, 0.0, 1.0]])
    R_cam_board = view.R_cam_w @ np.asarray(R_w_board, float)
    t_cam_board = view.R_cam_w @ np.asarray(o_board_w_mm, float) + view.t_cam_w
    H_board = view.K @ np.column_stack([R_cam_board[:, 0], R_cam_board[:, 1], t_cam_board])
    ss = np.array([[S, 0, 0.5 * S - 0.5], [0, S, 0.5 * S - 0.5], [0, 0, 1]])
    H = ss @ H_board @ A
    size = (width * S, height * S)
    # Seen from behind, a board shows its plain back.
    toward_camera = view.center_w - np.asarray(o_board_w_mm, float)
    if toward_camera @ np.asarray(R_w_board, float)[:, 2] > 0:
        texture = np.full_like(texture, 0.5)
    board = cv2.warpPerspective(texture, H, size, flags=cv2.INTER_LINEAR, borderValue=-1.0)
    inside = board >= 0
    board = cv2.resize(np.where(inside, board, 0).astype(np.float32), (width, height),
                       interpolation=cv2.INTER_AREA)
    cover = cv2.resize(inside.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
    bg = np.full((height, width), settings.background_mean_gray, np.float32)
    if background is not None:
        bg = np.asarray(background, np.float32)
    image = (1.0 - cover) * bg + 255.0 * board
    if settings.blur_sigma_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), settings.blur_sigma_px)
    if settings.noise_sigma_gray > 0:
        image = image + settings.noise_sigma_gray * rng.standard_normal(image.shape)
    return quantise(image)


def look_at_board(
    center_w: Array, normal_w: Array, up_w: Array, pattern: tuple[int, int], square_mm: float
) -> tuple[Array, Array]:
    """Pose of a board whose pattern is centred at ``center_w``, facing along ``normal_w``.

    ``normal_w`` points from the board toward the camera that should see it; ``up_w`` is the
    world direction of the board's -y axis (the rows run downward). Returns (R_w_board,
    o_board_w_mm) for :func:`render_checkerboard`.
    """
    n = np.asarray(normal_w, float)
    n = n / np.linalg.norm(n)
    z = -n  # board z points into the board, away from the viewer
    up = np.asarray(up_w, float)
    y = -(up - (up @ z) * z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    R = np.column_stack([x, y, z])
    cols, rows = pattern
    centre_board = np.array([(cols - 1) * square_mm / 2, (rows - 1) * square_mm / 2, 0.0])
    return R, np.asarray(center_w, float) - R @ centre_board
