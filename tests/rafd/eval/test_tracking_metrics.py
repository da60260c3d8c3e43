"""rafd.eval.tracking_metrics: TrackEval's HOTA, CLEAR and Identity on 2 m centre matching, against a case worked
out by hand."""

from __future__ import annotations

import numpy as np
import pytest

from rafd.eval.tracking_metrics import FrameTracks, similarity, tracking_metrics


def test_similarity_reaches_one_half_at_the_2m_match():
    s = similarity(np.zeros((1, 2)), np.array([[1.0, 0.0], [2.0, 0.0], [3.0, 0.0], [5.0, 0.0]]))
    assert s.tolist() == [[0.75, 0.5, 0.25, 0.0]]
    assert similarity(np.zeros((0, 2)), np.zeros((3, 2))).shape == (0, 3)


def test_a_hand_computed_tiny_case():
    """One vehicle (id 7) in 4 scans at the origin; the tracker follows it 0.5 m off as id 1 twice then id 2 twice
    (one switch), and adds a false box far away in the last scan.
    CLEAR: TP 4, FN 0, FP 1, IDSW 1 -> MOTA = 1 - (0 + 1 + 1) / 4 = 50%.
    Identity: the vehicle is best given to id 1 (or 2): IDTP 2, IDFN 2, IDFP 3 -> IDF1 = 4 / 9, IDP 2/5, IDR 2/4.
    HOTA at 2 m (similarity 0.875 >= 0.5): DetA = 4 / (4 + 0 + 1) = 0.8; each match's association 2 / (2 + 2 + 0)
    = 0.5 -> AssA 0.5, HOTA = sqrt(0.4). Averaged over alpha = 0.05 ... 0.95: the 0.5 m matches fail alpha 0.9
    and 0.95 (2 of 19 thresholds), so DetA = 0.8 * 17 / 19."""
    frames = []
    for t, track in enumerate([1, 1, 2, 2]):
        xy = [[0.5, 0.0]] + ([[50.0, 50.0]] if t == 3 else [])
        ids = [track] + ([9] if t == 3 else [])
        frames.append(FrameTracks(np.zeros((1, 2)), np.array([7]), np.array(xy), np.array(ids)))
    figures = tracking_metrics({"one": frames})
    assert (figures["TP"], figures["FN"], figures["FP"], figures["IDSW"]) == (4, 0, 1, 1)
    assert figures["MOTA"] == pytest.approx(50.0)
    assert figures["IDF1"] == pytest.approx(100 * 4 / 9)
    assert (figures["IDP"], figures["IDR"]) == (pytest.approx(40.0), pytest.approx(50.0))
    assert figures["DetA@2m"] == pytest.approx(80.0) and figures["AssA@2m"] == pytest.approx(50.0)
    assert figures["HOTA@2m"] == pytest.approx(100 * np.sqrt(0.4))
    assert figures["DetA"] == pytest.approx(80.0 * 17 / 19)
    # two sequences pool their counts (a second, perfectly tracked one)
    perfect = [FrameTracks(np.zeros((1, 2)), np.array([3]), np.zeros((1, 2)), np.array([5])) for _ in range(4)]
    both = tracking_metrics({"one": frames, "two": perfect})
    assert (both["TP"], both["FP"], both["IDSW"], both["objects"]) == (8, 1, 1, 8)
    assert both["MOTA"] == pytest.approx(100 * (1 - 2 / 8))


def test_nothing_tracked_or_nothing_to_track():
    empty = [FrameTracks(np.zeros((2, 2)), np.array([1, 2]), np.zeros((0, 2)), np.zeros(0, np.int64))]
    figures = tracking_metrics({"a": empty})
    assert figures["FN"] == 2 and figures["IDF1"] == 0.0 and figures["MOTA"] == 0.0
    false = [FrameTracks(np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros((1, 2)), np.array([4]))]
    assert tracking_metrics({"a": false})["FP"] == 1
