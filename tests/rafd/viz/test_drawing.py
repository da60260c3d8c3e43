"""rafd.viz.drawing: score labels never overlap each other or what they must avoid, and stay readable."""

from __future__ import annotations

import itertools

import numpy as np

from rafd.viz.drawing import PRED_COLOUR, draw_scores, place_labels
from tests.utils.pictures import dominant


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
