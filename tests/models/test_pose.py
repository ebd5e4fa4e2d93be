"""The base pose's point maps (models/pose.py)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from models.pose import Pose


def test_base_from_world_is_the_inverse_map_and_the_same_whatever_the_batch():
    """A point maps to the same bits alone, among a few or among thousands (a matrix product
    of many rows may take another kernel with another order of its sums, which made a batch
    of frames and the same frames one by one differ in the last bit), and back to itself."""
    rng = np.random.default_rng(5)
    pose = Pose(Rotation.random(random_state=rng).as_matrix(), rng.normal(0.0, 50.0, 3))
    points_w = rng.normal(0.0, 30.0, (4096, 3))
    whole = pose.base_from_world(points_w)
    for k in range(0, 4096, 97):
        np.testing.assert_array_equal(pose.base_from_world(points_w[k]), whole[k])
        np.testing.assert_array_equal(pose.base_from_world(points_w[k : k + 3]), whole[k : k + 3])
    grid = pose.base_from_world(points_w.reshape(64, 64, 3))
    np.testing.assert_array_equal(grid.reshape(-1, 3), whole)
    expected = (points_w - pose.o_b_w_mm) @ pose.R_w_b
    np.testing.assert_allclose(whole, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(pose.world_from_base(whole), points_w, rtol=0, atol=1e-12)
