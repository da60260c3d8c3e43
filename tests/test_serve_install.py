"""The serving image's install path without Docker: a fresh venv with ONLY the `serve` extra (no torch)
installs the package non-editably (as the Dockerfile does), starts `rafd-serve` on the shipped model with an
API key configured, keeps its probes open, and answers POST /detect only with the key.
"""

from __future__ import annotations

import base64
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from bench.server import free_port

pytestmark = pytest.mark.network

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def serve_venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    venv = tmp_path_factory.mktemp("serve-venv")
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    install = subprocess.run(
        [str(venv / "bin" / "pip"), "install", "-q", f"{REPO}[serve]"], capture_output=True, text=True
    )
    assert install.returncode == 0, install.stderr[-3000:]
    return venv


@pytest.mark.slow
def test_serve_extra_installs_without_torch_and_answers_detect(serve_venv: Path, tmp_path: Path):
    python = serve_venv / "bin" / "python"
    probe = subprocess.run(
        [str(python), "-c", "import importlib.util as u; print(u.find_spec('torch') is None)"],
        capture_output=True,
        text=True,
        check=True,
        cwd=tmp_path,
    )
    assert probe.stdout.strip() == "True", "the serve extra pulled in torch"
    # the tracker the service will carry per stream imports without torch (numpy + scipy)
    subprocess.run([str(python), "-c", "import rafd.tracking"], capture_output=True, check=True, cwd=tmp_path)

    port = free_port()
    key = "install-check-key-0123456789"
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAFD_")} | {"RAFD_API_KEYS": f"ci:{key}"}
    server = subprocess.Popen(
        [str(serve_venv / "bin" / "rafd-serve"), "--port", str(port), "--threads", "1"],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 90.0
        while True:
            assert server.poll() is None, f"rafd-serve exited: {server.stdout.read()[-3000:]}"
            try:
                if httpx.get(f"{url}/health/ready", timeout=1.0).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, "rafd-serve not ready after 90 s"
            time.sleep(0.25)
        assert httpx.get(f"{url}/model").status_code == 401  # the readiness probe above needed no key
        size = httpx.get(f"{url}/model", headers={"X-API-Key": key}).json()["input_size"]
        image = np.random.default_rng(0).integers(0, 60, (int(size), int(size)), dtype=np.uint8)
        ok, png = cv2.imencode(".png", image)
        assert ok
        body = {
            "stream_id": "install-check",
            "timestamp": 1.0,
            "pose": {"x": 0.0, "y": 0.0, "yaw": 0.0},
            "image": base64.b64encode(png.tobytes()).decode("ascii"),
        }
        assert httpx.post(f"{url}/detect", timeout=30.0, json=body).status_code == 401
        answer = httpx.post(f"{url}/detect", timeout=30.0, json=body, headers={"Authorization": f"Bearer {key}"})
        assert answer.status_code == 200, answer.text
        body = answer.json()
        assert body["frames_used"] == 1 and isinstance(body["boxes"], list)
    finally:
        server.terminate()
        server.wait(timeout=30)


@pytest.mark.slow
def test_the_installed_rafd_command_finds_its_commands_and_aliases(serve_venv: Path, tmp_path: Path):
    """A real (non-editable) install: `rafd --help` lists every command of its table (rafd.cli.main.COMMANDS), each
    command's `rafd-NAME` alias is installed (none for the benchmarks, `rafd bench NAME` only), and `rafd serve`
    reaches the service; the serve-only install has no foxglove-sdk, so --foxglove-port names the extra to install."""
    from rafd.cli.main import COMMANDS

    rafd = str(serve_venv / "bin" / "rafd")
    listed = subprocess.run([rafd, "--help"], capture_output=True, text=True, cwd=tmp_path)
    assert listed.returncode == 0, listed.stderr
    for command in COMMANDS:
        grouped = command.name.startswith("bench-")
        typed = command.name.replace("-", " ", 1) if grouped else command.name
        assert f"\n  {typed} " in listed.stdout, (command.name, listed.stdout)
        assert (serve_venv / "bin" / f"rafd-{command.name}").is_file() is not grouped, command.name
    installed = sorted(p.name for p in (serve_venv / "bin").iterdir() if p.name == "rafd" or p.name.startswith("rafd-"))
    assert len(installed) == 1 + sum(not c.name.startswith("bench-") for c in COMMANDS) <= 16, installed
    import rafd as source

    version = "from importlib.metadata import version; print(version('rafd'))"  # pyproject's dynamic version
    found = subprocess.run([str(serve_venv / "bin" / "python"), "-c", version], capture_output=True, text=True)
    assert found.stdout.strip() == source.__version__, found.stderr
    served = subprocess.run([rafd, "serve", "--help"], capture_output=True, text=True, cwd=tmp_path)
    assert served.returncode == 0 and served.stdout.startswith("usage: rafd serve")
    assert "--max-streams" in served.stdout and "--foxglove-port" in served.stdout
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAFD_")}
    live = subprocess.run(
        [rafd, "serve", "--foxglove-port", "0"], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120
    )
    assert live.returncode == 2 and "pip install 'rafd[live]'" in live.stderr, live.stderr
