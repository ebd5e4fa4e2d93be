"""``cathtrack import``: the lab's logs into a recording (tracker.io.lab_import)."""

from __future__ import annotations

import argparse
from pathlib import Path

from models.model_file import DEFAULT_MODEL_PATH, load_catheter
from models.rig_file import (
    RigFileError,
    base_from_dict,
    orthographic_rig,
    read_rig_file,
    rig_from_dict,
    rig_toml,
    written_model,
)
from tracker.io.lab_import import read_lab_logs, write_lab_recording


def run(args: argparse.Namespace) -> int:
    model_path = DEFAULT_MODEL_PATH if args.model is None else Path(args.model)
    catheter = load_catheter(model_path)
    logs = read_lab_logs(args.mapping, 1 + len(catheter.marker_arclengths_mm))
    data = read_rig_file(args.rig)
    base = base_from_dict(data, args.rig)
    if base is None:
        raise RigFileError(
            f"{args.rig}: no [base] table: register the base first (cathtrack register)"
        )
    if logs.unit == "px":
        rig = rig_from_dict(data, args.rig, "pinhole")
    else:
        rig = orthographic_rig(rig_from_dict(data, args.rig, written_model(data, args.rig)))
    summary = write_lab_recording(
        args.out,
        logs,
        model_toml=model_path.read_text(encoding="utf-8"),
        rig_toml=rig_toml(rig, base, f"registered rig of {Path(args.rig).name}"),
        settings={"command": "import", "mapping": Path(args.mapping).name, "files": logs.files},
    )
    print(
        f"cathtrack import: wrote {summary.path}: {summary.frames} frames,"
        f" {summary.joint_samples} joint samples, {summary.duration_s:.2f} s, points in"
        f" {logs.unit}"
    )
    for warning in summary.warnings:
        print(f"warning: {warning}")
    return 0
