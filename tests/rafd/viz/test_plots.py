"""rafd.viz.plots / rafd.viz.answer: labels never overlap, legends with the flow scale, the answer's zoomed picture."""

from __future__ import annotations

import base64
import itertools

import numpy as np
import pytest

from rafd.viz.answer import AnswerView, decode_flow, draw_answer, flow_arrows
from rafd.viz.plots import FLOW_COLOUR, PRED_COLOUR, draw_detections, draw_scores, place_labels

RES = 0.173611


def dominant(picture: np.ndarray, colour: tuple[int, int, int]) -> np.ndarray:
    """[H, W] mask of pixels close to a BGR colour (antialiased strokes blend at their edges)."""
    return (np.abs(picture.astype(int) - np.array(colour)) < 90).all(-1) & (picture.max(-1) > 120)


def overlaps(a, b) -> bool:
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]


def test_placed_labels_never_overlap_each_other_or_what_to_avoid():
    rng = np.random.default_rng(0)
    anchors = [(int(x), int(y), 12, 20) for x, y in rng.uniform(60, 120, (30, 2))]  # a crowded cluster
    avoid = [(0, 0, 60, 30)]
    rects = place_labels(anchors, [(28, 12)] * 30, (200, 200), avoid)
    placed = [r for r in rects if r is not None]
    assert len(placed) >= 20
    for a, b in itertools.combinations(placed + avoid, 2):
        assert not overlaps(a, b), (a, b)
    assert all(0 <= r[0] and 0 <= r[1] and r[0] + r[2] <= 200 and r[1] + r[3] <= 200 for r in placed)
    assert rects[0][1] + rects[0][3] <= anchors[0][1]  # the first (best) label sits right above its box


def test_score_labels_of_stacked_boxes_are_all_readable():
    canvas = np.zeros((300, 300, 3), np.uint8)
    polygons = np.array([[[100 + k, 100], [130 + k, 100], [130 + k, 160], [100 + k, 160]] for k in range(6)], float)
    rects = draw_scores(canvas, polygons, np.linspace(0.9, 0.4, 6), PRED_COLOUR)
    assert all(r is not None for r in rects)
    for a, b in itertools.combinations(rects, 2):
        assert not overlaps(a, b)
    assert dominant(canvas, PRED_COLOUR).sum() > 50  # the text is drawn


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
        "input": {"posted_size": posted, "model_size": model, "crop_offset_px": offset},
        "timing": {"model_ms": 12.0},
    }


@pytest.mark.parametrize("posted, model, zoom", [(1152, 128, 6), (1152, 256, 3), (128, 128, 6), (1152, 1152, 1)])
def test_the_model_crop_is_zoomed_and_the_side_panel_sits_beside_it(posted, model, zoom):
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


@pytest.mark.parametrize(
    "height,width,px_per_m,font_scale",
    [(256, 256, 4 / RES, 0.45), (768, 768, 6 / RES, 0.45), (128, 128, 1 / RES, 0.35), (1152, 1152, 1 / RES, 0.6)],
)
def test_the_scale_bar_label_never_touches_the_bar(height, width, px_per_m, font_scale):
    from rafd.viz.plots import SCALE_BAR_GAP_PX, draw_scale_bar, scale_bar_layout

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


def test_flow_arrows_only_where_the_scan_has_returns_or_boxes():
    from rafd.viz.plots import NEAR_BOX_M, meaningful_cells

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


def test_the_picture_states_the_threshold_its_boxes_were_drawn_at():
    from rafd.viz.plots import Legend, _legend_items

    assert _legend_items(Legend(score_threshold=0.4924))[0][0] == "prediction (score >= 0.49, operating threshold)"
    assert _legend_items(Legend())[0][0] == "prediction (score)"
    flow_text = _legend_items(Legend(flow_px_per_m=10.0, flow_scale=2.0, flow_where="returns or boxes"))[-1][0]
    assert flow_text == "flow, arrow = 1 m (drawn x2), at returns or boxes"


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


def test_answer_validity_from_the_answers_poses_identity_when_the_previous_is_unknown():
    from rafd.viz.answer import AnswerValidity, answer_validity

    first, second = answer_for(1152, 128), answer_for(1152, 128)
    first["timestamp"], first["flow"], first["pose"] = 1.0, None, {"x": 0.0, "y": 0.0, "yaw": 0.0}
    cell = 4 * RES  # one detection cell, 0.69 m
    second["timestamp"], second["pose"] = 2.0, {"x": 0.0, "y": 2 * cell, "yaw": 0.0}  # two cells forward
    second["flow"]["pair"] = [1.0, 2.0]
    at_rest = answer_validity(second, 4, 0)  # identity: only the outermost ring
    assert at_rest.shape == (32, 32) and np.all(at_rest[0] == 0) and np.all(at_rest[1:-1, 1:-1] == 1)
    track = AnswerValidity(geometry=lambda: (4, 0))  # asked of GET /model when first needed
    assert track(first) is None  # no flow: nothing to validate
    moved = track(second)
    assert np.all(moved[1:3, 3:-3] == 0) and np.all(moved[3, 3:-3] == 1)  # ahead: outside the previous crop
    assert np.all(moved[-2, 3:-3] == 1)
    lost = answer_for(1152, 128)
    lost["timestamp"], lost["pose"], lost["flow"]["pair"] = 3.0, second["pose"], [2.5, 3.0]  # a pair not seen
    np.testing.assert_array_equal(AnswerValidity(4)(lost), at_rest)


@pytest.mark.parametrize("flow_format", ["list", "base64"])
def test_the_answers_own_validity_is_used_when_it_carries_one(flow_format):
    from rafd.viz.answer import AnswerValidity, decode_validity

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

    def never():
        raise AssertionError("GET /model is not needed when the answer carries its validity")

    np.testing.assert_array_equal(AnswerValidity(geometry=never)(answer), decoded)
    assert decode_validity(answer_for(1152, 128)["flow"]) is None  # a service before validity
    assert AnswerValidity(geometry=lambda: None)(answer_for(1152, 128) | {"pose": answer["pose"]}) is None
