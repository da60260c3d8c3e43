"""rafd.viz.plots: the evaluation picture's legend strip, and flow arrows only where they mean something."""

from __future__ import annotations

import numpy as np
import pytest

from rafd.viz.drawing import FLOW_COLOUR, PRED_COLOUR
from rafd.viz.plots import draw_detections
from tests.utils.pictures import RES, dominant


def test_evaluation_picture_has_a_legend_strip_and_flow_arrows():
    image = np.full((64, 64), 40, np.uint8)
    flow = np.zeros((2, 16, 16))
    flow[0, 8, 8] = 1.0  # one cell moved 1 m to the right
    canvas = draw_detections(
        image,
        np.array([[0.0, 2.0, 2.0, 4.0, 0.0]]),
        np.array([[0.5, 2.0, 2.0, 4.0, 0.1]]),
        np.array([0.8]),
        RES,
        flow=flow,
        upscale=4,
    )
    assert canvas.shape[1] == 256 and canvas.shape[0] > 256  # the legend lies below the scan, not over it
    strip = canvas[256:]
    assert dominant(strip, FLOW_COLOUR).sum() > 20 and dominant(strip, PRED_COLOUR).sum() > 20
    assert dominant(canvas[:256], FLOW_COLOUR).sum() > 20


def test_flow_arrows_only_where_the_scan_has_returns_or_boxes():
    from rafd.viz.flow_cells import NEAR_BOX_M, meaningful_cells

    image = np.full((64, 64), 10, np.uint8)
    image[8:12, 8:12] = 220  # returns in cell (2, 2) only (stride 4)
    keep = meaningful_cells(image, (16, 16), 4)
    assert keep.sum() == 1 and keep[2, 2]
    near = meaningful_cells(image, (16, 16), 4, centres=np.array([[50.0, 50.0]]), near_px=NEAR_BOX_M / RES)
    assert near[2, 2] and near[12, 12] and not near[12, 0]
    flow = np.zeros((2, 16, 16))
    flow[0] = 1.0  # the network's flow moves everywhere, the empty edges included
    drawn = draw_detections(image, np.zeros((0, 5)), np.zeros((0, 5)), np.zeros(0), RES, flow=flow, upscale=4)
    everywhere = draw_detections(
        image, np.zeros((0, 5)), np.zeros((0, 5)), np.zeros(0), RES, flow=flow, upscale=4, all_flow=True
    )
    arrows, all_arrows = dominant(drawn[:256], FLOW_COLOUR), dominant(everywhere[:256], FLOW_COLOUR)
    assert 0 < arrows.sum() < all_arrows.sum() / 10
    rows, cols = np.nonzero(arrows)
    assert rows.max() < 64 and cols.max() < 64  # all near the returns in the top-left corner


def test_evaluation_pictures_draw_flow_only_in_valid_cells():
    image = np.full((64, 64), 220, np.uint8)  # returns everywhere: every cell is worth an arrow
    flow = np.zeros((2, 16, 16))
    flow[0] = 1.0
    validity = np.zeros((16, 16))
    validity[:, :8] = 1.0  # only the left half was measured over the full range
    validity[:, 8] = 0.99  # just below FLOW_VALID_MIN: not drawn
    kwargs = dict(flow=flow, upscale=4, flow_step=1)
    every = draw_detections(image, np.zeros((0, 5)), np.zeros((0, 5)), np.zeros(0), RES, **kwargs)
    valid = draw_detections(image, np.zeros((0, 5)), np.zeros((0, 5)), np.zeros(0), RES, validity=validity, **kwargs)
    unchanged = draw_detections(
        image, np.zeros((0, 5)), np.zeros((0, 5)), np.zeros(0), RES, validity=np.ones((16, 16)), **kwargs
    )
    arrows, all_arrows = dominant(valid[:256], FLOW_COLOUR), dominant(every[:256], FLOW_COLOUR)
    assert np.flatnonzero(all_arrows.any(0)).max() > 200  # without validity: arrows across the whole crop
    assert arrows.sum() > 0 and np.flatnonzero(arrows.any(0)).max() < 8 * 16  # with it: the left half only
    np.testing.assert_array_equal(unchanged[:256], every[:256])  # everywhere valid: the same picture
    with pytest.raises(ValueError, match="validity"):
        draw_detections(image, np.zeros((0, 5)), np.zeros((0, 5)), np.zeros(0), RES, flow=flow, validity=np.ones(3))
