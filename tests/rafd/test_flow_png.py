"""rafd.flow_png: the flow and its validity through PNG and back, to the millimetre and exactly."""

from __future__ import annotations

import numpy as np
import pytest

from rafd import flow_png


def test_the_flow_comes_back_to_the_millimetre_and_the_validity_exactly() -> None:
    rng = np.random.default_rng(0)
    flow = rng.normal(0.0, 2.0, (2, 48, 40))
    back = flow_png.decode_flow(flow_png.encode_flow(flow), flow.shape)
    assert back.shape == flow.shape and np.abs(back - flow).max() <= 0.0005 + 1e-12
    steps = rng.integers(0, 101, (48, 40))
    np.testing.assert_array_equal(flow_png.decode_steps(flow_png.encode_steps(steps), (48, 40)), steps / 100.0)


def test_a_still_flow_is_small_and_other_images_are_refused() -> None:
    assert (
        len(flow_png.encode_flow(np.zeros((2, 288, 288)))) < 4000
    )  # a whole scan of zeros: a few kilobytes (332 kB raw)
    with pytest.raises(ValueError, match="not a greyscale uint16 PNG"):
        flow_png.decode_flow(flow_png.encode_steps(np.zeros((4, 4))), (2, 2, 4))
