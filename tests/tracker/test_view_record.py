"""Views' segmentations through a float64 block and back (tracker.vision.view_record): every
field the same, bit for bit and type for type, for views with and without what a frame may
lack; a block too small is said, not overrun."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.tracker.segmentation_common import assert_same_views, flickering_scene
from tracker.vision.pair import PairSegmenter
from tracker.vision.segmentation import SegmentationFlag
from tracker.vision.view_record import read_views, view_size, write_views


@pytest.fixture(scope="module")
def views():
    """Views as a pair segmenter gives them, and the variants a frame may bring."""
    catheter, scene, renderer = flickering_scene(5, 0.4)
    pair = PairSegmenter(catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, renderer.backgrounds)
    rng = np.random.default_rng(5)
    out = []
    for q in ([0.2, 0.5, 0.7], [1.0, -0.4, 0.9]):
        out += list(pair.segment(renderer.render(np.array(q), 0.3, rng).images).views)
    found = out[0]
    segmenter = pair.segmenter
    empty = segmenter.empty_result(SegmentationFlag.NO_CATHETER, found.photometry)
    first_order = dataclasses.replace(
        found, photometry=dataclasses.replace(found.photometry, shift_cov_px2=None)
    )
    rng = np.random.default_rng(1)
    many = dataclasses.replace(
        found,
        markers_px=rng.normal(size=(5, 2)),
        markers_cov=rng.normal(size=(5, 2, 2)),
        markers_found=np.array([True, False, True, True, False]),
        bands_px=np.zeros((0, 2)),
        flags=SegmentationFlag.MARKER_MISSING | SegmentationFlag.EXTRA_BANDS,
    )
    return [*out, empty, dataclasses.replace(found, photometry=None), first_order, many]


def test_every_field_comes_back_the_same(views):
    assert views[4].centreline_px.shape[0] == 0 and views[5].photometry is None
    block = np.full(1 << 16, np.nan)
    used = write_views(block, tuple(views))
    assert used == sum(
        view_size(v.markers_found.size, v.centreline_px.shape[0], v.bands_px.shape[0])
        for v in views
    )
    back = read_views(block, len(views))
    for a, b in zip(views, back, strict=True):
        assert_same_views(a, b)
    block[:] = 0.0  # the views read are copies: the block may be written again
    for a, b in zip(views, back, strict=True):
        assert_same_views(a, b)


def test_a_block_too_small_is_said(views):
    size = view_size(1, views[0].centreline_px.shape[0], views[0].bands_px.shape[0])
    assert write_views(np.zeros(size - 1), views[:1]) == -1
    assert write_views(np.zeros(size), views[:1]) == size
    assert write_views(np.zeros(size), views[:2]) == -1  # the second does not fit
