"""Accuracy tables of a replay: statistics per group of frames, the paper's checks, markdown.

Every table is a list of rows (long format, degrees): ``overall``, per bending ``plane``,
against tip ``deflection``, against segmentation ``noise``, per ``configuration``, the
``consistency`` of the filters' uncertainty, and ``robustness``: per method, whether its
uncertainty can be trusted (:func:`replay.robustness.robustness_metrics`: 2-sigma coverage,
mean NEES, and the frames and configurations where it is confidently wrong, an error above
30 degrees with a std below 10). Each row is one method (or the bound, :data:`BOUND_NAME`)
over one group of the scored frames.

Groups. A label with at most :data:`LEVELS_MAX` distinct values over the scored frames (the
protocol's planes and configurations, its three noise and deflection levels) gets one group per
value. A continuous label -- a measured tip deflection or noise with its own value in every
frame -- gets one group per range instead, so that a table has a few rows whatever the number
of frames:

- deflection, mm: below 0.5, 0.5 to 1, 1 to 2, 2 to 4, 4 to 8, 8 and above
  (:data:`DEFLECTION_BIN_EDGES_MM`);
- noise, in the recording's noise unit (settings ``noise_unit``: mm, px or gray): below 0.25,
  then octaves 0.25 to 0.5, ..., 4 to 8, and 8 and above (:data:`NOISE_BIN_EDGES`).

A binned group is named by its range (``"1 to 2"``, ``"< 0.5"``, ``">= 8"``) and its rows carry
``group_median``, the median label value of its frames. Each method's per-frame arrays are made
once (:class:`~replay.evaluation.run.MethodResult`); a table sorts the frames by group once and
indexes those arrays per group, so its cost grows linearly with the frames (up to the sort).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from replay.evaluation.run import MethodResult, Replay
from replay.robustness import CONFIDENT_DEG, WRONG_DEG, robustness_metrics

Array = np.ndarray

BOUND_NAME = "crb-tip"
"""Name of the per-frame Cramer-Rao bound of the tip in the tables."""
TABLES = (
    "overall",
    "plane",
    "deflection",
    "noise",
    "configuration",
    "consistency",
    "robustness",
)

LEVELS_MAX = 8
"""A label with at most this many distinct values is grouped by value; one with more is a
continuous label, grouped by the ranges of its bin edges (where it has them)."""
DEFLECTION_BIN_EDGES_MM = (0.5, 1.0, 2.0, 4.0, 8.0)
"""Bin edges of a continuous tip deflection, mm: ranges ``[edge_k, edge_k+1)``, the first open
below (no deflection to the size of the segmentation noise) and the last open above."""
NOISE_BIN_EDGES = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
"""Bin edges of a continuous noise level, in the recording's noise unit (mm, px or gray): octaves,
which suit every unit since the errors grow roughly in proportion to the noise."""


def bin_names(edges: Sequence[float]) -> list[str]:
    """Names of the ranges that ``edges`` cut the real line into: ``< e0``, ``e0 to e1``, ...,
    ``>= e_last``."""
    inner = [f"{low:g} to {high:g}" for low, high in zip(edges[:-1], edges[1:], strict=True)]
    return [f"< {edges[0]:g}", *inner, f">= {edges[-1]:g}"]


@dataclass(frozen=True)
class Group:
    """Frames of one group.

    Parameters
    ----------
    key : int, float or str
        The label value, or the name of its range (:func:`bin_names`), or ``"all"``.
    frames : array of int
        Indices of the group's frames, in frame order.
    median : float
        Median label value over those frames (NaN for ``"all"``).
    """

    key: object
    frames: Array
    median: float = math.nan


def group_frames(
    values: Sequence, include: Array, bin_edges: Sequence[float] | None = None
) -> list[Group]:
    """Split the included frames with a label into groups, in sorted order.

    Parameters
    ----------
    values : sequence, length F
        The label of every frame: a number, or None where unknown.
    include : array of bool, shape (F,)
        Frames that may be grouped (the scored ones).
    bin_edges : sequence of float, optional
        Bin edges for a continuous label (more than :data:`LEVELS_MAX` distinct values);
        without them every distinct value is its own group.
    """
    present_values = [v for v in values if v is not None]
    integral = all(isinstance(v, int | np.integer) for v in present_values)
    x = np.array([np.nan if v is None else v for v in values], dtype=float)
    present = np.asarray(include, dtype=bool) & np.isfinite(x)
    levels = np.unique(x[present])
    if bin_edges is None or levels.size <= LEVELS_MAX:
        codes = np.searchsorted(levels, x)
        keys: list = [int(v) if integral else float(v) for v in levels]
    else:
        codes = np.searchsorted(np.asarray(bin_edges, dtype=float), x, side="right")
        keys = bin_names(bin_edges)
    codes = np.where(present, codes, len(keys))  # frames without a group sort last
    order = np.argsort(codes, kind="stable")
    ends = np.cumsum(np.bincount(codes, minlength=len(keys) + 1))
    groups = []
    for k, key in enumerate(keys):
        frames = order[(ends[k - 1] if k else 0) : ends[k]]
        if frames.size:
            groups.append(Group(key, frames, float(np.median(x[frames]))))
    return groups


def _stats(errors_rad: Array, valid: Array, std_rad: Array, known: Array) -> dict:
    """One method over a group of frames: the share of frames with an estimate, and the RMS,
    max and median |error| (degrees) and 2-sigma coverage over those that also have a truth."""
    n = int(valid.size)
    scored = valid & known & np.isfinite(errors_rad)
    err = errors_rad[scored]
    row = {
        "frames": n,
        "with_truth": int(np.count_nonzero(known)),
        "valid": float(np.count_nonzero(valid) / n) if n else 0.0,
    }
    if err.size == 0:
        row.update(rms_deg=math.nan, max_deg=math.nan, median_deg=math.nan)
    else:
        deg = np.degrees(np.abs(err))
        row.update(
            rms_deg=float(np.sqrt(np.mean(deg**2))),
            max_deg=float(deg.max()),
            median_deg=float(np.median(deg)),
        )
    ok = scored & np.isfinite(std_rad)
    row["within_2sigma"] = (
        float(np.mean(np.abs(errors_rad[ok]) <= 2 * std_rad[ok])) if ok.any() else math.nan
    )
    return row


def _bound_stats(bound_rad: Array) -> dict:
    b = bound_rad[~np.isnan(bound_rad)]
    b = np.minimum(b, np.pi)  # an uninformative frame can be no worse than a half turn
    n = int(bound_rad.size)
    if b.size == 0:
        return {
            "frames": n,
            "valid": 0.0,
            "rms_deg": math.nan,
            "max_deg": math.nan,
            "median_deg": math.nan,
        }
    deg = np.degrees(b)
    return {
        "frames": n,
        "valid": float(b.size / n) if n else 0.0,
        "rms_deg": float(np.sqrt(np.mean(deg**2))),
        "max_deg": float(deg.max()),
        "median_deg": float(np.median(deg)),
    }


def replay_tables(replay: Replay) -> dict[str, list[dict]]:
    """Every table as rows (long format, degrees): overall, per plane, deflection, noise,
    configuration, and the UKF consistency (see the module notes for the groups)."""
    truth = replay.truth_rad
    known = np.isfinite(truth)
    scored = replay.scored
    groupings = {
        "overall": [Group("all", np.flatnonzero(scored))],
        "plane": group_frames(replay.label("plane"), scored),
        "deflection": group_frames(replay.label("deflection_mm"), scored, DEFLECTION_BIN_EDGES_MM),
        "noise": group_frames(replay.label("noise_level"), scored, NOISE_BIN_EDGES),
        "configuration": group_frames(replay.label("configuration"), scored),
    }
    tables: dict[str, list[dict]] = {name: [] for name in TABLES}
    for table, groups in groupings.items():
        for group in groups:
            idx = group.frames
            extra: dict[str, object] = {}
            if table != "overall":
                extra["group_median"] = group.median
            if table == "noise":
                sigma = replay.sigma_image[idx]
                extra["sigma_image"] = (
                    float(np.nanmedian(sigma)) if np.isfinite(sigma).any() else math.nan
                )
            if table == "plane":
                delta_L = truth[idx][known[idx]]
                extra["delta_L_true_deg"] = (
                    float(np.degrees(delta_L[0])) if delta_L.size else math.nan
                )
                targets = replay.settings.get("delta_1_targets_rad")
                value = group.key
                if (
                    isinstance(targets, list)
                    and isinstance(value, int)
                    and 0 <= value < len(targets)
                ):
                    extra["delta_1_target_deg"] = float(np.degrees(targets[value]))
            head = {"table": table, "group": group.key}
            for name, result in replay.results.items():
                row = _stats(
                    result.errors_rad[idx], result.valid[idx], result.std_rad[idx], known[idx]
                )
                tables[table].append({**head, "method": name, **extra, **row})
            tables[table].append(
                {**head, "method": BOUND_NAME, **extra, **_bound_stats(replay.bound_rad[idx])}
            )
    for result in replay.results.values():
        if result.reports_nis:
            tables["consistency"].append(_consistency(result, known, scored))
    if known.any():
        configuration = replay.label("configuration")
        labelled = any(c is not None for c in configuration)
        for result in replay.results.values():
            tables["robustness"].append(
                _robustness(result, configuration if labelled else None, scored)
            )
    return tables


def _robustness(result: MethodResult, configuration: Array | None, scored: Array) -> dict:
    """One method's row of the robustness table over the scored frames."""
    m = robustness_metrics(result.name, result.errors_rad, result.std_rad, configuration, scored)
    return {
        "table": "robustness",
        "group": "all",
        "method": result.name,
        "frames": m.frames,
        "valid": m.valid,
        "rms_deg": m.rms_deg,
        "max_deg": m.max_deg,
        "within_2sigma": m.coverage_2sigma,
        "mean_nees": m.mean_nees,
        "confidently_wrong_frames": m.confidently_wrong_frames,
        "confidently_wrong_configurations": m.confidently_wrong_configurations,
    }


def _consistency(result: MethodResult, known: Array, scored: Array) -> dict:
    """NEES of a filter against its chi-square band and its 2-sigma coverage over the scored
    frames with a truth; its NIS per degree of freedom over the scored frames."""
    ok = result.valid & known & scored & (result.std_rad > 0)
    err, std = result.errors_rad[ok], result.std_rad[ok]
    n = int(err.size)
    nees = (err / std) ** 2
    steps = scored & np.isfinite(result.nis)
    nis, dof = result.nis[steps], result.nis_dof[steps].astype(float)
    low, high = (chi2.ppf(0.025, n) / n, chi2.ppf(0.975, n) / n) if n else (math.nan, math.nan)
    mean_nees = float(nees.mean()) if n else math.nan
    return {
        "table": "consistency",
        "group": "all",
        "method": result.name,
        "frames": n,
        "mean_nees": mean_nees,
        "nees_band_low": float(low),
        "nees_band_high": float(high),
        "consistent": bool(low <= mean_nees <= high) if n else False,
        "within_2sigma": float(np.mean(np.abs(err) <= 2 * std)) if n else math.nan,
        "mean_nis_per_dof": float(nis.sum() / dof.sum()) if dof.sum() > 0 else math.nan,
    }


@dataclass(frozen=True)
class Check:
    claim: str
    holds: bool | None
    detail: str


def paper_checks(tables: dict[str, list[dict]], bound_factor: float = 1.5) -> list[Check]:
    """The paper's findings, checked on the overall table (None: a method was not run)."""
    overall = {row["method"]: row for row in tables["overall"]}

    def rms(name: str) -> float | None:
        row = overall.get(name)
        return None if row is None or not np.isfinite(row["rms_deg"]) else row["rms_deg"]

    checks = []
    tip, bound, ukf, velocity = (
        rms("tip-position"),
        rms(BOUND_NAME),
        rms("ukf"),
        rms("tip-velocity"),
    )
    if tip is not None and bound is not None:
        ratio = tip / bound
        checks.append(
            Check(
                f"closed-form Tip Position within {bound_factor:g} x the Cramer-Rao bound",
                ratio <= bound_factor,
                f"RMS {tip:.3g} deg vs bound {bound:.3g} deg (x {ratio:.2f})",
            )
        )
    else:
        checks.append(Check(f"Tip Position within {bound_factor:g} x the bound", None, "not run"))
    if tip is not None and ukf is not None:
        checks.append(
            Check(
                "the UKF is better than Tip Position", ukf < tip, f"RMS {ukf:.3g} vs {tip:.3g} deg"
            )
        )
    else:
        checks.append(Check("the UKF is better than Tip Position", None, "not run"))
    # Tip Velocity against the other data (its least-squares twin is the same estimator)
    others = {
        m: r["rms_deg"]
        for m, r in overall.items()
        if m != BOUND_NAME and not m.startswith("tip-velocity") and np.isfinite(r["rms_deg"])
    }
    if velocity is not None and others:
        worst_other = max(others, key=others.get)
        checks.append(
            Check(
                "Tip Velocity is the worst method",
                velocity > others[worst_other],
                f"RMS {velocity:.3g} deg vs next worst {worst_other} {others[worst_other]:.3g} deg",
            )
        )
    else:
        checks.append(Check("Tip Velocity is the worst method", None, "not run"))
    return checks


def format_cell(x, digits: int = 2) -> str:
    if x is None:
        return ""
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int | np.integer):
        return str(int(x))
    if isinstance(x, float | np.floating):
        if not np.isfinite(x):
            return "n/a" if np.isnan(x) else "inf"
        return f"{x:.{digits}f}"
    return str(x)


def _percent(x: float | None, digits: int) -> str:
    if x is None:
        return ""
    return f"{100 * x:.{digits}f}%" if np.isfinite(x) else "n/a"


def _pivot(rows: list[dict], methods: Sequence[str], lead: Sequence[tuple[str, str]]) -> list[str]:
    """Markdown: one row per group, one "RMS / max" column per method."""
    groups: dict[object, dict[str, dict]] = {}
    for row in rows:
        groups.setdefault(row["group"], {})[row["method"]] = row
    header = "| " + " | ".join([title for title, _ in lead] + ["frames"] + list(methods)) + " |"
    lines = [header, "|" + "---|" * len(lead) + "---:|" + "---:|" * len(methods)]
    for group, by_method in groups.items():
        first = next(iter(by_method.values()))
        cells = [
            format_cell(group) if key == "group" else format_cell(first.get(key), 1)
            for _, key in lead
        ]
        cells.append(str(first["frames"]))
        for m in methods:
            r = by_method.get(m)
            cells.append(
                "" if r is None else f"{format_cell(r['rms_deg'])} / {format_cell(r['max_deg'])}"
            )
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _median_column(rows: list[dict], unit: str) -> list[tuple[str, str]]:
    """The pivot column of the median label value, for a table of binned groups."""
    if not any(isinstance(row["group"], str) for row in rows):
        return []
    return [(f"median ({unit})" if unit else "median", "group_median")]


def replay_markdown(replay: Replay, tables: dict[str, list[dict]]) -> str:
    """The report: the paper's table and its breakdowns, the UKF's consistency, throughput."""
    methods = list(replay.results) + [BOUND_NAME]
    settings = replay.settings
    lines = [f"# Replay evaluation of {Path(replay.path).name}", ""]
    unscored = int(np.count_nonzero(~replay.scored))
    lines.append(
        f"{len(replay.frames)} frames"
        + (
            f" ({unscored} while moving between configurations: replayed, not scored)"
            if unscored
            else ""
        )
        + (
            ", markers segmented from the recorded images"
            if replay.source == "images"
            else ", markers as recorded"
        )
        + (f", protocol '{settings['protocol']}'" if "protocol" in settings else "")
        + f", rig {replay.scene.rig.kind}. Bending-plane error = wrapped (estimated - true)"
        " delta_1, degrees; the bound is the per-frame Cramer-Rao bound of the tip at the truth"
        f" ({BOUND_NAME})."
    )
    if replay.report.warnings:
        lines += ["", "Read report:", ""] + [f"- {w}" for w in replay.report.warnings]
    if not np.isfinite(replay.truth_rad).any():
        lines += [
            "",
            "The recording has no ground truth: the tables give the share of frames with an"
            " estimate, no errors.",
        ]
    bound = next((r for r in tables["overall"] if r["method"] == BOUND_NAME), None)
    lines += [
        "",
        "## Over all configurations",
        "",
        "| method | RMS (deg) | max (deg) | median (deg) | valid frames | within 2 sigma"
        " | RMS / bound |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in tables["overall"]:
        ratio = (
            row["rms_deg"] / bound["rms_deg"]
            if bound is not None and row["method"] != BOUND_NAME and bound["rms_deg"] > 0
            else math.nan
        )
        within = row.get("within_2sigma")
        lines.append(
            f"| {row['method']} | {format_cell(row['rms_deg'])} | {format_cell(row['max_deg'])} |"
            f" {format_cell(row['median_deg'])} | {100 * row['valid']:.0f}% |"
            f" {_percent(within, 0)} | {format_cell(ratio)} |"
        )
    lines += ["", "Checks against the paper's findings:", ""]
    for check in paper_checks(tables):
        mark = {True: "holds", False: "DOES NOT HOLD", None: "not checked"}[check.holds]
        lines.append(f"- {check.claim}: **{mark}** ({check.detail})")
    if tables["robustness"]:
        lines += ["", "## Can the uncertainty be trusted?", ""]
        lines += robustness_markdown(tables["robustness"])
    if tables["plane"]:
        lines += ["", "## Per bending plane (RMS / max, deg)", ""]
        lines += _pivot(
            tables["plane"],
            methods,
            [
                ("plane", "group"),
                ("delta_1 target (deg)", "delta_1_target_deg"),
                ("true delta_L (deg)", "delta_L_true_deg"),
            ],
        )
    if tables["deflection"]:
        lines += ["", "## Against tip deflection (RMS / max, deg)", ""]
        lead = [("deflection (mm)", "group")] + _median_column(tables["deflection"], "mm")
        lines += _pivot(tables["deflection"], methods, lead)
    if tables["noise"]:
        unit = settings.get("noise_unit", "")
        image_unit = "px" if replay.scene.rig.kind == "pinhole" else "mm"
        lines += [
            "",
            "## Against segmentation noise (RMS / max, deg)"
            + (f"; noise level in {unit}" if unit else ""),
            "",
        ]
        lines += _pivot(
            tables["noise"],
            methods,
            [("noise level", "group")]
            + _median_column(tables["noise"], unit.split(" ")[0])
            + [(f"tip segmentation sigma ({image_unit}, median)", "sigma_image")],
        )
    if tables["consistency"]:
        lines += [
            "",
            "## Consistency of the filters' uncertainty",
            "",
            "| method | frames | mean NEES | 95% band for independent frames | consistent"
            " | within 2 sigma (expect 95%) | NIS / dof |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for row in tables["consistency"]:
            lines.append(
                f"| {row['method']} | {row['frames']} | {format_cell(row['mean_nees'])} |"
                f" {format_cell(row['nees_band_low'])} to {format_cell(row['nees_band_high'])} |"
                f" {format_cell(row['consistent'])} | {_percent(row['within_2sigma'], 1)} |"
                f" {format_cell(row['mean_nis_per_dof'])} |"
            )
        lines += [
            "",
            "Successive filter estimates are correlated, so the band (for independent frames) is"
            " narrower than the real spread of the mean NEES; the 2 sigma coverage is the more"
            " robust figure.",
        ]
    lines += ["", "## Throughput", ""]
    n = max(len(replay.frames), 1)
    for step, seconds in replay.timings_s.items():
        lines.append(f"- {step}: {seconds:.2f} s ({1e6 * seconds / n:.0f} us per frame)")
    return "\n".join(lines) + "\n"


ROBUSTNESS_HEADER = (
    "| method | frames | RMS (deg) | max (deg) | within 2 sigma | mean NEES"
    " | confidently wrong frames | confidently wrong configurations |"
)


def robustness_markdown(rows: Sequence[dict]) -> list[str]:
    """The robustness table (rows of :func:`replay_tables`' ``robustness``) as markdown lines,
    with a note on how to read it."""
    lines = [ROBUSTNESS_HEADER, "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        lines.append(
            f"| {row['method']} | {row['frames']} | {format_cell(row['rms_deg'])} |"
            f" {format_cell(row['max_deg'])} | {_percent(row['within_2sigma'], 1)} |"
            f" {format_cell(row['mean_nees'])} | {row['confidently_wrong_frames']} |"
            f" {row['confidently_wrong_configurations']} |"
        )
    lines += [
        "",
        f"Confidently wrong: an error above {WRONG_DEG:g} deg while the reported std is below"
        f" {CONFIDENT_DEG:g} deg (the target is 0 configurations). An honest std covers the"
        " truth within 2 sigma in about 95% of frames, with a mean NEES (error^2 / std^2) near"
        " 1; more coverage and a smaller NEES mean a std wider than the error.",
    ]
    return lines


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
