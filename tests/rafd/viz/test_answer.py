"""rafd.viz.answer: the model crop zoomed beside its panel, the flow arrows at scale, validity from the answer."""

from __future__ import annotations

import base64

import numpy as np
import pytest

from rafd.viz.answer import AnswerView, decode_flow, draw_answer, flow_arrows
from rafd.viz.drawing import FLOW_COLOUR
from tests.utils.pictures import RES, dominant


def answer_for(posted: int, model: int, flow_format: str = "list") -> dict:
    """A /detect answer with one box 3 m ahead and one flow cell moving 1 m right (grid stride 4)."""
    offset = (posted - model) // 2
    cells = model // 4
    values = np.zeros((2, cells, cells))
    values[0, cells // 2, cells // 2] = 1.0
    encoded = (
        values.tolist() if flow_format == "list" else base64.b64encode(values.astype("<f2").tobytes()).decode("ascii")
    )
    centre = posted / 2.0
    polygon = [
        [centre - 6, centre - 23],
        [centre + 6, centre - 23],
        [centre + 6, centre - 11],
        [centre - 6, centre - 11],
    ]
    return {
        "timestamp": 12.5,
        "frames_used": 2,
        "num_frames": 4,
        "warming_up": True,
        "pose_source": "request",
        "boxes": [
            {
                "x": 0.0,
                "y": 3.0,
                "width": 2.0,
                "length": 2.0,
                "yaw": 0.0,
                "score": 0.77,
                "class": "vehicle",
                "polygon": polygon,
                "track_id": "0a1b2c3d-1",
                "velocity": None,
            }
        ],
        "flow": {
            "shape": [2, cells, cells],
            "encoding": "list" if flow_format == "list" else "base64-float16",
            "values": encoded,
            "grid": {
                "height": cells,
                "width": cells,
                "cell_size_m": 4 * RES,
                "stride_px": 4,
                "origin_px": [offset, offset],
            },
        },
        "input": {
            "posted_size": posted,
            "model_size": model,
            "covered": {"side_px": model, "offset_px": offset, "side_m": model * RES, "range_m": None, "tiles": 1},
        },
        "timing": {"model_ms": 12.0},
    }


@pytest.mark.parametrize("posted, model, zoom", [(1152, 128, 6), (1152, 256, 3), (128, 128, 6), (1152, 1152, 2 / 3)])
def test_the_covered_area_is_fitted_to_the_view_and_the_side_panel_sits_beside_it(posted, model, zoom):
    scan = np.full((posted, posted), 30, np.uint8)
    picture = draw_answer(scan, answer_for(posted, model), truth_polygons=np.zeros((0, 4, 2)), resolution=RES)
    assert picture.shape == (max(model * zoom, picture.shape[0]), model * zoom + AnswerView().panel_px, 3)
    no_flow = answer_for(posted, model)
    no_flow["flow"] = None
    assert draw_answer(scan, no_flow, np.zeros((0, 4, 2)), RES).shape == picture.shape  # one size per sequence


def test_flow_arrow_is_drawn_at_its_scale_ending_at_the_cell():
    answer = answer_for(1152, 128)
    picture = draw_answer(np.zeros((1152, 1152), np.uint8), answer, None, RES, AnswerView(flow_step=1))
    view = picture[:768, :768]
    yellow_columns = np.flatnonzero(dominant(view, FLOW_COLOUR).any(0))
    # Cell (16, 16) centre: posted u = 512 + 66 = 578 -> view (578 - 512) * 6 = 396; 1 m at zoom 6 = 34.6 px.
    assert yellow_columns.min() == pytest.approx(396 - 34.6, abs=3) and yellow_columns.max() == pytest.approx(
        396, abs=2
    )


def test_flow_encodings_decode_alike_and_bad_scans_are_refused():
    np.testing.assert_allclose(
        decode_flow(answer_for(1152, 128, "base64")["flow"]), decode_flow(answer_for(1152, 128)["flow"])
    )
    heads, motions = flow_arrows(answer_for(1152, 128)["flow"], min_m=0.05)
    assert heads.tolist() == [[578.0, 578.0]] and motions.tolist() == [[1.0, 0.0]]
    with pytest.raises(ValueError, match="posted"):
        draw_answer(np.zeros((256, 256), np.uint8), answer_for(1152, 128), None, RES)


def test_the_answer_picture_skips_invalid_flow_cells():
    answer = answer_for(1152, 128)  # one cell, (16, 16), moves 1 m
    scan = np.zeros((1152, 1152), np.uint8)
    view = AnswerView(flow_step=1)
    valid = np.ones((32, 32))
    drawn = draw_answer(scan, answer, None, RES, view, validity=valid)[:768, :768]
    valid[16, 16] = 0.5
    skipped = draw_answer(scan, answer, None, RES, view, validity=valid)[:768, :768]
    assert dominant(drawn, FLOW_COLOUR).sum() > 20 and dominant(skipped, FLOW_COLOUR).sum() == 0
    default = draw_answer(scan, answer, None, RES, view)[:768, :768]  # no validity: drawn as before
    np.testing.assert_array_equal(default, drawn)


@pytest.mark.parametrize("flow_format", ["list", "base64"])
def test_the_answers_own_validity_decodes_in_the_flows_encoding(flow_format):
    from rafd.viz.answer import decode_validity

    answer = answer_for(1152, 128, flow_format)
    answer["pose"], answer["flow"]["pair"] = {"x": 0.0, "y": 0.0, "yaw": 0.0}, [12.4, 12.5]
    validity = np.ones((32, 32))
    validity[16, 16] = 0.99
    answer["flow"]["validity"] = (
        validity.tolist()
        if flow_format == "list"
        else base64.b64encode(validity.astype("<f2").tobytes()).decode("ascii")
    )
    decoded = decode_validity(answer["flow"])
    assert decoded is not None and decoded.shape == (32, 32) and decoded[16, 16] < 1.0 and decoded[0, 0] == 1.0
    assert decode_validity(answer_for(1152, 128)["flow"]) is None  # a flow without validity: none drawn from it
