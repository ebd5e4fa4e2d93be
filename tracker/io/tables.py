"""Tables of numbers with named columns, from CSV or MATLAB .mat files (docs/setup.md).

The set-up files (measured shapes, the registration routine and its observations) and the
lab's logs are tables: one column per quantity, one row per sample.

- CSV: a header row of column names, then one row of numbers per sample; an empty cell or
  ``nan`` is a missing value; lines starting with ``#`` are comments.
- MATLAB .mat (``save(..., '-v7')`` or earlier; read with :func:`scipy.io.loadmat`): one
  numeric vector per column, all of the same length; other variables are ignored.

Every problem ends in one :class:`TableError` naming the file, the column and, for a bad
value, the line (CSV) or element (.mat).
"""

from __future__ import annotations

import csv
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

Array = np.ndarray

SUFFIXES = (".csv", ".mat")


class TableError(ValueError):
    """A table file that cannot be read, or lacks a column or a valid value."""


def point_columns(view: str, n_points: int) -> list[tuple[str, str]]:
    """Default column names of the segmented points of one view: ``(u, v)`` per point.

    Points in the order of :class:`tracker.types.Frame`: the tip, then the markers:
    ``front_tip_u, front_tip_v, front_marker0_u, front_marker0_v, ...``.
    """
    names = ["tip"] + [f"marker{k}" for k in range(n_points - 1)]
    return [(f"{view}_{name}_u", f"{view}_{name}_v") for name in names]


@dataclass(frozen=True, eq=False)
class Table:
    """Columns of one file, all of the same length.

    Parameters
    ----------
    source : str
        The file, for messages.
    columns : mapping of str to array, shape (n,)
        Values as floats; NaN where missing.
    lines : array of int, shape (n,), optional
        File line of each row (CSV), for messages; None for .mat files.
    """

    source: str
    columns: Mapping[str, Array]
    lines: Array | None = None

    @property
    def n_rows(self) -> int:
        return next(iter(self.columns.values())).size if self.columns else 0

    def has(self, name: str) -> bool:
        return name in self.columns

    def where(self, row: int) -> str:
        """``line 12`` (CSV) or ``element 12`` (.mat) for a 0-based row."""
        return f"line {self.lines[row]}" if self.lines is not None else f"element {row + 1}"

    def column(self, name: str, finite: bool = True) -> Array:
        """One column, shape (n,); with ``finite``, a TableError at its first missing value."""
        if name not in self.columns:
            raise TableError(
                f"{self.source}: no column '{name}' (columns: {', '.join(self.columns) or 'none'})"
            )
        values = self.columns[name]
        if finite:
            bad = np.flatnonzero(~np.isfinite(values))
            if bad.size:
                raise TableError(
                    f"{self.source}: column '{name}' has {bad.size} missing or non-finite"
                    f" value(s), the first at {self.where(int(bad[0]))}"
                )
        return values


def _number(cell: str) -> float:
    cell = cell.strip()
    return float(cell) if cell else float("nan")


def _read_csv(path: Path) -> Table:
    try:
        with open(path, newline="", encoding="utf-8") as handle:
            raw = [(n, row) for n, row in enumerate(csv.reader(handle), start=1)]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise TableError(f"cannot read {path}: {exc}") from None
    raw = [(n, row) for n, row in raw if row and not row[0].lstrip().startswith("#")]
    if not raw:
        raise TableError(f"{path}: empty file (expected a header row of column names)")
    header_line, header = raw[0]
    names = [name.strip() for name in header]
    if any(not name for name in names):
        raise TableError(f"{path} line {header_line}: empty column name in the header")
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise TableError(f"{path}: column(s) {', '.join(repeated)} appear more than once")
    data = raw[1:]
    if not data:
        raise TableError(f"{path}: no data rows below the header")
    values = np.empty((len(data), len(names)))
    for i, (line, row) in enumerate(data):
        if len(row) != len(names):
            raise TableError(
                f"{path} line {line}: {len(row)} cells, the header has {len(names)} columns"
            )
        for j, cell in enumerate(row):
            try:
                values[i, j] = _number(cell)
            except ValueError:
                raise TableError(
                    f"{path} line {line}, column '{names[j]}': {cell.strip()!r} is not a number"
                ) from None
    lines = np.array([line for line, _ in data])
    return Table(str(path), {name: values[:, j] for j, name in enumerate(names)}, lines)


def _read_mat(path: Path) -> Table:
    from scipy.io import loadmat

    try:
        data = loadmat(path)
    except NotImplementedError:
        raise TableError(f"{path}: MATLAB v7.3 files are not supported; save with '-v7'") from None
    except (OSError, ValueError, TypeError) as exc:
        raise TableError(f"cannot read {path} as a MATLAB .mat file: {exc}") from None
    columns: dict[str, Array] = {}
    for name, value in data.items():
        if name.startswith("__") or not isinstance(value, np.ndarray):
            continue
        if value.dtype.kind not in "biuf":
            continue  # strings, cells and structs are not columns
        vector = np.asarray(value, dtype=float)
        if vector.ndim > 1 and sum(n > 1 for n in vector.shape) > 1:
            raise TableError(
                f"{path}: variable '{name}' has shape {vector.shape}; each column must be a vector"
            )
        columns[name] = vector.ravel()
    if not columns:
        raise TableError(f"{path}: no numeric variables (one vector per column expected)")
    lengths = {name: v.size for name, v in columns.items()}
    first = next(iter(lengths))
    for name, n in lengths.items():
        if n != lengths[first]:
            raise TableError(
                f"{path}: variable '{name}' has {n} elements, '{first}' has {lengths[first]};"
                " every column must have the same length"
            )
    return Table(str(path), columns)


def read_table(path: str | Path) -> Table:
    """A CSV or .mat table (see the module docstring), or one TableError."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise TableError(
            f"{path}: unsupported file type '{path.suffix}'; give a .csv or a MATLAB .mat file"
        )
    if not path.is_file():
        raise TableError(f"cannot read {path}: no such file")
    return _read_csv(path) if suffix == ".csv" else _read_mat(path)


def _cell(x: float | int, integer: bool) -> str:
    if integer:
        return str(int(x))
    x = float(x)
    return repr(x) if np.isfinite(x) else ""


def write_csv(path: str | Path, columns: Mapping[str, Array], comment: str = "") -> Path:
    """Write columns (equal lengths) as CSV: ``repr`` floats (read back exactly), NaN empty.

    Integer arrays are written as integers; ``comment`` lines go first, each after ``# ``.
    """
    path = Path(path)
    arrays = {name: np.asarray(values) for name, values in columns.items()}
    sizes = {values.size for values in arrays.values()}
    if len(sizes) > 1:
        raise ValueError(f"columns of different lengths: {sorted(sizes)}")
    n = sizes.pop() if sizes else 0
    integer = {name: values.dtype.kind in "iub" for name, values in arrays.items()}
    lines = [f"# {line}" for line in comment.splitlines()]
    lines.append(",".join(arrays))
    for i in range(n):
        lines.append(",".join(_cell(arrays[name][i], integer[name]) for name in arrays))
    try:
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    except OSError as exc:
        raise OSError(f"cannot write {path}: {exc.strerror or exc}") from None
    return path
