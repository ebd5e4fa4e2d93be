"""``cathtrack calibrate``: a rig file from checkerboard images (tracker.vision.rig_calibration)."""

from __future__ import annotations

import argparse

from tracker.vision.rig_calibration import (
    calibrate_folders,
    parse_board,
    report_lines,
    write_rig,
)


def parse_view_folder(text: str) -> tuple[str, str]:
    """``NAME=DIR`` of ``--view`` (one per camera)."""
    name, sep, folder = text.partition("=")
    if not sep or not name.isidentifier() or not folder:
        raise ValueError(f"--view takes NAME=DIR (e.g. front=images/front), got {text!r}")
    return name, folder


def run(args: argparse.Namespace) -> int:
    pattern = parse_board(args.board)
    folders = [parse_view_folder(text) for text in args.view or ()]
    if len(folders) < 2:
        raise ValueError("give one --view NAME=DIR per camera, two or more")
    calibration, files = calibrate_folders(folders, pattern, args.square_mm, args.fix_aspect_ratio)
    world = calibration.world_pair
    boards = " / ".join(f[world].name for f in files)
    comment = (
        f"cathtrack calibrate: {len(files[0])} image sets, board {pattern[0]}x{pattern[1]}"
        f" of {args.square_mm:g} mm squares;\nworld frame: the board in {boards}"
    )
    path = write_rig(args.out, calibration.rig, calibration, comment)
    for line in report_lines(calibration):
        print(line)
    print(f"world frame: the board in {boards}")
    print(f"wrote {path}")
    return 0
