"""Run estimators over a sequence of frames and summarise their accuracy against the truth."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from models.catheter import Catheter
from models.rotations import wrap_angle
from tracker.estimators import make_estimator
from tracker.observation import Estimate, Flag, Observation
from tracker.pipeline import Frame, Reconstructor

Array = np.ndarray


@dataclass(frozen=True)
class MethodResult:
    """One estimator's estimates over a session and their errors against the truth."""

    name: str
    estimates: tuple[Estimate, ...]
    truth_rad: Array  # (T,)

    @property
    def valid(self) -> Array:
        return np.array([e.valid for e in self.estimates], dtype=bool)

    @property
    def errors_rad(self) -> Array:
        """Wrapped estimate - truth for valid frames (NaN elsewhere), rad."""
        est = np.array([e.delta_L_rad for e in self.estimates])
        return np.where(self.valid, wrap_angle(np.nan_to_num(est) - self.truth_rad), np.nan)

    @property
    def std_rad(self) -> Array:
        return np.array([e.std_rad for e in self.estimates])

    def summary(self) -> dict[str, float]:
        """RMS, median absolute and maximum error in degrees; valid fraction; 2-sigma coverage."""
        err = self.errors_rad[self.valid]
        if err.size == 0:
            return {
                "rms_deg": np.inf,
                "median_deg": np.inf,
                "max_deg": np.inf,
                "valid": 0.0,
                "coverage_2sigma": 0.0,
                "rejected": 0,
            }
        std = self.std_rad[self.valid]
        return {
            "rms_deg": float(np.degrees(np.sqrt(np.mean(err**2)))),
            "median_deg": float(np.degrees(np.median(np.abs(err)))),
            "max_deg": float(np.degrees(np.max(np.abs(err)))),
            "valid": float(np.mean(self.valid)),
            "coverage_2sigma": float(np.mean(np.abs(err) <= 2 * std)),
            "rejected": int(sum(Flag.OUTLIER_REJECTED in e.flags for e in self.estimates)),
        }


def observations_from_frames(reconstructor: Reconstructor, frames: Sequence[Frame]) -> list:
    reconstructor.reset()
    return [reconstructor.observe(frame) for frame in frames]


def run_methods(
    catheter: Catheter,
    observations: Sequence[Observation],
    truth_rad: Array,
    names: Sequence[str],
) -> dict[str, MethodResult]:
    """Run every named estimator over the same observations."""
    results = {}
    for name in names:
        estimator = make_estimator(name, catheter)
        estimates = tuple(estimator.step(obs) for obs in observations)
        results[name] = MethodResult(name, estimates, np.asarray(truth_rad, dtype=float))
    return results


def markdown_table(results: dict[str, MethodResult], bound_rms_deg: float | None = None) -> str:
    """A markdown table of every method's accuracy, degrees."""
    lines = [
        "| method | RMS error (deg) | median abs (deg) | max abs (deg) | valid frames | "
        "within 2 sigma |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, result in results.items():
        s = result.summary()
        lines.append(
            f"| {name} | {s['rms_deg']:.2f} | {s['median_deg']:.2f} | {s['max_deg']:.2f} | "
            f"{100 * s['valid']:.0f}% | {100 * s['coverage_2sigma']:.0f}% |"
        )
    if bound_rms_deg is not None:
        lines.append(f"| Cramer-Rao bound, tip, per frame | {bound_rms_deg:.2f} | | | | |")
    return "\n".join(lines)
