"""The robustness table of docs/vision.md: the tip under what imaging changes between frames.

Run from the repository root: ``python benchmarks/segmentation_robustness.py [--configs 40]
[--seed 0] [--write-docs]``.

For each condition of :data:`replay.simulation.robustness.CONDITIONS` (no change, a gain of
0.85 to 1.15 drawn for every frame, an offset of +/-15 gray levels, sensor noise of 8 gray
levels, a gamma of 0.9 to 1.1, and all of them together), ``--configs`` rendered pairs of
bent configurations go through a :class:`tracker.vision.pair.PairSegmenter` as one sequence;
the table gives, over the views where the tip is visible, how often it is found and its
error against the truth (median, 95th percentile, maximum), px, with the default settings
and with the plain segmentation of before (no photometric normalisation, a frozen
background). ``--write-docs`` replaces the table between the markers in docs/vision.md.
Takes about 10 s.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

from _common import ROOT  # puts the repository on sys.path

from replay.simulation.robustness import CONDITIONS, markdown_table, run_conditions
from tracker.vision.settings import DEFAULT_SETTINGS

DOCS = ROOT / "docs" / "vision.md"
BEGIN = "<!-- robustness table: benchmarks/segmentation_robustness.py -->"
END = "<!-- end of robustness table -->"

PLAIN = dataclasses.replace(
    DEFAULT_SETTINGS, normalise=False, freeze_background=True, roi_pad_px=0.0
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", type=int, default=40, help="configurations (40)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--write-docs", action="store_true", help="write the tables into docs/vision.md"
    )
    args = parser.parse_args()
    t0 = time.perf_counter()
    tables = []
    for title, settings in (
        ("With the default settings", DEFAULT_SETTINGS),
        ("Without the photometric normalisation, with a frozen background (the detection"
         " as above)", PLAIN),
    ):
        results = run_conditions(CONDITIONS, args.configs, args.seed, settings)
        tables.append(f"{title}:\n\n{markdown_table(results)}")
    text = (
        f"{args.configs} bent configurations (seed {args.seed}), both views of the default"
        " rendering rig, one sequence per condition; tip error against the truth.\n\n"
        + "\n".join(tables)
    )
    print(text)
    print(f"({time.perf_counter() - t0:.0f} s)")
    if args.write_docs:
        doc = DOCS.read_text(encoding="utf-8")
        start, stop = doc.index(BEGIN) + len(BEGIN), doc.index(END)
        DOCS.write_text(doc[:start] + "\n" + text + doc[stop:], encoding="utf-8")
        print(f"wrote the tables into {DOCS}")


if __name__ == "__main__":
    main()
