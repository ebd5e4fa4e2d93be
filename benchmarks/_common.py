"""Shared by the benchmark scripts: run from a checkout without installing, and verdicts.

Importing this module puts the repository root on ``sys.path`` so that ``python
benchmarks/bench_*.py`` works from a plain checkout as well as from the project's venv.
"""

from __future__ import annotations

import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def verdict(ok: bool) -> str:
    """PASS or MISS against a benchmark target."""
    return "PASS" if ok else "MISS"


@contextmanager
def busy_processes(n: int):
    """``n`` processes that spin for as long as the block runs (a CPU hog each)."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
