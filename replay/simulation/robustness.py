"""Segmentation under what imaging changes between frames: the table of docs/vision.md.

Rendered pairs of bent configurations (:class:`replay.simulation.render.Renderer`) go through
a :class:`tracker.vision.pair.PairSegmenter` as one sequence of frames, once per condition:
no change, each nuisance of :class:`replay.simulation.render.ImagingNuisance` alone (a gain
changing from frame to frame, an offset, sensor noise, a gamma) and all of them together.
Per condition, over the views where the tip is visible: how often the tip is found and how
far from the truth it lands, px. ``benchmarks/segmentation_robustness.py`` writes the table,
``tests/tracker/test_segmentation.py`` checks it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.catheter import Catheter, default_catheter
from models.imaging import PinholeView
from replay.simulation.render import (
    CatheterPose,
    ImagingNuisance,
    Renderer,
    RenderSettings,
    catheter_points_w,
    default_render_rig,
)
from tracker.vision.pair import PairSegmenter
from tracker.vision.settings import DEFAULT_SETTINGS, SegmentationSettings

Array = np.ndarray

BASE_W = np.array([0.0, 0.0, -15.0])


@dataclass(frozen=True)
class Condition:
    """One row of the table: the nuisance and the sensor noise of every frame."""

    key: str
    name: str
    nuisance: ImagingNuisance = ImagingNuisance()
    noise_sigma_gray: float = RenderSettings().noise_sigma_gray


CONDITIONS = (
    Condition("none", "none"),
    Condition("gain", "gain 0.85-1.15, each frame", ImagingNuisance(gain_flicker=0.15)),
    Condition(
        "offset", "offset +/-15 gray levels, each frame", ImagingNuisance(offset_gray=15.0)
    ),
    Condition("noise", "sensor noise 8 gray levels", noise_sigma_gray=8.0),
    Condition("gamma", "gamma 0.9-1.1, each frame", ImagingNuisance(gamma_range=0.1)),
    Condition(
        "all",
        "all of them",
        ImagingNuisance(gain_flicker=0.15, offset_gray=15.0, gamma_range=0.1),
        noise_sigma_gray=8.0,
    ),
)


@dataclass(frozen=True)
class ConditionResult:
    """Tips of one condition over the views where the tip is visible.

    Attributes
    ----------
    condition : Condition
    visible, found : int
        Views where the tip is visible, and where the segmentation gave it.
    errors_px : array (found,)
        Distance of each tip found from the truth, px.
    """

    condition: Condition
    visible: int
    found: int
    errors_px: Array

    @property
    def found_fraction(self) -> float:
        return self.found / max(self.visible, 1)

    @property
    def median_px(self) -> float:
        return float(np.median(self.errors_px)) if self.errors_px.size else float("nan")

    @property
    def p95_px(self) -> float:
        return float(np.percentile(self.errors_px, 95)) if self.errors_px.size else float("nan")

    @property
    def max_px(self) -> float:
        return float(self.errors_px.max()) if self.errors_px.size else float("nan")


def bent_configurations(n: int, seed: int) -> tuple[Array, Array]:
    """Joints (n, 3) and torsional losses (n,) of bent catheters (|q_p| >= 0.4 mm)."""
    rng = np.random.default_rng(seed)
    q_p = rng.uniform(0.4, 1.0, n) * rng.choice([-1.0, 1.0], n)
    q = np.column_stack([rng.uniform(-np.pi, np.pi, n), q_p, rng.uniform(-1.0, 1.0, n)])
    return q, rng.uniform(-np.pi, np.pi, n)


def tip_visible(
    view: PinholeView,
    catheter: Catheter,
    pose: CatheterPose,
    margin_px: float = 12.0,
    clearance_px: float = 4.0,
) -> bool:
    """The tip lies inside the image and the catheter's image stays clear of itself.

    Parts of the backbone more than 5 mm apart along the catheter must stay a proximal tube
    diameter plus ``clearance_px`` apart in the image: otherwise the segmentation withholds
    the view by design (``SegmentationFlag.OVERLAP``).
    """
    s = np.linspace(0.0, catheter.length_mm, 59)
    uv = view.project(catheter_points_w(catheter, pose, s))
    width, height = view.image_size
    tip = uv[-1]
    if not (margin_px <= tip[0] <= width - 1 - margin_px
            and margin_px <= tip[1] <= height - 1 - margin_px):
        return False
    px_per_mm = float(view.K[0, 0] / np.linalg.norm(view.t_cam_w))
    apart = np.abs(s[:, None] - s[None, :]) > 5.0
    distance = np.linalg.norm(uv[:, None, :] - uv[None, :, :], axis=-1)
    return not np.any(distance[apart] < 1.2 * px_per_mm + clearance_px)


def run_condition(
    condition: Condition,
    n_configurations: int = 40,
    seed: int = 0,
    catheter: Catheter | None = None,
    settings: SegmentationSettings = DEFAULT_SETTINGS,
) -> ConditionResult:
    """Render and segment ``n_configurations`` pairs under one condition, as one sequence.

    The same seed gives the same configurations and scene in every condition; each condition
    draws its own nuisances and noise from ``default_rng([seed, 1])``.
    """
    catheter = default_catheter() if catheter is None else catheter
    rig = default_render_rig()
    render_settings = RenderSettings(noise_sigma_gray=condition.noise_sigma_gray)
    renderer = Renderer(
        catheter, rig, np.eye(3), BASE_W, render_settings, seed=seed, nuisance=condition.nuisance
    )
    segmenter = PairSegmenter(catheter, rig, np.eye(3), BASE_W, renderer.backgrounds, settings)
    q, delta_L = bent_configurations(n_configurations, seed)
    rng = np.random.default_rng([seed, 1])
    visible = found = 0
    errors = []
    for qi, di in zip(q, delta_L, strict=True):
        pair = renderer.render(qi, di, rng)
        result = segmenter.segment(pair.images)
        pose = renderer.pose(qi, di)
        for k, (view, uv) in enumerate(zip(renderer.views, result.uv, strict=True)):
            if not tip_visible(view, catheter, pose):
                continue
            visible += 1
            if np.all(np.isfinite(uv[0])):
                found += 1
                errors.append(float(np.linalg.norm(uv[0] - pair.points_px[k][0])))
    return ConditionResult(condition, visible, found, np.asarray(errors))


def run_conditions(
    conditions: Sequence[Condition] = CONDITIONS,
    n_configurations: int = 40,
    seed: int = 0,
    settings: SegmentationSettings = DEFAULT_SETTINGS,
) -> list[ConditionResult]:
    return [run_condition(c, n_configurations, seed, settings=settings) for c in conditions]


def markdown_table(results: Sequence[ConditionResult]) -> str:
    """The results as the markdown table of docs/vision.md."""
    lines = [
        "| change of the frames | tip found (views where visible) | median / p95 / max tip error |",
        "|---|---:|---:|",
    ]
    for r in results:
        errors = (
            f"{r.median_px:.2f} / {r.p95_px:.2f} / {r.max_px:.2f} px" if r.errors_px.size else "-"
        )
        lines.append(
            f"| {r.condition.name} | {r.found}/{r.visible} ({100 * r.found_fraction:.0f} %)"
            f" | {errors} |"
        )
    return "\n".join(lines) + "\n"

