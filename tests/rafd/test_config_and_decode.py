import subprocess
import sys

import numpy as np
import pytest

from rafd.config import RaFDConfig
from rafd.detections import decode_detections


def test_import_rafd_does_not_import_torch():
    code = "import sys, rafd, rafd.geometry, rafd.detections; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_config_json_round_trip_and_validation():
    for cfg in (RaFDConfig.paper(), RaFDConfig.tiny(), RaFDConfig.tiny(num_frames=1)):
        assert RaFDConfig.from_json(cfg.to_json()) == cfg
    with pytest.raises(ValueError, match="num_frames"):
        RaFDConfig.tiny(num_frames=3)
    with pytest.raises(ValueError, match="unknown"):
        RaFDConfig.from_dict({"bogus": 1})
    assert RaFDConfig.paper().feature_size == 64 and RaFDConfig.tiny().feature_size == 32


def test_decode_thresholds_and_sorts():
    boxes = np.arange(20, dtype=float).reshape(4, 5)
    scores = np.array([0.2, 0.9, np.nan, 0.5])
    det = decode_detections(boxes, scores, score_threshold=0.3)
    np.testing.assert_array_equal(det.scores, [0.9, 0.5])
    np.testing.assert_array_equal(det.boxes, boxes[[1, 3]])
    assert det.as_array().shape == (2, 6)
