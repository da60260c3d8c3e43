"""Cross-stream batching end to end: a small model exported with a batch axis, served on a real server with
RAFD_MAX_BATCH=4 and one model slot, three streams posting at once: some model runs hold several streams' steps
(the batch-size histogram says so) and every answer equals the one the same server gives with batching off."""

from __future__ import annotations

import threading
from pathlib import Path

import httpx
import numpy as np
import pytest

from export.onnx_export import export_onnx
from export.verify import random_sequence
from rafd.runtime import OnnxRunner
from service.app import create_app
from service.settings import Settings
from tests.utils.export_testing import make_checkpoint, small_config
from tests.utils.service_testing import detect_json, serve_in_thread

STREAMS, FRAMES = 3, 6


@pytest.fixture(scope="module")
def batchable_model(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("batching")
    checkpoint = make_checkpoint(root / "model.pt", small_config(4))
    return export_onnx(checkpoint, root / "step.onnx", batch="dynamic", verify=False, log=lambda _: None).path


def serve_streams(model: Path, max_batch: int) -> tuple[dict[tuple[int, int], dict], str]:
    settings = Settings(threads=1, concurrent_runs=1, max_batch=max_batch, batch_window_ms=20.0, score_threshold=0.0)
    app = create_app(settings, runner=OnnxRunner(model, threads=1))
    answers: dict[tuple[int, int], dict] = {}
    cfg = small_config(4)

    def post(stream: int, url: str, start: threading.Barrier) -> None:
        frames, poses = random_sequence(cfg, FRAMES, seed=100 + stream)
        with httpx.Client(base_url=url, timeout=30.0) as client:
            start.wait()
            for n in range(FRAMES):
                image = (frames[n] * 255).round().astype(np.uint8)
                body = detect_json(f"s{stream}", 10.0 + n, image, tuple(poses[n]))
                answer = client.post("/detect", json=body)
                assert answer.status_code == 200, answer.text
                answers[(stream, n)] = answer.json()

    with serve_in_thread(app) as url:
        start = threading.Barrier(STREAMS)
        threads = [threading.Thread(target=post, args=(k, url, start)) for k in range(STREAMS)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=120.0)
        metrics = httpx.get(f"{url}/metrics").text
        model = httpx.get(f"{url}/model").json()
    assert model["runtime"]["max_batch"] == max_batch
    return answers, metrics


def batched_runs(metrics: str) -> float:
    """Model runs that held more than one step: all runs minus those in the le="1.0" bucket."""
    lines = dict(line.rsplit(" ", 1) for line in metrics.splitlines() if line.startswith("rafd_model_batch_size"))
    return float(lines["rafd_model_batch_size_count"]) - float(lines['rafd_model_batch_size_bucket{le="1.0"}'])


def test_batched_answers_equal_unbatched_ones(batchable_model: Path):
    batched, metrics = serve_streams(batchable_model, max_batch=4)
    alone, alone_metrics = serve_streams(batchable_model, max_batch=1)
    assert len(batched) == len(alone) == STREAMS * FRAMES
    assert batched_runs(metrics) > 0 and batched_runs(alone_metrics) == 0
    for key, answer in alone.items():
        other = batched[key]
        assert other["frames_used"] == answer["frames_used"]
        ours = np.array([[b["x"], b["y"], b["width"], b["length"], b["score"]] for b in other["boxes"]])
        theirs = np.array([[b["x"], b["y"], b["width"], b["length"], b["score"]] for b in answer["boxes"]])
        assert ours.shape == theirs.shape
        np.testing.assert_allclose(ours, theirs, atol=1e-3)
