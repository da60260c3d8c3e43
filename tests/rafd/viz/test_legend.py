"""rafd.viz.legend: the scale bar's label clear of the bar, the legend stating the threshold."""

from __future__ import annotations

import numpy as np
import pytest

from tests.utils.pictures import RES


@pytest.mark.parametrize(
    "height,width,px_per_m,font_scale",
    [(256, 256, 4 / RES, 0.45), (768, 768, 6 / RES, 0.45), (128, 128, 1 / RES, 0.35), (1152, 1152, 1 / RES, 0.6)],
)
def test_the_scale_bar_label_never_touches_the_bar(height, width, px_per_m, font_scale):
    from rafd.viz.legend import SCALE_BAR_GAP_PX, draw_scale_bar, scale_bar_layout

    canvas = np.full((height, width, 3), 128, np.uint8)  # mid grey: the black outlines show too
    draw_scale_bar(canvas, px_per_m, font_scale)
    metres, bar, label = scale_bar_layout(canvas.shape, px_per_m, font_scale)
    drawn_rows = np.flatnonzero((canvas != 128).any(axis=(1, 2)))
    bar_top = bar[1]
    label_rows = drawn_rows[drawn_rows < bar_top]
    bar_rows = drawn_rows[drawn_rows >= bar_top]
    assert len(label_rows) and len(bar_rows), "both the label and the bar are drawn"
    assert bar_rows.min() - label_rows.max() - 1 >= SCALE_BAR_GAP_PX - 1, (label_rows.max(), bar_rows.min())
    assert label_rows.min() >= label[1]  # the label stays inside its rect


def test_the_picture_states_the_threshold_its_boxes_were_drawn_at():
    from rafd.viz.legend import Legend, _legend_items

    assert _legend_items(Legend(score_threshold=0.4924))[0][0] == "prediction (score >= 0.49, operating threshold)"
    assert _legend_items(Legend())[0][0] == "prediction (score)"
    flow_text = _legend_items(Legend(flow_px_per_m=10.0, flow_scale=2.0, flow_where="returns or boxes"))[-1][0]
    assert flow_text == "flow, arrow = 1 m (drawn x2), at returns or boxes"
