"""The service on the SHIPPED model (ONNX, streaming) answers what offline PyTorch inference answers.

Offline references: for crops posted at the model's size, the shipped checkpoint's model.forward on the same padded
window (export.verify.window_from_history) at the poses the service reports using; for whole scans, `rafd eval
--full-scan`'s own prediction (rafd.eval.fullscan) on the same scans and poses.
"""

from __future__ import annotations

from collections.abc import Iterator

import cv2
import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.utils.service_testing import b64png, serve_in_thread, wait_ready

torch = pytest.importorskip("torch", reason="the offline PyTorch reference needs the train extra")

from export.verify import window_from_history  # noqa: E402
from rafd.assets import default_checkpoint, default_onnx  # noqa: E402
from rafd.detections import decode_detections  # noqa: E402
from rafd.model.checkpoint import load_checkpoint  # noqa: E402
from rafd.runtime import OnnxRunner  # noqa: E402
from service.app import create_app  # noqa: E402
from service.settings import Settings  # noqa: E402

THRESHOLD = 0.3
# Streaming ORT vs PyTorch: float32 differences of ~1e-5; the answer rounds boxes to 0.1 mm and flow to 1 mm.
BOX_ATOL, SCORE_ATOL, FLOW_ATOL = 2e-3, 1e-3, 2e-3


@pytest.fixture(scope="module")
def shipped() -> tuple[OnnxRunner, torch.nn.Module]:
    runner = OnnxRunner(default_onnx(), threads=1)
    model, cfg, _ = load_checkpoint(default_checkpoint())
    assert cfg == runner.config, "the shipped ONNX and checkpoint were made from different configs"
    return runner, model


@pytest.fixture
def client(shipped) -> Iterator[TestClient]:
    runner, _ = shipped
    with TestClient(create_app(Settings(threads=1, score_threshold=THRESHOLD), runner=runner)) as test_client:
        wait_ready(test_client, timeout=60.0)
        yield test_client


def offline(model: torch.nn.Module, crops: list[np.ndarray], poses: list[np.ndarray]) -> dict[str, np.ndarray]:
    """PyTorch on the newest padded window of a history of uint8 crops and world poses."""
    frames, window_poses = window_from_history(crops, np.asarray(poses), model.num_frames)
    x = torch.from_numpy(np.stack(frames).astype(np.float32) / 255.0)[None, :, None]  # [1, T, 1, S, S]
    p = torch.from_numpy(window_poses.astype(np.float32))[None]  # [1, T, 3]
    with torch.no_grad():
        out = model(x, p)
    return {k: v[0].numpy() for k, v in out.items()}


def assert_same_answer(answer: dict, reference: dict[str, np.ndarray], frames_used: int) -> None:
    served = np.array([[b["x"], b["y"], b["width"], b["length"], b["yaw"], b["score"]] for b in answer["boxes"]])
    served = served.reshape(-1, 6)
    scores = reference["scores"]
    boxes = reference["boxes"]
    # Every clear offline detection is served, and every served box is an offline detection (as sets:
    # top-K ties may order differently; scores within the tolerance of the threshold may go either way).
    clear = decode_detections(boxes, scores, THRESHOLD + SCORE_ATOL)
    loose = decode_detections(boxes, scores, THRESHOLD - SCORE_ATOL)
    loose_rows = np.column_stack([loose.boxes, loose.scores]) if len(loose.scores) else np.zeros((0, 6))
    assert len(clear.scores) <= len(served) <= len(loose_rows)
    for row in served:
        distance = np.abs(loose_rows[:, :2] - row[:2]).max(axis=1)
        match = loose_rows[int(np.argmin(distance))]
        yaw_diff = np.angle(np.exp(1j * (match[4] - row[4])))
        assert np.abs(match[:4] - row[:4]).max() < BOX_ATOL and abs(yaw_diff) < BOX_ATOL, (row, match)
        assert abs(match[5] - row[5]) < SCORE_ATOL
    if frames_used >= 2:
        flow = np.asarray(answer["flow"]["values"])  # [2, Hf, Wf], newest pair
        np.testing.assert_allclose(flow, reference["flow"][-1], atol=FLOW_ATOL)


def test_whole_tiny_foggy_scans_are_answered_as_rafd_eval_full_scan_detects_them(
    client, shipped, radiate_sample, tmp_path
):
    """6 real RADIATE scans (1152 px, no poses: the service's odometry) posted whole: the boxes are those of
    `rafd eval --full-scan` (rafd.eval.fullscan.predict_full_scan, the PyTorch model streamed over the same tiles by
    the same rafd.runtime.view) on the same scans at the poses the service used; and the flow covers the whole scan."""
    from rafd.data import RadarWindowDataset
    from rafd.data.poses import write_ego_poses
    from rafd.eval.fullscan import predict_full_scan, scan_config

    runner, model = shipped
    folder = tmp_path / "foggy"
    (folder / "Navtech_Cartesian").mkdir(parents=True)
    lines = (radiate_sample / "Navtech_Cartesian.txt").read_text().splitlines()[:6]
    (folder / "Navtech_Cartesian.txt").write_text("\n".join(lines) + "\n")
    (folder / "meta.json").write_text((radiate_sample / "meta.json").read_text())
    (folder / "annotations").mkdir()
    (folder / "annotations" / "annotations.json").write_text("[]")  # no labels: only the detections are compared
    answers, poses, stamps = [], [], []
    for k, line in enumerate(lines):
        name = f"{int(line.split()[1]):06d}.png"
        (folder / "Navtech_Cartesian" / name).write_bytes((radiate_sample / "Navtech_Cartesian" / name).read_bytes())
        scan = cv2.imread(str(radiate_sample / "Navtech_Cartesian" / name), cv2.IMREAD_GRAYSCALE)
        answer = client.post(
            "/detect", json={"stream_id": "foggy", "timestamp": 100.0 + 0.25 * k, "image": b64png(scan)}
        )
        assert answer.status_code == 200, answer.text
        body = answer.json()
        assert body["pose_source"] == "odometry" and body["input"]["covered"]["tiles"] == 21
        answers.append(body)
        poses.append([body["pose"][key] for key in ("x", "y", "yaw")])
        stamps.append(line.split()[3])
    write_ego_poses(folder / "ego_poses.csv", range(1, 7), stamps, np.array(poses))
    cfg = runner.config
    dataset = RadarWindowDataset(tmp_path, cfg=scan_config(cfg, 1152), warm_up=True)
    results = predict_full_scan(model, dataset, cfg, progress=False)
    assert len(results) == 6
    for body, result in zip(answers, results):
        rows = result.predictions  # [N, 6], all K of every tile, merged
        reference = {"boxes": rows[:, :5], "scores": rows[:, 5]}
        assert_same_answer(body, reference, 1)
    assert answers[-1]["flow"]["shape"] == [2, 288, 288]


def test_simulated_stream_over_real_uvicorn_matches_offline_pytorch(shipped):
    """A simulated sequence with true poses, posted at the model's input size to a real server."""
    from rafd.sim.sensor import Difficulty
    from rafd.sim.sequence import run_simulation

    runner, model = shipped
    size = runner.config.input_size
    sequence = run_simulation(4242, 8, "test", size, Difficulty(), name="served")
    app = create_app(Settings(threads=1, score_threshold=THRESHOLD), runner=runner)
    crops, poses = [], []
    with serve_in_thread(app) as url, httpx.Client(base_url=url, timeout=30.0) as http:
        wait_ready(http, timeout=60.0)
        for k, (image, pose) in enumerate(zip(sequence.images, sequence.poses)):
            body = {
                "stream_id": "sim",
                "timestamp": 10.0 + k,
                "image": b64png(image),
                "pose": {"x": float(pose[0]), "y": float(pose[1]), "yaw": float(pose[2])},
            }
            answer = http.post("/detect", json=body)
            assert answer.status_code == 200, answer.text
            crops.append(image)
            poses.append(np.asarray(pose, dtype=np.float64))
            assert_same_answer(answer.json(), offline(model, crops, poses), answer.json()["frames_used"])
