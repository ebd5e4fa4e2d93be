"""What the segmentation tests (``test_segmentation.py``, ``test_segmentation_kernels.py``)
share: the catheter's base, a rendered scene (catheter, rig, renderer) and a bent
configuration."""

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
