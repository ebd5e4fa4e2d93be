"""Fitting both segments to whole-catheter shapes: exact recovery, scoring, identifiability."""

from __future__ import annotations

import numpy as np
import pytest

from models.catheter import default_catheter
from models.shape_fit import (
    AngleShapes,
    PointShapes,
    cross_validate,
    fit_shapes,
    fold_indices,
    shape_residuals,
)

GRID = np.linspace(-1.0, 1.0, 5)


def grid_joints(rng):
    q_p, q_d = (g.ravel() for g in np.meshgrid(GRID, GRID))
    return np.column_stack([rng.uniform(-np.pi, np.pi, q_p.size), q_p, q_d])


def point_shapes(catheter, rng, noise_mm=0.0):
    q = grid_joints(rng)
    s = np.concatenate([np.linspace(2.6, 13.0, 5), 13.0 + np.linspace(3.2, 16.0, 5)])
    points = catheter.backbone(q, 0.0, s)
    return PointShapes(q, s, points + noise_mm * rng.standard_normal(points.shape))


@pytest.mark.parametrize("delta_2", [0.0, np.pi / 2])
def test_noise_free_points_give_both_matrices_exactly(delta_2):
    truth = default_catheter(delta_2_rad=delta_2)
    shapes = point_shapes(truth, np.random.default_rng(0))
    fit = fit_shapes(shapes, truth)
    np.testing.assert_allclose(fit.catheter.proximal.A, truth.proximal.A, atol=1e-7)
    np.testing.assert_allclose(fit.catheter.distal.A, truth.distal.A, atol=1e-7)
    residuals = shape_residuals(fit.catheter, shapes)
    assert residuals.mm["overall"] < 1e-8 and residuals.deg["overall"] < 1e-6


def test_noise_free_angles_give_both_matrices_exactly():
    truth = default_catheter()
    q = grid_joints(np.random.default_rng(1))
    s = (np.linspace(0.0, 13.0, 6), np.linspace(0.0, 16.0, 7))
    theta = tuple(
        seg.theta(s_k[None, :], q[:, 1 + k, None])
        for k, (seg, s_k) in enumerate(zip((truth.proximal, truth.distal), s, strict=True))
    )
    shapes = AngleShapes(q, s, theta)
    fit = fit_shapes(shapes, truth)
    np.testing.assert_allclose(fit.catheter.proximal.A, truth.proximal.A, atol=1e-9)
    np.testing.assert_allclose(fit.catheter.distal.A, truth.distal.A, atol=1e-9)
    assert shape_residuals(fit.catheter, shapes).mm is None


def test_cross_validated_residual_estimates_the_noise():
    """With the right bases the held-out residual is the noise (sqrt(3) x 0.1 mm per point)."""
    truth = default_catheter()
    shapes = point_shapes(truth, np.random.default_rng(2), noise_mm=0.1)
    held_out = cross_validate(shapes, truth, folds=5)
    in_sample = shape_residuals(fit_shapes(shapes, truth).catheter, shapes)
    assert in_sample.mm["overall"] <= held_out.mm["overall"]
    assert held_out.mm["overall"] == pytest.approx(0.1 * np.sqrt(3), rel=0.15)


def test_too_few_configurations_or_arclengths_are_one_line_errors():
    truth = default_catheter()
    shapes = point_shapes(truth, np.random.default_rng(3))
    few = shapes.subset(np.flatnonzero(np.isin(shapes.q[:, 1], GRID[:2])))
    with pytest.raises(ValueError, match="2 distinct q_p value.* proximal joint basis of size 3"):
        fit_shapes(few, truth)
    with pytest.raises(ValueError, match="arclength basis of size 6"):
        fit_shapes(shapes, truth, psi_sizes=(6, 3))
    diagonal = shapes.subset(np.flatnonzero(shapes.q[:, 1] == shapes.q[:, 2]))  # 5 shapes
    fit_shapes(diagonal, truth)
    with pytest.raises(ValueError, match="cross-validation fold 1 of 2 .* 2 distinct q_p"):
        cross_validate(diagonal, truth, folds=2)
    with pytest.raises(ValueError, match="2 to 25 folds"):
        fold_indices(25, 26)
