"""``cathtrack simulate``: a recording of the paper's simulated protocol (replay.protocol)."""

from __future__ import annotations

import argparse
import math

from replay.commands.nuisance import nuisance_from_args
from replay.protocol import ProtocolSettings, simulate_protocol
from replay.simulation.simulator import LabConditions


def lab_conditions_from_args(args: argparse.Namespace) -> LabConditions:
    """The lab conditions of ``cathtrack simulate``'s options (replay.cli)."""
    options = {
        "model_scale_error": args.model_scale_error,
        "contact_joint_std_mm": args.contact_joint_std_mm,
        "outlier_probability": args.outlier_rate,
        "dropout_probability": args.dropout_rate,
        "windup_play_rad": math.radians(args.windup_play_deg),
    }
    if args.outlier_size_mm is not None:
        options["outlier_magnitude"] = args.outlier_size_mm
    return LabConditions(**options)


def run(args: argparse.Namespace) -> int:
    options = {
        "seed": args.seed,
        "planes": args.planes,
        "configurations": args.configs,
        "frames_per_configuration": args.frames,
        "frame_rate_hz": args.frame_rate_hz,
        "joint_rate_hz": args.joint_rate_hz,
        "images": not args.no_images,
        "rig": args.rig,
        "transition_frames": not args.no_transition_frames,
        "image_nuisance": nuisance_from_args(args),
        "lab_conditions": lab_conditions_from_args(args),
    }
    for option, field in (
        ("noise_levels_mm", "noise_levels_mm"),
        ("image_noise_levels_gray", "image_noise_levels_gray"),
        ("deflection_levels_mm", "deflection_levels_mm"),
    ):
        if getattr(args, option) is not None:
            options[field] = tuple(getattr(args, option))
    settings = ProtocolSettings(**options)
    summary = simulate_protocol(
        settings, args.out, args.model, workers=args.workers, progress=not args.no_progress
    )
    print(
        f"cathtrack simulate: wrote {summary.path}: protocol {args.protocol},"
        f" {settings.planes} planes, {settings.configurations} configurations,"
        f" {summary.frames} frames ({'images and markers' if settings.images else 'markers only'}),"
        f" {summary.joint_samples} joint samples, {summary.duration_s:.1f} s of session,"
        f" {summary.bytes / 1e6:.1f} MB"
    )
    return 0
