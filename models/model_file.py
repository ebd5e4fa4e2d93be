"""Reading a catheter model from TOML: the only I/O in ``models``.

The format is documented in docs/model-file.md; ``models/default_catheter.toml`` is the
default model of DESIGN.md section 3 written in it.
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


class ModelFileError(ValueError):
    """A model file that cannot be read or does not describe a valid catheter."""


def _require(table: dict[str, Any], key: str, where: str) -> Any:
    if key not in table:
        raise ModelFileError(f"{where}: missing key '{key}'")
    return table[key]


def _basis(spec: Any, where: str):
    if not isinstance(spec, dict):
        raise ModelFileError(f"{where}: expected a table like {{ basis = \"power\", size = 3 }}")
    name = _require(spec, "basis", where)
    if name not in BASES:
        raise ModelFileError(f"{where}: unknown basis '{name}', known: {', '.join(BASES)}")
    size = _require(spec, "size", where)
    if not isinstance(size, int) or size < 1:
        raise ModelFileError(f"{where}: size must be a positive integer, got {size!r}")
    return BASES[name](size)


def _segment(table: Any, where: str) -> ModalSegment:
    if not isinstance(table, dict):
        raise ModelFileError(f"{where}: expected a table")
    length = _require(table, "length_mm", where)
    if not isinstance(length, int | float) or not length > 0:
        raise ModelFileError(f"{where}: length_mm must be a positive number, got {length!r}")
    psi = _basis(_require(table, "psi", where), f"{where}.psi")
    eta = _basis(_require(table, "eta", where), f"{where}.eta")
    try:
        A = np.array(_require(table, "A", where), dtype=float)
        return ModalSegment(length_mm=float(length), A=A, psi=psi, eta=eta)
    except (TypeError, ValueError) as exc:
        raise ModelFileError(f"{where}: {exc}") from None


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
    if found != version:
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
    markers = data.get("marker_arclengths_mm", [])
    order = data.get("quadrature_order")
    kwargs = {} if order is None else {"quadrature_order": order}
    try:
        return Catheter(
            proximal=proximal,
            distal=distal,
            delta_2_rad=float(delta_2),
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
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ModelFileError(f"cannot read model file {path}: {exc}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ModelFileError(f"{path}: malformed TOML: {exc}") from None
    return catheter_from_dict(data, str(path))
