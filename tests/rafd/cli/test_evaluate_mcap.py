"""rafd-eval --mcap: one Foxglove/MCAP log per sequence holding each window's newest frame, the model's boxes and
flow and the protocol's ground truth, read back with the mcap reader."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="MCAP logs need the logs extra (foxglove-sdk)")
from mcap.reader import make_reader  # noqa: E402
from mcap_protobuf.decoder import DecoderFactory  # noqa: E402

from rafd.cli.evaluate import main  # noqa: E402


def read_log(path: Path) -> tuple[dict[str, str], dict[str, int], dict[str, list]]:
    with path.open("rb") as handle:
        reader = make_reader(handle, validate_crcs=True, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        counts = {c.topic: summary.statistics.channel_message_counts[c.id] for c in summary.channels.values()}
        messages: dict[str, list] = {}
        for _, channel, message, decoded in reader.iter_decoded_messages():
            messages.setdefault(channel.topic, []).append((message.log_time, decoded))
    return schemas, counts, messages


def test_eval_writes_one_log_per_sequence(trained_checkpoint: Path, sim_root: Path, tmp_path: Path) -> None:
    logs, report = tmp_path / "logs", tmp_path / "metrics.json"
    assert (
        main(
            [
                str(trained_checkpoint),
                str(sim_root),
                "--split",
                "train",
                "--mcap-dir",
                str(logs),
                "--json",
                str(report),
                "--device",
                "cpu",
                "--quiet",
            ]
        )
        == 0
    )
    assert sorted(p.name for p in logs.glob("*.mcap")) == ["sim_12_0.mcap", "sim_12_1.mcap"]
    frames = json.loads(report.read_text())["per_sequence"]["sim_12_0"]["frames"]
    schemas, counts, messages = read_log(logs / "sim_12_0.mcap")
    assert (
        schemas["/radar/scan"] == "foxglove.CompressedImage"
        and schemas["/radar/ground_truth"] == "foxglove.SceneUpdate"
    )
    assert schemas["/radar/flow"] == "foxglove.SceneUpdate" and schemas["/tf"] == "foxglove.FrameTransform"
    assert set(counts.values()) == {frames} and len(counts) == 8  # every topic, every window, flow included
    times = [t for t, _ in messages["/radar/scan"]]
    assert times == sorted(times) and len(set(times)) == frames


def test_logged_boxes_are_the_models_predictions(trained_checkpoint: Path, sim_root: Path, tmp_path: Path) -> None:
    from rafd.data.windows import open_windows
    from rafd.eval.mcap import write_evaluation_logs
    from rafd.eval.predict import predict
    from rafd.model.checkpoint import load_checkpoint

    model, cfg, _ = load_checkpoint(trained_checkpoint, map_location="cpu")
    dataset = open_windows(sim_root, "train", cfg)
    results = predict(model.eval(), dataset, cfg, "cpu", keep_flow=True, progress=False)
    paths = write_evaluation_logs(tmp_path, dataset, results, cfg, "ckpt", score_threshold=0.0)  # every query
    _, _, messages = read_log(paths[0])
    first = next(r for r in results if r.sequence == paths[0].stem)
    _, update = messages["/radar/detections"][0]
    assert len(update.entities) == len(first.predictions) > 0
    cube = next(e for e in update.entities if e.id == "pred-0").cubes[0]
    x, y, width, length, yaw, _ = first.predictions[0]
    assert (cube.pose.position.x, cube.pose.position.y, cube.size.x, cube.size.y) == pytest.approx(
        (x, y, width, length)
    )
    assert math.remainder(
        2 * math.atan2(cube.pose.orientation.z, cube.pose.orientation.w) - yaw, 2 * math.pi
    ) == pytest.approx(0.0, abs=1e-6)
    truths = 0
    for path in paths:  # the protocol's ground truth, frame by frame
        ordered = sorted((r for r in results if r.sequence == path.stem), key=lambda r: r.frame)
        for (_, truth), result in zip(read_log(path)[2]["/radar/ground_truth"], ordered):
            logged = [[e.cubes[0].pose.position.x, e.cubes[0].pose.position.y] for e in truth.entities]
            np.testing.assert_allclose(np.reshape(logged, (-1, 2)), result.ground_truth[:, :2].reshape(-1, 2))
            truths += len(logged)
    assert truths > 0
    _, flow = messages["/radar/flow"][0]
    moving = (np.hypot(*first.flow) > 0.05).sum()
    arrows = flow.entities[0].arrows
    # only moving cells whose flow is valid (rafd.flow_validity): never the ring the search cannot measure from
    assert 0 < len(arrows) <= moving
    from rafd.flow_validity import search_reach_m
    from rafd.model.checkpoint import read_checkpoint

    cfg = read_checkpoint(trained_checkpoint)[1]
    edge = 0.5 * cfg.input_size * cfg.resolution - 0.5 * cfg.flow.stride * cfg.resolution
    reach = search_reach_m(cfg.flow.stride, cfg.resolution, cfg.flow.local_radius)
    for arrow in arrows:  # an arrow's base is its cell's centre
        assert max(abs(arrow.pose.position.x), abs(arrow.pose.position.y)) <= edge - reach + 1e-3


def test_mcap_without_the_logs_extra_or_checkpoint_fails_clearly(
    sim_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main([str(tmp_path / "none.pt"), str(sim_root), "--split", "train", "--mcap-dir", str(tmp_path)]) == 2
    assert "none.pt" in capsys.readouterr().err
