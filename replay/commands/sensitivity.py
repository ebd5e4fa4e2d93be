"""``cathtrack sensitivity``: the paper's three sensitivity studies (:mod:`replay.studies`)."""

from __future__ import annotations

import argparse
import dataclasses

from replay import studies

# Command-line option -> SensitivitySettings field. Every option defaults to None: unset
# options keep the value of --settings FILE, or the documented default.
SENSITIVITY_OPTIONS = {
    "seed": "seed",
    "trials": "trials",
    "ukf_trials": "ukf_trials",
    "chunk_trials": "chunk_trials",
    "methods": "methods",
    "studies": "studies",
    "delta_2_deg": "delta_2_deg",
    "view": "view",
    "noise_levels_mm": "noise_levels_mm",
    "noise_mm": "noise_mm",
    "configuration_deg": "configuration_theta_L_deg",
    "theta_l1_deg": "theta_L1_deg",
    "theta_l2_deg": "theta_L2_deg",
    "deflection_levels_mm": "deflection_levels_mm",
    "deflections": "deflections",
    "deflection_joint": "deflection_joint",
    "joint_rates": "joint_rates",
    "frame_interval_s": "frame_interval_s",
    "frames_per_trial": "frames_per_trial",
    "delta_l_deg": "delta_L_deg",
}


def run(args: argparse.Namespace) -> int:
    base = studies.SensitivitySettings()
    if args.settings:
        base = studies.load_settings(args.settings)
    changes = {
        field: getattr(args, option)
        for option, field in SENSITIVITY_OPTIONS.items()
        if getattr(args, option) is not None
    }
    settings = dataclasses.replace(base, **changes)
    result = studies.run_sensitivity(
        settings, workers=args.workers, scheduler=args.scheduler, progress=not args.no_progress
    )
    paths = studies.write_outputs(result, args.out)
    print(
        f"cathtrack sensitivity: studies {', '.join(settings.studies)}, {settings.trials} trials"
        f" per point ({settings.effective_ukf_trials} for the UKF), seed {settings.seed},"
        f" {result.elapsed_s:.1f} s"
    )
    for finding in studies.findings(result.rows):
        mark = {True: "holds", False: "DOES NOT HOLD", None: "not checked"}[finding.holds]
        print(f"  {finding.claim}: {mark}")
    print(f"wrote {len(paths)} files to {args.out}: " + ", ".join(p.name for p in paths))
    return 0
