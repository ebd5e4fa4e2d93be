"""A script run in a fresh interpreter, for what only a new process shows: compiled versions
of the numba kernels accumulate in a process, so whether a first frame compiles or loads
anything is seen in one that has done nothing else."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def last_value(script: str):
    """Run ``script`` (Python source) from the repository's root in a new interpreter; the
    value whose ``repr`` it printed last (``ast.literal_eval``: numbers, strings, tuples,
    lists, dicts, booleans). A failing script fails the caller with its output."""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stdout + out.stderr
    return ast.literal_eval(out.stdout.strip().splitlines()[-1])
