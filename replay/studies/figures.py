"""The figures of the sensitivity studies (matplotlib, Agg: no display needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from replay.studies.settings import (
    BOUND_METHOD,
    BOUND_ROWS,
    DEFLECTIONS,
    SensitivitySettings,
    row_order,
)
from replay.studies.tables import SensitivityResult

Array = np.ndarray

METHOD_COLOURS = {
    "tip-position": "tab:blue",
    "body-positions": "tab:orange",
    "tip-velocity": "tab:green",
    "ukf": "tab:red",
    "ukf-position": "tab:purple",
    "tip-position-lsq": "tab:cyan",
    "body-positions-lsq": "tab:brown",
    "tip-velocity-lsq": "tab:olive",
    "crb-all-frames": "tab:red",
}
PLOT_FLOOR_DEG = 1e-2
PLOT_CEILING_DEG = 180.0


def _colour(method: str) -> str:
    return METHOD_COLOURS.get(BOUND_ROWS.get(method, method), "tab:gray")


def _clip(values) -> Array:
    return np.clip(np.asarray(values, dtype=float), PLOT_FLOOR_DEG, PLOT_CEILING_DEG)


def _line_panel(ax, rows: list[dict], x_column: str, order: list[tuple[str, str]]) -> None:
    for method, kind in order:
        mine = sorted((r for r in rows if r["method"] == method), key=lambda r: r[x_column])
        if not mine:
            continue
        x = [r[x_column] for r in mine]
        colour = _colour(method)
        if kind == "bound":
            ax.plot(
                x, _clip([r["median_deg"] for r in mine]), "--", color=colour, lw=1.2, label=method
            )
            continue
        ax.plot(
            x,
            _clip([r["median_deg"] for r in mine]),
            "-o",
            color=colour,
            ms=3,
            lw=1.6,
            label=method,
        )
        ax.fill_between(
            x,
            _clip([r["p25_deg"] for r in mine]),
            _clip([r["p75_deg"] for r in mine]),
            color=colour,
            alpha=0.15,
            lw=0,
        )
        # An estimator that gave no estimate in some trials (the UKF's gate refusing data the
        # model cannot explain): say how often it answered, at the bottom of the panel.
        for r in mine:
            if r["valid_fraction"] < 0.995:
                ax.annotate(
                    f"{100 * r['valid_fraction']:.0f}%",
                    (r[x_column], 1.6 * PLOT_FLOOR_DEG),
                    color=colour,
                    fontsize=6.5,
                    ha="center",
                )
    ax.set_yscale("log")
    ax.set_ylim(PLOT_FLOOR_DEG, 2 * PLOT_CEILING_DEG)
    ax.grid(True, which="major", alpha=0.3)


def _legend(fig, axes) -> None:
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right upper", fontsize=7.5, frameon=False)


def _figure(n_rows: int, n_cols: int, width: float, height: float):
    fig = Figure(figsize=(width * n_cols, height * n_rows), layout="constrained")
    axes = fig.subplots(n_rows, n_cols, squeeze=False, sharey=True)
    return fig, axes


def _footnote(s: SensitivitySettings, noise: str) -> str:
    return (
        f"{noise}; median |error| with 25-75% band; dashed: Cramer-Rao bound as the median"
        f" |error| of an efficient estimator (clipped at {PLOT_CEILING_DEG:g} deg); n%: share"
        f" of trials with an estimate; {s.trials} trials per point ({s.effective_ukf_trials}"
        f" for the UKF); {s.view} views; seed {s.seed}"
    )


def figure_study_a(result: SensitivityResult):
    s = result.settings
    rows = result.rows["a"]
    order = row_order(s)
    fig, axes = _figure(1, len(s.delta_2_deg), 4.6, 3.6)
    for ax, delta_2 in zip(axes[0], s.delta_2_deg, strict=True):
        _line_panel(ax, [r for r in rows if r["delta_2_deg"] == delta_2], "noise_mm", order)
        ax.set_title(
            f"delta_2 = {delta_2:g} deg, theta_L = {s.configuration_theta_L_deg[0]:g},"
            f" {s.configuration_theta_L_deg[1]:g} deg",
            fontsize=9,
        )
        ax.set_xlabel("segmentation noise sigma (mm)")
    axes[0, 0].set_ylabel("bending-plane error |delta_L| (deg)")
    _legend(fig, axes)
    fig.suptitle("(a) error against segmentation noise", fontsize=11)
    _add_footnote(fig, _footnote(s, "noise per image axis in both views"))
    return fig


def _add_footnote(fig, text: str) -> None:
    """The small print under a figure: settings, units and what the lines mean."""
    fig.text(0.01, -0.02, text, fontsize=6.5, ha="left", va="top", wrap=True)


def figure_study_c(result: SensitivityResult):
    s = result.settings
    rows = result.rows["c"]
    order = row_order(s)
    variants = [v for v in DEFLECTIONS if v in s.deflections]
    fig, axes = _figure(len(variants), len(s.delta_2_deg), 4.6, 3.3)
    for i, variant in enumerate(variants):
        for ax, delta_2 in zip(axes[i], s.delta_2_deg, strict=True):
            _line_panel(
                ax,
                [r for r in rows if r["delta_2_deg"] == delta_2 and r["variant"] == variant],
                "deflection_mm",
                order,
            )
            how = "joints offset" if variant == "in-plane" else "normal to the plane"
            ax.set_title(f"{variant} ({how}), delta_2 = {delta_2:g} deg", fontsize=8.5)
            ax.set_xlabel("tip deflection (mm)")
        axes[i, 0].set_ylabel("error |delta_L| (deg)")
    _legend(fig, axes)
    fig.suptitle("(c) error against tip deflection by contact", fontsize=11)
    _add_footnote(
        fig,
        _footnote(
            s,
            f"noise {s.noise_mm:g} mm; in-plane: the catheter bends as if {s.deflection_joint}"
            " were larger than the model sees (the paper's experiment); out-of-plane: the tip is"
            " pushed normal to the bending plane (cantilever profile)",
        ),
    )
    return fig


def figure_study_b(result: SensitivityResult):
    s = result.settings
    rows = result.rows["b"]
    panels = [m for m, kind in row_order(s) if kind == "estimator"]
    panels += [m for m in ("crb-body", "crb-all-frames") if BOUND_METHOD in s.methods]
    fig, axes = _figure(len(s.delta_2_deg), len(panels), 2.5, 2.45)
    norm = LogNorm(vmin=0.1, vmax=PLOT_CEILING_DEG)
    t1, t2 = sorted(set(s.theta_L1_deg)), sorted(set(s.theta_L2_deg))
    image = None
    for i, delta_2 in enumerate(s.delta_2_deg):
        for ax, method in zip(axes[i], panels, strict=True):
            grid = np.full((len(t2), len(t1)), np.nan)
            for r in rows:
                if r["delta_2_deg"] == delta_2 and r["method"] == method:
                    grid[t2.index(r["theta_L2_deg"]), t1.index(r["theta_L1_deg"])] = r["median_deg"]
            image = ax.imshow(
                np.clip(grid, 0.1, PLOT_CEILING_DEG),
                origin="lower",
                norm=norm,
                cmap="viridis",
                extent=_extent(t1, t2),
                aspect="auto",
                interpolation="nearest",
            )
            ax.plot([90], [90], "w+", ms=6)
            ax.set_title(f"{method}\ndelta_2 = {delta_2:g} deg", fontsize=8)
            ax.tick_params(labelsize=7)
            if i == len(s.delta_2_deg) - 1:
                ax.set_xlabel("theta_L1 (deg)", fontsize=8)
        axes[i, 0].set_ylabel("theta_L2 (deg)", fontsize=8)
    if image is not None:
        bar = fig.colorbar(image, ax=axes, shrink=0.8)
        bar.set_label("median |error| (deg); bounds: of an efficient estimator", fontsize=8)
    fig.suptitle(
        f"(b) error over the workspace (+ = straight), noise {s.noise_mm:g} mm, {s.trials} trials"
        f" per point ({s.effective_ukf_trials} for the UKF), {s.view} views, seed {s.seed}",
        fontsize=10,
    )
    return fig


def _extent(x: list[float], y: list[float]) -> list[float]:
    def edges(v: list[float]) -> tuple[float, float]:
        step = (v[-1] - v[0]) / (len(v) - 1) if len(v) > 1 else 1.0
        return v[0] - step / 2, v[-1] + step / 2

    return [*edges(x), *edges(y)]


FIGURES = {"a": figure_study_a, "b": figure_study_b, "c": figure_study_c}


def write_figures(result: SensitivityResult, out_dir: Path, dpi: int = 110) -> list[Path]:
    """One PNG per study (Agg, no display needed)."""
    paths = []
    for study in result.rows:
        path = Path(out_dir) / f"study_{study}.png"
        FIGURES[study](result).savefig(path, dpi=dpi, bbox_inches="tight")
        paths.append(path)
    return paths
