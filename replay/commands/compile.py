"""``cathtrack compile``: every numba kernel compiled and cached now
(:mod:`replay.compile_ahead`)."""

from __future__ import annotations

import argparse
import sys

from replay.compile_ahead import compile_all
from replay.parallel import worker_count


def run(args: argparse.Namespace) -> int:
    if args.jobs is not None and args.jobs < 1:
        raise ValueError(f"--jobs must be at least 1, got {args.jobs}")
    jobs = worker_count(args.jobs)
    print(f"cathtrack compile: the numba kernels, {jobs} at a time (cached: only loaded)")
    try:
        took = compile_all(jobs, report=lambda line: print(line, flush=True))
    except RuntimeError as exc:  # a kernel that does not compile: the code, not the user
        print(f"cathtrack compile: error: {exc}", file=sys.stderr)
        return 1
    print(f"cathtrack compile: done in {took:.1f} s")
    return 0
