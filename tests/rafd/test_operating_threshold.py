"""rafd.protocol.OperatingThreshold and rafd.detections.answered: which detections are answered, near and far."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rafd.detections import answered, answered_mask
from rafd.protocol import DEFAULT_SCORE_THRESHOLD, OperatingThreshold, operating_threshold

FAR = OperatingThreshold(0.35, far=0.45, far_from_m=50.0)


def test_the_far_threshold_applies_from_its_range_outwards():
    assert FAR.lowest == 0.35 and OperatingThreshold(0.5, far=0.4, far_from_m=10.0).lowest == 0.4
    predictions = np.array(
        [
            [30.0, 40.0, 2, 4, 0, 0.40],  # 50 m out: far, 0.40 < 0.45, not answered
            [30.0, 39.0, 2, 4, 0, 0.40],  # 49.2 m: near, answered
            [-60.0, 0.0, 2, 4, 0, 0.46],  # far, answered
            [0.0, 10.0, 2, 4, 0, 0.34],  # near, below 0.35
            [0.0, 10.0, 2, 4, 0, np.nan],  # no score, never answered
        ]
    )
    np.testing.assert_array_equal(answered(predictions, FAR), predictions[[1, 2]])
    np.testing.assert_array_equal(answered_mask(predictions[:, :2], predictions[:, 5], 0.3), [1, 1, 1, 1, 0])


def test_a_model_s_thresholds_are_read_from_checkpoint_meta_or_onnx_text():
    meta = {"operating_threshold": 0.35, "operating_threshold_far": {"from_m": 50, "threshold": 0.45}}
    assert operating_threshold(meta) == FAR
    text = {"operating_threshold": "0.35", "operating_threshold_far": json.dumps({"from_m": 50, "threshold": 0.45})}
    assert operating_threshold(text) == FAR
    assert operating_threshold({"operating_threshold": 0.35}) == OperatingThreshold(0.35)
    assert operating_threshold(None) == OperatingThreshold(DEFAULT_SCORE_THRESHOLD)
    assert operating_threshold(meta, override=0.5) == OperatingThreshold(0.5)  # the user's, at every range
    assert str(FAR) == "0.350 within 50 m, 0.450 beyond"


@pytest.mark.parametrize(
    "far",
    [{"from_m": 50}, "not json", {"from_m": 50, "threshold": 1.5}, {"from_m": -1, "threshold": 0.4}],
)
def test_a_malformed_far_threshold_is_refused_naming_it(far):
    with pytest.raises(ValueError, match="far|threshold"):
        operating_threshold({"operating_threshold": 0.35, "operating_threshold_far": far})
