"""Evaluating many recordings at once: a local process pool or a Dask cluster.

:func:`evaluate_batch` runs :func:`~replay.evaluation.outputs.evaluate_recording` on every
recording, each into its own folder, and :func:`write_batch` sums them up in ``batch.md`` and
``batch.csv``; a recording that cannot be read is reported there, the others are evaluated,
and what the reader found in a damaged one (the parts lost, by kind and span) is listed
there too.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

from replay.evaluation.outputs import CSV_COLUMNS, evaluate_recording
from replay.evaluation.run import progress_bar
from replay.evaluation.tables import Check, format_cell
from replay.parallel import worker_count


@dataclass(frozen=True)
class BatchItem:
    """One recording of a batch: its overall rows and checks, or the error that stopped it."""

    path: str
    out_dir: str | None
    overall: tuple[dict, ...] = ()
    checks: tuple[Check, ...] = ()
    warnings: tuple[str, ...] = ()
    error: str | None = None


def _batch_task(path: str, out_dir: str | None, options: dict) -> BatchItem:
    """Evaluate one recording; the errors a bad input can cause (a
    :class:`~tracker.io.recording.RecordingError` or another ValueError naming the file, an
    OSError) become the item's error. Anything else is a bug, and stops the batch."""
    try:
        result = evaluate_recording(path, out_dir, **options)
    except (ValueError, OSError) as exc:
        return BatchItem(path, out_dir, error=str(exc) or type(exc).__name__)
    return BatchItem(
        path,
        out_dir,
        tuple(result.tables["overall"]),
        tuple(result.checks()),
        tuple(result.replay.report.warnings),
    )


def evaluate_batch(
    paths: Sequence[str | Path],
    out_dir: str | Path,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
    **options,
) -> list[BatchItem]:
    """Evaluate many recordings, each into ``out_dir/<name>/``, on a local process pool
    (``workers``, default all CPUs) or a Dask cluster (``scheduler`` address); writes
    ``out_dir/batch.md`` and ``out_dir/batch.csv``. A recording that cannot be read is
    reported in the batch table, the others are evaluated; should the batch stop on an
    unexpected error, the tables still sum up the recordings done before it is raised."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = _unique_names([Path(p) for p in paths])
    jobs = [(str(p), str(out / name)) for p, name in zip(paths, names, strict=True)]
    options = {**options, "progress": False, "workers": 1}
    workers = worker_count(workers)
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    bar = progress_bar(len(jobs), "evaluate", progress, unit="recording")
    items: list[BatchItem | None] = [None] * len(jobs)
    try:
        if scheduler:
            try:  # imported here: dask.distributed is slow to import and only needed here
                from dask.distributed import Client
                from dask.distributed import as_completed as dask_completed
            except ImportError as exc:  # pragma: no cover - dask is a dependency
                raise ValueError("--scheduler needs dask.distributed installed") from exc
            try:
                client = Client(scheduler, set_as_default=False, timeout="10s")
            except (OSError, TimeoutError) as exc:
                raise ValueError(
                    f"cannot connect to the Dask scheduler at {scheduler}: {exc}"
                ) from exc
            try:
                futures = [client.submit(_batch_task, p, o, options, pure=False) for p, o in jobs]
                index = {f.key: i for i, f in enumerate(futures)}
                for future in dask_completed(futures, loop=client.loop):
                    items[index[future.key]] = future.result()
                    bar.update()
            finally:
                client.close()
        elif workers == 1 or len(jobs) == 1:
            for i, (p, o) in enumerate(jobs):
                items[i] = _batch_task(p, o, options)
                bar.update()
        else:
            with ProcessPoolExecutor(max_workers=min(workers, len(jobs))) as pool:
                futures = {
                    pool.submit(_batch_task, p, o, options): i for i, (p, o) in enumerate(jobs)
                }
                for future in as_completed(futures):
                    items[futures[future]] = future.result()
                    bar.update()
    finally:
        bar.close()
        done = [item for item in items if item is not None]
        write_batch(done, out)
    return done


def _unique_names(paths: Sequence[Path]) -> list[str]:
    names, seen = [], {}
    for p in paths:
        stem = p.stem or "recording"
        seen[stem] = seen.get(stem, 0) + 1
        names.append(stem if seen[stem] == 1 else f"{stem}-{seen[stem]}")
    return names


def write_batch(items: Sequence[BatchItem], out: Path) -> list[Path]:
    """batch.csv (overall rows of every recording) and batch.md (RMS / max per method)."""
    rows = []
    for item in items:
        for row in item.overall:
            rows.append({"recording": item.path, **row})
    csv_path = out / "batch.csv"
    with open(csv_path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=("recording",) + CSV_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
        for item in items:
            if item.error:
                writer.writerow({"recording": item.path, "table": "error", "group": item.error})
    methods: list[str] = []
    for item in items:
        for row in item.overall:
            if row["method"] not in methods:
                methods.append(row["method"])
    lines = [
        "# Batch evaluation (RMS / max bending-plane error, deg)",
        "",
        "| recording | " + " | ".join(methods) + " | checks |",
        "|---|" + "---:|" * len(methods) + "---|",
    ]
    for item in items:
        if item.error:
            lines.append(
                f"| {item.path} | " + " | ".join("" for _ in methods) + f" | error: {item.error} |"
            )
            continue
        by = {r["method"]: r for r in item.overall}
        cells = [
            f"{format_cell(by[m]['rms_deg'])} / {format_cell(by[m]['max_deg'])}" if m in by else ""
            for m in methods
        ]
        held = sum(c.holds is True for c in item.checks)
        checked = sum(c.holds is not None for c in item.checks)
        lines.append(f"| {item.path} | " + " | ".join(cells) + f" | {held}/{checked} hold |")
    warned = [item for item in items if item.warnings]
    if warned:
        lines += ["", "## Read reports (what the reader skipped or lost)", ""]
        for item in warned:
            lines += [f"- {item.path}:"] + [f"  - {w}" for w in item.warnings]
    md_path = out / "batch.md"
    md_path.write_text("\n".join(lines) + "\n")
    return [md_path, csv_path]
