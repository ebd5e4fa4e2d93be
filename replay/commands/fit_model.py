"""``cathtrack fit-model``: the modal matrices of both segments from measured shapes.

The shapes come from a table (tracker.io.shapes), the fit and its cross-validation from
models.shape_fit; the model file is written by tracker.io.shapes, the figure here.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from models.catheter import Catheter
from models.model_file import DEFAULT_MODEL_PATH, load_catheter
from models.shape_fit import (
    PointShapes,
    ShapeResiduals,
    Shapes,
    cross_validate,
    fit_shapes,
    shape_residuals,
)
from tracker.io.shapes import read_shapes, write_model


def _sizes(values: list[int] | None, option: str) -> tuple[int, int]:
    """One size for both segments or one each."""
    values = [3] if values is None else values
    if len(values) not in (1, 2) or any(v < 1 for v in values):
        raise ValueError(
            f"{option} takes one or two positive sizes (proximal, distal), got {values}"
        )
    return (values[0], values[-1])


def _residual_cells(r: ShapeResiduals | None, name: str) -> str:
    if r is None:
        return f"{'-':>8} {'-':>8}"
    mm = "-" if r.mm is None or not np.isfinite(r.mm[name]) else f"{r.mm[name]:.3f}"
    deg = "-" if not np.isfinite(r.deg[name]) else f"{r.deg[name]:.2f}"
    return f"{mm:>8} {deg:>8}"


def residual_lines(fit: ShapeResiduals, held_out: ShapeResiduals | None, folds: int) -> list[str]:
    """The residual table of ``fit-model``."""
    cv = f"{folds}-fold cross-validated" if held_out is not None else "(no cross-validation)"
    lines = [
        f"{'':10} {'fit':>17}   {cv}",
        f"{'segment':10} {'mm':>8} {'deg':>8}   {'mm':>8} {'deg':>8}",
    ]
    for name in ("proximal", "distal", "overall"):
        lines.append(f"{name:10} {_residual_cells(fit, name)}   {_residual_cells(held_out, name)}")
    return lines


def run(args: argparse.Namespace) -> int:
    template = load_catheter(DEFAULT_MODEL_PATH if args.template is None else args.template)
    psi, eta = _sizes(args.psi_size, "--psi-size"), _sizes(args.eta_size, "--eta-size")
    shapes = read_shapes(args.shapes)
    folds = min(args.folds, shapes.n_shapes)  # at most one configuration per fold
    try:
        fit = fit_shapes(shapes, template, psi, eta)
        held_out = None
        if folds:
            held_out = cross_validate(shapes, template, psi, eta, folds, args.seed)
    except ValueError as exc:
        raise ValueError(f"{args.shapes}: {exc}") from None
    in_sample = shape_residuals(fit.catheter, shapes)
    kind = "backbone points" if isinstance(shapes, PointShapes) else "tangent angles"
    counts = shapes.samples(template.proximal.length_mm)
    print(
        f"cathtrack fit-model: {shapes.n_shapes} configurations from {args.shapes}: {kind},"
        f" {counts[0]} proximal + {counts[1]} distal per shape"
    )
    print(f"bases: proximal psi {psi[0]} x eta {eta[0]}, distal psi {psi[1]} x eta {eta[1]}")
    for line in residual_lines(in_sample, held_out, folds):
        print(line)
    comment = (
        f"cathtrack fit-model: {shapes.n_shapes} configurations of {Path(args.shapes).name}"
        f" ({kind});\nRMS residual {_overall(in_sample)}"
        + (f", {folds}-fold cross-validated {_overall(held_out)}" if held_out else "")
    )
    written = [write_model(args.out, fit.catheter, comment)]
    if not args.no_figure:
        figure = Path(args.figure) if args.figure else Path(args.out).with_suffix(".png")
        written.append(write_fit_figure(figure, fit.catheter, shapes))
    print("wrote " + " and ".join(str(p) for p in written))
    return 0


def _overall(r: ShapeResiduals) -> str:
    mm = "" if r.mm is None else f"{r.mm['overall']:.3f} mm, "
    return f"{mm}{r.deg['overall']:.2f} deg"


def write_fit_figure(path: str | Path, catheter: Catheter, shapes: Shapes, most: int = 9) -> Path:
    """Measured shapes (dots) and the fitted model (lines), for up to ``most`` shapes.

    Point shapes are drawn in each shape's bending plane (distance from the base axis
    against height along it); angle shapes as tangent angle against arclength per segment.
    """
    from matplotlib.figure import Figure

    chosen = np.unique(np.linspace(0, shapes.n_shapes - 1, min(most, shapes.n_shapes)).round())
    chosen = chosen.astype(int)
    figure = Figure(figsize=(10, 4.5), layout="constrained")
    left, right = figure.subplots(1, 2)
    colors = [f"C{k % 10}" for k in range(chosen.size)]
    if isinstance(shapes, PointShapes):
        dense = np.linspace(0.0, catheter.length_mm, 120)
        for color, i in zip(colors, chosen, strict=True):
            q = shapes.q[i]
            c, s = np.cos(q[0]), np.sin(q[0])
            measured = shapes.points_b_mm[i]
            model = catheter.backbone(q, 0.0, dense)
            left.plot(model[:, 0] * c + model[:, 1] * s, model[:, 2], color=color, lw=1)
            left.plot(
                measured[:, 0] * c + measured[:, 1] * s, measured[:, 2], "o", color=color, ms=3
            )
        left.set(xlabel="in the bending plane (mm)", ylabel="along the base axis z_b (mm)")
        left.set_aspect("equal", adjustable="datalim")
        error = np.linalg.norm(
            shapes.points_b_mm - catheter.backbone(shapes.q, 0.0, shapes.arclength_mm), axis=-1
        )
        right.plot(np.broadcast_to(shapes.arclength_mm, error.shape).ravel(), error.ravel(), ".")
        right.axvline(catheter.proximal.length_mm, color="0.6", lw=0.8)
        right.set(xlabel="arclength (mm)", ylabel="|measured - fitted| (mm)")
        left.set_title("measured (dots) and fitted (lines) shapes")
        right.set_title("point residuals (line: end of the proximal segment)")
    else:
        for ax, k, segment in ((left, 0, catheter.proximal), (right, 1, catheter.distal)):
            s = shapes.arclength_mm[k]
            dense = np.linspace(0.0, segment.length_mm, 60)
            for color, i in zip(colors, chosen, strict=True):
                ax.plot(dense, np.degrees(segment.theta(dense, shapes.q[i, 1 + k])), color=color)
                ax.plot(s, np.degrees(shapes.theta_rad[k][i]), "o", color=color, ms=3)
            name = ("proximal", "distal")[k]
            ax.set(xlabel=f"{name} arclength (mm)", ylabel="tangent angle (deg)", title=name)
    figure.suptitle(f"cathtrack fit-model: {chosen.size} of {shapes.n_shapes} configurations")
    path = Path(path)
    try:
        figure.savefig(path, dpi=110)
    except OSError as exc:
        raise OSError(f"cannot write figure {path}: {exc.strerror or exc}") from None
    return path
