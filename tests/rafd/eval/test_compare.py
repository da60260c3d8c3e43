"""Paired bootstrap over drives: exact at unit weights, exact under resampling, and able to tell models apart."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rafd.eval.compare import FrameDetections, _Scored, load_detections, paired_bootstrap, save_detections
from rafd.eval.predict import FrameResult, summarise


def make_frames(seed: int = 0, drives: int = 6, frames_per_drive: int = 5) -> list[FrameDetections]:
    """Vehicles with noisy detections (some missed, some boxes poor) and false positives, continuous scores."""
    rng = np.random.default_rng(seed)
    out = []
    for d in range(drives):
        for f in range(frames_per_drive):
            n = int(rng.integers(0, 5))
            truth = np.column_stack(
                [rng.uniform(-20, 20, (n, 2)), np.full(n, 2.0), np.full(n, 4.6), rng.uniform(-np.pi, np.pi, n)]
            )
            found = truth[rng.random(n) < 0.7].copy()
            found[:, :2] += rng.normal(0, 0.6, (len(found), 2))
            found[:, 4] += rng.normal(0, 0.3, len(found))
            false = np.column_stack(
                [
                    rng.uniform(-20, 20, (k := int(rng.integers(0, 4)), 2)),
                    np.full(k, 2.0),
                    np.full(k, 4.6),
                    rng.uniform(-np.pi, np.pi, k),
                ]
            )
            boxes = np.concatenate([found, false])
            scores = np.concatenate([rng.uniform(0.3, 1.0, len(found)), rng.uniform(0.0, 0.8, len(false))])
            out.append(FrameDetections(f"drive_{d}", f + 1, np.column_stack([boxes, scores]), truth))
    return out


FIGURES = ("mAP@0.3", "mAP@0.5", "mAP@0.7", "centre_AP", "recall_at_1fp")


def evaluated(frames: list[FrameDetections]) -> dict:
    """rafd-eval's figures (rafd.eval.predict.summarise) of the same frames."""
    return summarise(
        [
            FrameResult(f.sequence, f.frame, f.predictions, f.ground_truth, float("nan"), float("nan"), 0, 0)
            for f in frames
        ]
    )


def test_unit_weights_give_the_evaluations_figures() -> None:
    frames = make_frames()
    expected = evaluated(frames)
    got = _Scored(frames).metrics(np.ones(len(frames)))
    for name in FIGURES:
        assert got[name] == pytest.approx(expected[name], abs=1e-9), name


def test_integer_weights_equal_duplicated_frames() -> None:
    # a resample that draws a drive twice must score as if its frames were there twice
    frames = make_frames(seed=1)
    weights = np.random.default_rng(2).integers(0, 3, len(frames)).astype(float)
    duplicated = [f for f, w in zip(frames, weights) for _ in range(int(w))]
    expected = evaluated(duplicated)
    got = _Scored(frames).metrics(weights)
    for name in FIGURES:
        assert got[name] == pytest.approx(expected[name], abs=1e-9), name


def test_identical_models_differ_by_nothing() -> None:
    frames = make_frames()
    result = paired_bootstrap(frames, list(reversed(frames)), resamples=50)  # order does not matter
    for row in result.values():
        assert row["difference"] == 0 and row["low"] == 0 and row["high"] == 0 and row["p_better"] == 0


def test_a_clearly_worse_model_is_called_worse() -> None:
    frames = make_frames(seed=3, drives=8)
    rng = np.random.default_rng(4)
    worse = []
    for f in frames:  # confident false positives in every frame
        clutter = np.column_stack(
            [rng.uniform(30, 40, (3, 2)), np.full(3, 2.0), np.full(3, 4.6), np.zeros(3), rng.uniform(0.9, 1.0, 3)]
        )
        worse.append(FrameDetections(f.sequence, f.frame, np.concatenate([f.predictions, clutter]), f.ground_truth))
    result = paired_bootstrap(frames, worse, resamples=300, seed=1)
    for name in ("centre_AP", "mAP@0.3", "recall_at_1fp"):
        row = result[name]
        assert row["difference"] < 0 and row["low"] <= row["difference"] <= row["high"] < 0, (name, row)
        assert row["p_better"] == 0.0


def test_frames_must_match(tmp_path: Path) -> None:
    frames = make_frames()
    with pytest.raises(ValueError, match="same frames"):
        paired_bootstrap(frames, frames[:-1], resamples=5)
    with pytest.raises(ValueError, match="resamples"):
        paired_bootstrap(frames, frames, resamples=0)


def test_detections_round_trip(tmp_path: Path) -> None:
    frames = make_frames()
    frames.append(FrameDetections("empty", 9, np.zeros((0, 6)), np.zeros((0, 5))))
    path = tmp_path / "sub" / "dets"  # no .npz suffix: written where asked
    save_detections(path, frames)
    back = load_detections(path)
    assert [(f.sequence, f.frame) for f in back] == [(f.sequence, f.frame) for f in frames]
    for a, b in zip(frames, back):
        np.testing.assert_array_equal(a.predictions, b.predictions)
        np.testing.assert_array_equal(a.ground_truth, b.ground_truth)
    (tmp_path / "bad.npz").write_bytes(b"not an npz")
    with pytest.raises(ValueError, match="not a detections file"):
        load_detections(tmp_path / "bad.npz")
