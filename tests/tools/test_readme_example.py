"""The top-level README's curl example: its JSON answer is what the command gives on the shipped model.

The command posts frames 1 then 2 of tiny_foggy to a fresh stream `demo` (multipart, ?flow=false); the README shows
the second answer. When the shipped model changes, regenerate the block with
    python -m tools.readme_example "$RAFD_RADIATE_SAMPLE" --write README.md
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tools.readme_example import EXAMPLE_BEGIN, FRAMES, QUERY, STREAM_ID, example_answer, read_block, shown

README = Path(__file__).resolve().parents[2] / "README.md"
# Odometry and onnxruntime on another CPU may differ in the last digits: tolerances far below a 17 cm pixel.
POSE_ATOL, BOX_ATOL, SCORE_ATOL, POLYGON_ATOL = 2e-3, 2e-3, 2e-3, 0.05


def test_the_readme_command_is_the_one_reproduced():
    readme = README.read_text()
    command = readme[: readme.index(EXAMPLE_BEGIN)].rsplit("```bash", 1)[1]
    assert f"for i in {' '.join(map(str, FRAMES))}" in command
    assert f"-F stream_id={STREAM_ID}" in command and "-F timestamp=$i" in command
    assert "Navtech_Cartesian/00000$i.png" in command and f"/detect{QUERY}" in command


def test_the_readme_answer_is_what_the_command_gives_on_the_shipped_model(radiate_sample: Path):
    pytest.importorskip("onnxruntime", reason="the shipped model runs on onnxruntime (serve extra)")
    readme = read_block(README.read_text())
    served = shown(example_answer(radiate_sample))
    for key in (
        "stream_id",
        "timestamp",
        "frames_used",
        "num_frames",
        "warming_up",
        "pose_source",
        "flow",
        "input",
        "model",
    ):
        assert readme[key] == served[key], key
    assert set(readme) == set(served) and set(readme["timing"]) == set(served["timing"])
    np.testing.assert_allclose(
        [readme["pose"][k] for k in ("x", "y", "yaw")], [served["pose"][k] for k in ("x", "y", "yaw")], atol=POSE_ATOL
    )
    assert len(readme["boxes"]) == len(served["boxes"]), "regenerate the README block: the answer changed"
    for shown_box, box in zip(readme["boxes"], served["boxes"]):
        assert shown_box["class"] == box["class"] and shown_box["class_id"] == box["class_id"]
        np.testing.assert_allclose(
            [shown_box[k] for k in ("x", "y", "width", "length", "yaw")],
            [box[k] for k in ("x", "y", "width", "length", "yaw")],
            atol=BOX_ATOL,
        )
        assert shown_box["score"] == pytest.approx(box["score"], abs=SCORE_ATOL)
        np.testing.assert_allclose(shown_box["polygon"], box["polygon"], atol=POLYGON_ATOL)
