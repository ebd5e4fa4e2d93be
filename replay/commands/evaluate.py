"""``cathtrack evaluate``: recordings replayed through the estimators (:mod:`replay.evaluation`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from replay import evaluation
from replay.parallel import worker_count


def run(args: argparse.Namespace) -> int:
    options = dict(
        methods=args.methods,
        source=args.source,
        rrd=not args.no_rrd,
        rrd_frame_every=args.rrd_frame_every,
        rrd_image_every=args.rrd_image_every,
        figures=not args.no_figures,
    )
    if len(args.recordings) == 1 and not args.scheduler:
        result = evaluation.evaluate_recording(
            args.recordings[0],
            args.out,
            progress=not args.no_progress,
            workers=worker_count(args.workers),
            **options,
        )
        print(Path(result.files[0]).read_text(), end="")
        print(
            f"wrote {len(result.files)} files to {args.out}: "
            + ", ".join(f.name for f in result.files)
        )
        return 0
    items = evaluation.evaluate_batch(
        args.recordings,
        args.out,
        workers=args.workers,
        scheduler=args.scheduler,
        progress=not args.no_progress,
        **options,
    )
    print((Path(args.out) / "batch.md").read_text(), end="")
    failed = [item for item in items if item.error]
    for item in failed:
        print(f"cathtrack evaluate: {item.path}: error: {item.error}", file=sys.stderr)
    print(f"wrote {Path(args.out) / 'batch.md'}, batch.csv and one folder per recording")
    return 1 if failed else 0
