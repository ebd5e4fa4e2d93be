"""What the segmentation tests (``test_segmentation.py``, ``test_segmentation_kernels.py``,
``test_parallel.py``, ``test_view_record.py``, ``test_priority.py``) share: the catheter's
base, a rendered scene (catheter, rig, renderer; one that flickers and vibrates), a bent
configuration, and the comparison of two views' results field by field."""

import dataclasses

import numpy as np
import pytest

from models.catheter import default_catheter
from replay.simulation.render import Renderer, default_render_rig

BASE_W = np.array([0.0, 0.0, -15.0])


@pytest.fixture(scope="module")
def scene():
    catheter = default_catheter()
    rig = default_render_rig()
    renderer = Renderer(catheter, rig, np.eye(3), BASE_W, seed=2)
    return catheter, rig, renderer


Q_BENT = np.array([0.8, 0.7, 0.5])


def flickering_scene(seed: int, vibration_px: float):
    """The default scene's catheter, scene and a renderer whose frames flicker (10% gain)
    and vibrate (``vibration_px``): what the live loop's segmenters must handle."""
    from replay.simulation.render import ImagingNuisance
    from replay.simulation.simulator import default_scene

    catheter = default_catheter()
    scene = default_scene(catheter, default_render_rig())
    renderer = Renderer(
        catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, seed=seed,
        nuisance=ImagingNuisance(gain_flicker=0.1, vibration_px=vibration_px),
    )  # fmt: skip
    return catheter, scene, renderer


def view_fields(view) -> list:
    """Every field of a ViewSegmentation (the photometry's expanded), for comparison."""
    return [value for _, value in named_view_fields(view)]


def named_view_fields(view) -> list[tuple[str, object]]:
    """:func:`view_fields` with their names (``photometry.gain``...), for messages."""
    out = []
    for f in dataclasses.fields(view):
        value = getattr(view, f.name)
        if f.name == "photometry" and value is not None:
            out += [(f"photometry.{g.name}", getattr(value, g.name))
                    for g in dataclasses.fields(value)]
        else:
            out.append((f.name, value))
    return out


def assert_same(a, b, what: str = ""):
    """The same type and value, bit for bit (NaNs included) for arrays; ``what`` names
    the value in the message."""
    assert type(a) is type(b), what
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, what
        if a.tobytes() != b.tobytes():
            with np.errstate(invalid="ignore"):
                off = np.nanmax(np.abs(a.astype(float) - b.astype(float)), initial=0.0)
            raise AssertionError(f"{what} differs (largest difference {off:.3g}):\n{a!r}\n{b!r}")
    elif isinstance(a, float):
        assert a == b or (np.isnan(a) and np.isnan(b)), f"{what}: {a!r} != {b!r}"
    else:
        assert a == b, f"{what}: {a!r} != {b!r}"


def assert_same_views(a, b, what: str = "view"):
    """Two ViewSegmentations equal in every field (:func:`assert_same`)."""
    for (name, x), (_, y) in zip(named_view_fields(a), named_view_fields(b), strict=True):
        assert_same(x, y, f"{what}: {name}")
