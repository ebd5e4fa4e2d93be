"""Estimators of delta_L: per-frame closed forms and baselines, the UKF and the grid filter.

Every estimator has ``step(observation) -> Estimate`` and ``reset()``; :func:`make_estimator`
builds one by name. To add an estimator, write it in a module of this package and add its name
here (docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import replace

from models.catheter import Catheter
from tracker.estimators.checks import CheckedEstimator
from tracker.estimators.grid import DEFAULT_CELLS, GridFilter
from tracker.estimators.per_frame import Estimator, PerFrameEstimator
from tracker.estimators.ukf import BendingPlaneUKF, UKFSettings

PER_FRAME_NAMES = {
    f"{label}{suffix}": (kind, solver)
    for kind, label in PerFrameEstimator.NAMES.items()
    for suffix, solver in (("", "closed-form"), ("-lsq", "least-squares"))
}


def estimator_names() -> list[str]:
    """Every name :func:`make_estimator` accepts."""
    return sorted(PER_FRAME_NAMES) + ["ukf", "ukf-position", "grid"]


def make_estimator(name: str, catheter: Catheter, **settings) -> Estimator:
    """Build an estimator by name (see :func:`estimator_names`), behind the input checks of
    :mod:`tracker.estimators.checks` (a bad observation is a flagged, skipped step).

    The filters take :class:`UKFSettings` fields as keyword settings; ``grid`` also takes
    ``cells`` (default :data:`~tracker.estimators.grid.DEFAULT_CELLS`).
    """
    n_markers = len(catheter.marker_arclengths_mm)
    estimator = _make_estimator(name, catheter, **settings)
    stateful = not isinstance(estimator, PerFrameEstimator)
    return CheckedEstimator(estimator, n_markers, check_time=stateful)


def _make_estimator(name: str, catheter: Catheter, **settings) -> Estimator:
    if name in PER_FRAME_NAMES:
        if settings:
            raise ValueError(f"estimator {name!r} takes no settings, got {sorted(settings)}")
        kind, solver = PER_FRAME_NAMES[name]
        return PerFrameEstimator(catheter, kind, solver)
    if name in ("ukf", "ukf-position"):
        ukf_settings = UKFSettings(**settings)
        if name == "ukf-position":
            ukf_settings = replace(ukf_settings, use_velocity=False)
        return BendingPlaneUKF(catheter, ukf_settings, name=name)
    if name == "grid":
        cells = settings.pop("cells", DEFAULT_CELLS)
        return GridFilter(catheter, UKFSettings(**settings), cells=cells, name=name)
    raise ValueError(f"unknown estimator {name!r}; choose from {', '.join(estimator_names())}")

