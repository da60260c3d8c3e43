"""rafd.preprocess: the one path from a scan to the model's input frame."""

import numpy as np
import pytest

from rafd.preprocess import model_crop, model_frame, to_model_input


def test_model_crop_keeps_the_radar_at_the_centre():
    scan = np.zeros((1152, 1152), np.uint8)
    scan[576, 576] = 200  # the pixel just below-right of the radar point
    crop = model_crop(scan, 256)
    assert crop.shape == (256, 256) and crop.flags.c_contiguous
    assert crop[128, 128] == 200 and crop.sum() == 200


def test_model_input_is_grey_over_255():
    crop = np.arange(256, dtype=np.uint8).reshape(16, 16)
    frame = to_model_input(crop)
    assert frame.dtype == np.float32 and frame.min() == 0.0 and frame.max() == 1.0
    np.testing.assert_allclose(frame, crop / 255.0, atol=1e-7)
    np.testing.assert_array_equal(model_frame(crop, 16), frame)


@pytest.mark.parametrize("bad", [np.zeros((10, 12), np.uint8), np.zeros((3, 3, 3), np.uint8)])
def test_non_square_scans_are_refused(bad):
    with pytest.raises(ValueError, match="square"):
        model_crop(bad, 2)


def test_odd_crop_difference_and_non_uint8_are_refused():
    with pytest.raises(ValueError, match="odd"):
        model_crop(np.zeros((11, 11), np.uint8), 4)
    with pytest.raises(ValueError, match="8-bit"):
        to_model_input(np.zeros((4, 4), np.float32))
