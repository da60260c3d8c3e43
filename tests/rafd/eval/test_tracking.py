"""rafd.eval.tracking: the tracker run over synthetic streams and scored: identities kept, velocity errors, the
baselines, and confirmation removing lone false positives (does time help detection)."""

from __future__ import annotations

import numpy as np
import pytest

from rafd.eval.tracking import evaluate_tracking, run_tracker, sequences_of
from rafd.eval.tracking_inputs import TrackingFrame
from rafd.eval.tracking_table import format_tracking
from rafd.tracking import TrackerSettings

PERIOD = 0.25


def synthetic_frames(name: str, count: int, seed: int, false_per_scan: int = 2) -> list[TrackingFrame]:
    """Three vehicles (one parked) seen by a detector with 0.1 m of noise (score 0.6) and `false_per_scan` lone false
    boxes per scan at random places (score 0.9: no threshold separates them); the ego drives 5 m/s north."""
    rng = np.random.default_rng(seed)
    start = np.array([[10.0, 0.0], [-10.0, 30.0], [5.0, -20.0]])
    velocity = np.array([[0.0, 8.0], [3.0, -4.0], [0.0, 0.0]])
    frames = []
    for k in range(count):
        pose = np.array([1000.0, 2000.0 + 5.0 * PERIOD * k, 0.0])
        world = start + velocity * PERIOD * k
        ego = world - pose[:2]
        truth = np.concatenate([ego, np.tile([1.8, 4.5, 0.0], (3, 1))], 1)
        found = truth.copy()
        found[:, :2] += rng.normal(0.0, 0.1, (3, 2))
        false = np.concatenate(
            [rng.uniform(-60, 60, (false_per_scan, 2)), np.tile([1.8, 4.5, 0.0], (false_per_scan, 1))], 1
        )
        detections = np.concatenate(
            [
                np.concatenate([found, np.full((3, 1), 0.6)], 1),
                np.concatenate([false, np.full((false_per_scan, 1), 0.9)], 1),
            ]
        )
        frames.append(
            TrackingFrame(
                sequence=name,
                frame=k + 1,
                timestamp=100.0 + PERIOD * k,
                pose=pose,
                detections=detections,
                truth=truth,
                truth_ids=np.array([1, 2, 3]),
                truth_velocity=velocity.copy(),
                ignore=np.zeros((0, 5)),
                flow=None,
                condition="clear" if seed % 2 else "fog",
            )
        )
    return frames


def test_tracks_and_velocities_of_synthetic_streams_are_scored():
    frames = synthetic_frames("a", 16, 1) + synthetic_frames("b", 16, 2)
    report = evaluate_tracking(frames, 0.5, TrackerSettings("filter"), velocity_truth="simulator")
    assert report["sequences"] == 2 and report["frames"] == 32
    assert report["identity_kept"]["percent"] == 100.0 and report["identity_kept"]["pairs"] == 2 * 15 * 3
    tracking = report["tracking"]
    assert tracking["IDSW"] == 0 and tracking["FN"] == 0 and tracking["FP"] == 2 * 16 * 2  # lone boxes answered
    velocity = report["velocity"]
    assert velocity["matched"] == 96 and velocity["coverage"] == pytest.approx(100 * 90 / 96)  # first scans: none
    assert velocity["mean"] < 0.5
    # the baselines: no flow here, so the flow baseline has no velocity; differencing is noisier than the filter
    assert report["baselines"]["flow_centre_unchecked"]["with_velocity"] == 0
    assert report["baselines"]["centre_differencing"]["mean"] > velocity["mean"]
    assert set(report["candidates"]) == {"flow_centre", "flow_box", "filter", "filter_flow"}
    assert set(report["by_condition"]) == {"clear", "fog"}
    # does time help detection: two lone false boxes per scan scoring above every vehicle
    study = report["time_helps_detection"]
    assert study["detections"]["at_budget"]["recall"] == 0.0  # <= 1 false box per scan costs every vehicle
    confirmed = study["confirmed"]["at_budget"]
    assert confirmed["recall"] > 90.0 and confirmed["fp_per_frame"] < 0.1  # two lone boxes rarely meet again
    text = format_tracking(report)
    assert "HOTA" in text and "candidate filter" in text and "does time help detection" in text


def test_coasting_boxes_in_ignore_regions_are_not_answered():
    frames = synthetic_frames("a", 6, 3, false_per_scan=0)
    hidden = frames[:3] + [
        TrackingFrame(
            **{**f.__dict__, "detections": f.detections[1:], "ignore": np.array([[*f.truth[0, :2], 20.0, 20.0, 0.0]])}
        )
        for f in frames[3:]
    ]
    settings = TrackerSettings("filter", answer_coasting=True)
    answers = run_tracker(sequences_of(hidden)["a"], settings, 0.5)
    assert [len(a) for a in answers] == [3, 3, 3, 2, 2, 2]
    shown = frames[:3] + [TrackingFrame(**{**f.__dict__, "detections": f.detections[1:]}) for f in frames[3:]]
    assert [len(a) for a in run_tracker(sequences_of(shown)["a"], settings, 0.5)] == [3, 3, 3, 3, 3, 3]
