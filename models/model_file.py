"""Reading a catheter model from TOML: the only I/O in ``models``.

The format is documented in docs/model-file.md; ``models/default_catheter.toml`` is the
default model of docs/design.md section 3 written in it.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from models.catheter import Catheter
from models.modal import ModalSegment, PowerBasis

MODEL_FORMAT = "cathtrack-catheter"
MODEL_VERSION = 1
BASES = {"power": PowerBasis}
DEFAULT_MODEL_PATH = Path(__file__).with_name("default_catheter.toml")

# Limits of a plausible model: a steerable segment is millimetres to decimetres long, a modal
# basis has a handful of terms, and a quadrature order beyond a few dozen only costs time
# (order 3,000 took 29 s to load). Values outside are typing errors, refused with one line.
LENGTH_RANGE_MM = (0.1, 1000.0)
MAX_BASIS_SIZE = 12
QUADRATURE_ORDER_RANGE = (2, 200)
MAX_MODAL_COEFFICIENT = 1e3
MAX_MARKERS = 32


class ModelFileError(ValueError):
    """A model file that cannot be read or does not describe a valid catheter."""


def _require(table: dict[str, Any], key: str, where: str) -> Any:
    if key not in table:
        raise ModelFileError(f"{where}: missing key '{key}'")
    return table[key]


def _is_number(x: Any) -> bool:
    """A TOML integer or float; a boolean is not a number."""
    return isinstance(x, int | float) and not isinstance(x, bool)


def _number(x: Any, key: str, where: str, low: float, high: float, what: str = "a number") -> float:
    if not _is_number(x) or not np.isfinite(x) or not low <= x <= high:
        raise ModelFileError(f"{where}: {key} must be {what} in [{low:g}, {high:g}], got {x!r}")
    return float(x)


def _integer(x: Any, key: str, where: str, low: int, high: int) -> int:
    if not isinstance(x, int) or isinstance(x, bool) or not low <= x <= high:
        raise ModelFileError(f"{where}: {key} must be an integer in [{low}, {high}], got {x!r}")
    return x


def _basis(spec: Any, where: str):
    if not isinstance(spec, dict):
        raise ModelFileError(f"{where}: expected a table like {{ basis = \"power\", size = 3 }}")
    name = _require(spec, "basis", where)
    if not isinstance(name, str) or name not in BASES:
        raise ModelFileError(f"{where}: unknown basis {name!r}, known: {', '.join(BASES)}")
    size = _integer(_require(spec, "size", where), "size", where, 1, MAX_BASIS_SIZE)
    return BASES[name](size)


def _matrix(rows: Any, shape: tuple[int, int], where: str) -> np.ndarray:
    ok = isinstance(rows, list) and all(isinstance(r, list) for r in rows)
    if ok:
        ok = all(_is_number(x) for r in rows for x in r)
    if not ok:
        raise ModelFileError(f"{where}: A must be a table of numbers (a list of rows)")
    if len(rows) != shape[0] or any(len(r) != shape[1] for r in rows):
        got = f"{len(rows)} rows of lengths {sorted({len(r) for r in rows})}"
        raise ModelFileError(f"{where}: A has the wrong shape: {got}, need {shape[0]}x{shape[1]}")
    A = np.array(rows, dtype=float)
    if not np.all(np.isfinite(A)) or np.max(np.abs(A), initial=0.0) > MAX_MODAL_COEFFICIENT:
        raise ModelFileError(
            f"{where}: A must hold finite numbers of magnitude at most {MAX_MODAL_COEFFICIENT:g}"
        )
    return A


def _segment(table: Any, where: str) -> ModalSegment:
    if not isinstance(table, dict):
        raise ModelFileError(f"{where}: expected a table")
    length = _require(table, "length_mm", where)
    length = _number(length, "length_mm", where, *LENGTH_RANGE_MM, "a positive number")
    psi = _basis(_require(table, "psi", where), f"{where}.psi")
    eta = _basis(_require(table, "eta", where), f"{where}.eta")
    A = _matrix(_require(table, "A", where), (psi.size, eta.size), where)
    try:
        return ModalSegment(length_mm=length, A=A, psi=psi, eta=eta)
    except (TypeError, ValueError) as exc:
        raise ModelFileError(f"{where}: {exc}") from None


def read_toml_file(path: str | Path, error: type, what: str) -> dict[str, Any]:
    """The parsed TOML of a cathtrack file, or one ``error`` (a ValueError subclass) naming the
    file and the problem: unreadable, not UTF-8, malformed or too deeply nested TOML."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise error(f"cannot read {what} file {path}: {exc.strerror or exc}") from None
    try:
        return tomllib.loads(text)
    except (tomllib.TOMLDecodeError, RecursionError) as exc:
        message = " ".join(str(exc).split()) or "nested too deeply"
        raise error(f"{path}: malformed TOML: {message}") from None


def check_header(
    data: dict[str, Any], fmt: str, version: int, source: str, error: type, what: str
) -> None:
    """Check the ``format`` and ``version`` keys every cathtrack TOML file starts with.

    Raises ``error`` (a ValueError subclass) naming the file and the key.
    """
    found = data.get("format")
    if found != fmt:
        raise error(f"{source}: 'format' must be \"{fmt}\", got {found!r}")
    found = data.get("version")
    if found != version or type(found) is not int:  # true and 1.0 are not the integer 1
        raise error(
            f"{source}: unsupported {what} version {found!r} (this cathtrack reads version "
            f"{version})"
        )


def catheter_from_dict(data: dict[str, Any], source: str = "model") -> Catheter:
    """Build and validate a catheter from the parsed TOML tables."""
    check_header(data, MODEL_FORMAT, MODEL_VERSION, source, ModelFileError, "model")
    proximal = _segment(_require(data, "proximal", source), f"{source} [proximal]")
    distal = _segment(_require(data, "distal", source), f"{source} [distal]")
    delta_2 = data.get("delta_2_rad", 0.0)
    delta_2 = _number(delta_2, "delta_2_rad", source, -2 * np.pi, 2 * np.pi)
    markers = data.get("marker_arclengths_mm", [])
    total_mm = proximal.length_mm + distal.length_mm
    if (
        not isinstance(markers, list)
        or len(markers) > MAX_MARKERS
        or not all(_is_number(x) and np.isfinite(x) for x in markers)
    ):
        raise ModelFileError(
            f"{source}: marker_arclengths_mm must be a list of at most {MAX_MARKERS} numbers"
            f" (arclengths inside the catheter, 0 to {total_mm:g} mm), got {markers!r}"
        )
    order = data.get("quadrature_order")
    kwargs = {}
    if order is not None:
        kwargs["quadrature_order"] = _integer(
            order, "quadrature_order", source, *QUADRATURE_ORDER_RANGE
        )
    try:
        return Catheter(
            proximal=proximal,
            distal=distal,
            delta_2_rad=delta_2,
            marker_arclengths_mm=tuple(float(s) for s in markers),
            **kwargs,
        )
    except (TypeError, ValueError) as exc:
        raise ModelFileError(f"{source}: {exc}") from None


def load_catheter(path: str | Path) -> Catheter:
    """Read a catheter model from a TOML file (see docs/model-file.md).

    Raises
    ------
    ModelFileError
        One message naming the file and the problem: unreadable file, malformed TOML, a
        missing or invalid key.
    """
    data = read_toml_file(path, ModelFileError, "model")
    return catheter_from_dict(data, str(path))
