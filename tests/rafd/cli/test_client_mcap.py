"""rafd-client --mcap: the log read back with the mcap reader holds every topic in Foxglove's schemas, one message
per frame, and the service's own answer (boxes, poses, flow, ground truth), on a loopback rafd-serve."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from rafd.cli.client import main  # noqa: E402
from rafd.data import read_sequence  # noqa: E402
from service.app import create_app  # noqa: E402
from service.settings import Settings  # noqa: E402
from tests.utils.service_testing import serve_in_thread, wait_ready  # noqa: E402

pytest.importorskip("foxglove", reason="MCAP logs need the logs extra (foxglove-sdk)")
from mcap.reader import make_reader  # noqa: E402
from mcap_protobuf.decoder import DecoderFactory  # noqa: E402

SCHEMAS = {
    "/radar/scan": "foxglove.CompressedImage",
    "/radar/scan/grid": "foxglove.Grid",
    "/tf": "foxglove.FrameTransform",
    "/radar/detections": "foxglove.SceneUpdate",
    "/radar/detections/image": "foxglove.ImageAnnotations",
    "/radar/flow": "foxglove.SceneUpdate",
    "/radar/velocity": "foxglove.SceneUpdate",
    "/radar/ground_truth": "foxglove.SceneUpdate",
    "/radar/ground_truth/image": "foxglove.ImageAnnotations",
}


def read_log(path: Path) -> tuple[dict[str, str], dict[str, int], dict[str, list], dict[str, dict[str, str]]]:
    """-> ({topic: schema}, {topic: message count}, {topic: [(log_time, decoded message)]}, {metadata name: values})."""
    with path.open("rb") as handle:
        reader = make_reader(handle, validate_crcs=True, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert all(channel.message_encoding == "protobuf" for channel in summary.channels.values())
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        counts = {c.topic: summary.statistics.channel_message_counts[c.id] for c in summary.channels.values()}
        messages: dict[str, list] = {}
        for _, channel, message, decoded in reader.iter_decoded_messages():
            messages.setdefault(channel.topic, []).append((message.log_time, decoded))
        metadata = {record.name: dict(record.metadata) for record in reader.iter_metadata()}
    return schemas, counts, messages, metadata


def yaw_of(quaternion) -> float:
    """Rotation about z of a z-only quaternion."""
    assert abs(quaternion.x) < 1e-12 and abs(quaternion.y) < 1e-12
    return 2.0 * math.atan2(quaternion.z, quaternion.w)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 labelled full-size frames (the fake model crops 128 px at offset 512), with poses and polar scans."""
    from rafd.sim import Difficulty
    from rafd.sim.sequence import run_simulation
    from rafd.sim.writer import write_sequence

    truth = run_simulation(1, 4, "test", 1152, Difficulty(), name="sim_mcap")
    return write_sequence(truth, tmp_path_factory.mktemp("client_mcap") / "sim_mcap", polar=True)


def check_log_against_answers(path: Path, answers: list[dict], folder: Path, labelled: bool) -> dict[str, list]:
    schemas, counts, messages, metadata = read_log(path)
    expected = {t: s for t, s in SCHEMAS.items() if labelled or "ground_truth" not in t}
    assert schemas == expected
    frames = len(answers)
    with_flow = sum(a["flow"] is not None for a in answers)
    assert counts == {t: (with_flow if t == "/radar/flow" else frames) for t in expected}
    sequence = read_sequence(folder, estimate_poses=False)
    stamps = [f.timestamp_ns for f in sequence.frames][:frames]
    for topic, logged in messages.items():
        times = [t for t, _ in logged]
        assert times == (stamps[frames - len(times) :] if topic == "/radar/flow" else stamps)  # the scans' own times
    assert metadata["rafd-client"]["frames"] == str(frames)
    for k, answer in enumerate(answers):
        _, update = messages["/radar/detections"][k]
        entities = {e.id: e for e in update.entities}
        assert len(entities) == len(answer["boxes"]) and update.deletions[0].type == 1  # ALL older entities go
        _, annotations = messages["/radar/detections/image"][k]
        assert len(annotations.points) == len(answer["boxes"])
        for index, box in enumerate(answer["boxes"]):
            cube = entities[f"pred-{index}"].cubes[0]
            assert (cube.pose.position.x, cube.pose.position.y) == pytest.approx((box["x"], box["y"]), abs=1e-9)
            assert (cube.size.x, cube.size.y) == pytest.approx((box["width"], box["length"]), abs=1e-9)
            assert math.remainder(yaw_of(cube.pose.orientation) - box["yaw"], 2 * math.pi) == pytest.approx(0, abs=1e-9)
            assert entities[f"pred-{index}"].frame_id == "radar"
            outline = [(p.x, p.y) for p in annotations.points[index].points]
            np.testing.assert_allclose(outline, box["polygon"], atol=1e-9)
        _, transform = messages["/tf"][k]
        assert (transform.parent_frame_id, transform.child_frame_id) == ("world", "radar")
        assert (transform.translation.x, transform.translation.y) == pytest.approx(
            (answer["pose"]["x"], answer["pose"]["y"])
        )
        assert yaw_of(transform.rotation) == pytest.approx(answer["pose"]["yaw"], abs=1e-9)
        _, image = messages["/radar/scan"][k]
        scan = sequence.frames[k].load()
        assert image.format == "png"
        np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_GRAYSCALE), scan)
        _, velocities = messages["/radar/velocity"][k]  # one arrow per box with a ground velocity
        moving = [b for b in answer["boxes"] if b["velocity"] and (b["velocity"]["x"], b["velocity"]["y"]) != (0, 0)]
        assert len(velocities.entities[0].arrows) == len(moving)
        _, grid = messages["/radar/scan/grid"][k]
        offset, size = answer["input"]["covered"]["offset_px"], answer["input"]["covered"]["side_px"]
        assert grid.column_count == size and grid.row_stride == size and grid.fields[0].name == "intensity"
        cells = np.frombuffer(grid.data, np.uint8).reshape(size, size)[::-1]  # row 0 of a Grid is its smallest y
        np.testing.assert_array_equal(cells, scan[offset : offset + size, offset : offset + size])
        if labelled:
            _, truth = messages["/radar/ground_truth"][k]
            objects = sequence.frames[k].objects
            assert len(truth.entities) == len(objects)
            for entity, obj in zip(truth.entities, objects):
                assert (entity.cubes[0].pose.position.x, entity.cubes[0].size.y) == pytest.approx(
                    (obj.box[0], obj.box[3])
                )
    return messages


def test_mcap_log_holds_the_services_answers(simulated: Path, service_url: str, tmp_path: Path):
    log, out = tmp_path / "run.mcap", tmp_path / "out"
    assert main([str(simulated), "--url", service_url, "--mcap", str(log), "--out", str(out)]) == 0
    answers = [json.loads(line) for line in (out / "answers.jsonl").read_text().splitlines()]
    assert len(answers) == 4 and all(a["boxes"] for a in answers) and answers[1]["flow"] is not None
    messages = check_log_against_answers(log, answers, simulated, labelled=True)
    # Flow arrows: one per valid cell (the answer's validity) moving more than 5 cm, tail + length = where the
    # cell's content is now.
    flow = answers[-1]["flow"]
    values = np.asarray(flow["values"])  # [2, Hf, Wf]
    speed = np.hypot(values[0], values[1])
    valid = np.asarray(flow["validity"]) >= flow["validity_min"]
    drawn = (speed > 0.05) & valid
    assert 0 < drawn.sum() < (speed > 0.05).sum()  # the outer ring at least is not drawn
    _, update = messages["/radar/flow"][-1]
    arrows = update.entities[0].arrows
    assert len(arrows) == drawn.sum()
    lengths = sorted(a.shaft_length + a.head_length for a in arrows)
    np.testing.assert_allclose(lengths, sorted(speed[drawn]), atol=1e-9)


def test_polar_only_folder_is_posted_polar_and_logged_converted(simulated: Path, service_url: str, tmp_path: Path):
    polar = Path(shutil.copytree(simulated, tmp_path / "polar_only"))
    shutil.rmtree(polar / "Navtech_Cartesian")
    (polar / "Navtech_Cartesian.txt").unlink()
    log, out = tmp_path / "polar.mcap", tmp_path / "out"
    assert main([str(polar), "--url", service_url, "--mcap", str(log), "--out", str(out), "--limit", "2"]) == 0
    answers = [json.loads(line) for line in (out / "answers.jsonl").read_text().splitlines()]
    assert [a["input"]["posted_size"] for a in answers] == [1152, 1152]  # meta.json's image_size
    assert [a["input"]["posted_format"] for a in answers] == ["polar", "polar"]  # posted as on disk
    check_log_against_answers(log, answers, polar, labelled=True)


def test_unlabelled_folder_logs_no_ground_truth_and_bad_paths_fail(
    simulated: Path, service_url: str, tmp_path: Path, capsys: pytest.CaptureFixture
):
    bare = Path(shutil.copytree(simulated, tmp_path / "bare"))
    shutil.rmtree(bare / "annotations")
    log = tmp_path / "bare.mcap"
    assert main([str(bare), "--url", service_url, "--mcap", str(log), "--limit", "2", "--stream-id", "bare"]) == 0
    schemas, _, _, _ = read_log(log)
    assert not any("ground_truth" in topic for topic in schemas)
    assert main([str(bare), "--url", service_url, "--mcap", str(tmp_path / "no" / "such" / "run.mcap")]) == 2
    assert "--mcap" in capsys.readouterr().err


def test_mcap_log_of_the_shipped_model_on_real_frames(radiate_sample: Path, tmp_path: Path):
    """End to end on the real service path (shipped ONNX model, odometry) and real RADIATE frames: whatever the
    shipped model answers is what the log holds."""
    with serve_in_thread(create_app(Settings(threads=1))) as url:
        import httpx

        with httpx.Client(base_url=url) as http:
            wait_ready(http, timeout=60.0)
        log, out = tmp_path / "real.mcap", tmp_path / "out"
        assert main([str(radiate_sample), "--url", url, "--mcap", str(log), "--out", str(out), "--limit", "3"]) == 0
    answers = [json.loads(line) for line in (out / "answers.jsonl").read_text().splitlines()]
    check_log_against_answers(log, answers, radiate_sample, labelled=True)
