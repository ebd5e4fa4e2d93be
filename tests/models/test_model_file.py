"""Model files: the default file reproduces the default model; bad files give one clear error."""

import numpy as np
import pytest

from models import default_catheter, load_catheter
from models.model_file import DEFAULT_MODEL_PATH, ModelFileError

TEMPLATE = DEFAULT_MODEL_PATH.read_text()


def test_default_file_equals_default_model():
    loaded = load_catheter(DEFAULT_MODEL_PATH)
    reference = default_catheter()
    q = np.random.default_rng(0).uniform([-3, -1, -1], [3, 1, 1], (50, 3))
    np.testing.assert_allclose(loaded.tip(q, 0.4), reference.tip(q, 0.4), atol=1e-12)
    assert loaded.marker_arclengths_mm == reference.marker_arclengths_mm


def test_file_settings_are_used(tmp_path):
    path = tmp_path / "model.toml"
    text = TEMPLATE.replace("delta_2_rad = 0.0", "delta_2_rad = 1.5707963267948966")
    text = text.replace("marker_arclengths_mm = [13.0]", "marker_arclengths_mm = [6.5, 21.0]")
    path.write_text(text)
    loaded = load_catheter(path)
    q = np.array([0.2, 0.7, -0.4])
    np.testing.assert_allclose(loaded.tip(q, 0.1), default_catheter(np.pi / 2).tip(q, 0.1))
    assert loaded.marker_arclengths_mm == (6.5, 21.0)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.replace("length_mm = 13.0", "length_mm = -13.0"), "length_mm must be a positive number"),
        (lambda t: t.replace("length_mm = 16.0", "length_mm = 0"), r"\[distal\].*length_mm"),
        (lambda t: t.replace("[0.0, 0.3, 0.0],\n]", "]", 1), r"\[proximal\].*shape"),
        (lambda t: t.replace('format = "cathtrack-catheter"', ""), "'format' must be"),
        (lambda t: t.replace("version = 1", "version = 7"), "unsupported model version 7"),
        (lambda t: t.replace('psi = { basis = "power", size = 3 }', "", 1), "missing key 'psi'"),
        (lambda t: t.replace('"power", size = 3 }', '"chebyshev", size = 3 }', 1), "unknown basis"),
        (lambda t: t.replace("[13.0]", "[13.0, 40.0]"), "outside the catheter"),
        (lambda t: t.replace("[13.0]", "[13.0, 29.0]"), "tip is always measured on its own"),
        (lambda t: t.replace("[distal]", "[distal"), "malformed TOML"),
        (lambda t: t.replace("-2.2", '"nan"'), r"\[proximal\]"),
    ],
)
def test_bad_model_files(tmp_path, edit, message):
    path = tmp_path / "bad.toml"
    path.write_text(edit(TEMPLATE))
    with pytest.raises(ModelFileError, match=message):
        load_catheter(path)


def test_unreadable_file(tmp_path):
    with pytest.raises(ModelFileError, match="cannot read model file"):
        load_catheter(tmp_path / "missing.toml")
