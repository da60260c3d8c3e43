"""The serving image, built from the Dockerfile and run in a real Docker engine.

Opt-in: RAFD_DOCKER_TESTS=1 and a running engine (here: `bash ../shared/tools/docker-engine.sh`; no registry is
reachable, so it provides a stand-in python:3.11-slim and containers use --network host). The build uses the
engine's layer cache: seconds when nothing changed, about 4 minutes from scratch on this machine's vfs storage.
RAFD_DOCKER_IMAGE names an image already built instead (then nothing is built).
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.utils.answers_testing import assert_same_answer, in_process_service

REPO = Path(__file__).resolve().parents[2]
PINNED = {"RAFD_RUNTIME": "onnxruntime", "RAFD_PRECISION": "fp32"}  # comparable answers on both sides
FRAMES = 4  # real tiny_foggy scans per stream: a full window, flow from the second on

if os.environ.get("RAFD_DOCKER_TESTS") != "1":
    pytest.skip(
        "Docker image tests are opt-in: set RAFD_DOCKER_TESTS=1 with a Docker engine running "
        "(bash ../shared/tools/docker-engine.sh)",
        allow_module_level=True,
    )
if shutil.which("docker") is None or subprocess.run(["docker", "info"], capture_output=True).returncode != 0:
    pytest.skip(
        "RAFD_DOCKER_TESTS=1 but no Docker engine answers `docker info` "
        "(start one: bash ../shared/tools/docker-engine.sh)",
        allow_module_level=True,
    )

from bench.server import free_port, http_get  # noqa: E402
from rafd.cpu import usable_cpus  # noqa: E402

pytestmark = pytest.mark.docker


def docker(*args: str, check: bool = True, timeout: float = 60.0) -> str:
    done = subprocess.run(["docker", *args], capture_output=True, text=True, timeout=timeout)
    if check and done.returncode != 0:
        raise AssertionError(f"docker {' '.join(args)} failed: {done.stderr[-2000:]}")
    return done.stdout.strip()


@pytest.fixture(scope="module")
def image() -> str:
    if os.environ.get("RAFD_DOCKER_IMAGE"):
        return os.environ["RAFD_DOCKER_IMAGE"]
    tag = "rafd-serve:test"
    docker("build", "--network", "host", "-t", tag, str(REPO), timeout=1200.0)
    return tag


class Container:
    """One `docker run -d --network host` of the image, serving on a free port (RAFD_PORT)."""

    def __init__(self, image: str, *run_args: str, env: dict[str, str] | None = None) -> None:
        self.port = free_port()
        self.name = f"rafd-test-{uuid.uuid4().hex[:8]}"
        env_args = [a for k, v in {**(env or {}), "RAFD_PORT": str(self.port)}.items() for a in ("-e", f"{k}={v}")]
        # The image's own command and HEALTHCHECK (both on RAFD_PORT), checked every second instead of 15 s.
        docker(
            "run",
            "-d",
            "--name",
            self.name,
            "--network",
            "host",
            "--health-interval",
            "1s",
            "--health-start-period",
            "120s",
            *env_args,
            *run_args,
            image,
        )
        self.url = f"http://127.0.0.1:{self.port}"

    def health(self) -> str:
        return docker("inspect", "-f", "{{.State.Health.Status}}", self.name)

    def wait_healthy(self, timeout: float = 180.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            status = self.health()
            if status == "healthy":
                return
            if docker("inspect", "-f", "{{.State.Running}}", self.name) != "true":
                break
            time.sleep(0.5)
        raise AssertionError(f"{self.name} not healthy ({self.health()}): {docker('logs', self.name, check=False)}")

    def exec(self, *command: str) -> str:
        return docker("exec", self.name, *command)

    def remove(self) -> None:
        docker("rm", "-f", self.name, check=False)


@pytest.fixture(scope="module")
def container(image: str) -> Iterator[Container]:
    running = Container(image, env=PINNED)
    try:
        running.wait_healthy()
        yield running
    finally:
        running.remove()


def post(url: str, body: dict) -> dict:
    import urllib.request

    request = urllib.request.Request(
        f"{url}/detect", data=json.dumps(body).encode(), headers={"content-type": "application/json"}, method="POST"
    )
    with urllib.request.urlopen(request, timeout=60) as response:
        return json.loads(response.read())


def test_image_becomes_healthy_and_runs_as_non_root(container: Container):
    assert container.health() == "healthy"
    uid_lines = [line for line in container.exec("cat", "/proc/1/status").splitlines() if line.startswith("Uid:")]
    assert uid_lines and all(int(uid) != 0 for uid in uid_lines[0].split()[1:]), uid_lines  # real, effective, saved
    assert container.exec("id", "-u") != "0"


def test_image_holds_no_torch(container: Container):
    found = container.exec("python", "-c", "import importlib.util as u; print(u.find_spec('torch'))")
    assert found == "None"
    listing = container.exec(
        "python",
        "-c",
        "import importlib.metadata as m; "
        "print(' '.join(sorted(d.metadata['Name'].lower() for d in m.distributions())))",
    )
    assert "torch" not in listing.split() and "onnxruntime" in listing.split()


def test_image_answers_detect_as_the_in_process_service(container: Container, radiate_sample: Path):
    """Real scans, no poses (odometry): the container's answers equal the in-process service's, frame by frame."""
    scans = sorted((radiate_sample / "Navtech_Cartesian").glob("*.png"))[:FRAMES]
    with in_process_service(**{k.removeprefix("RAFD_").lower(): v for k, v in PINNED.items()}) as client:
        for t, path in enumerate(scans):
            body = {
                "stream_id": "docker",
                "timestamp": 100.0 + t,
                "image": base64.b64encode(path.read_bytes()).decode("ascii"),
            }
            served = post(container.url, body)
            reference = client.post("/detect", json=body)
            assert reference.status_code == 200, reference.text
            assert_same_answer(served, reference.json())
    assert served["frames_used"] == min(FRAMES, served["num_frames"])
    assert (served["flow"] is not None) == (served["num_frames"] > 1)


@pytest.mark.parametrize("cpus", [1, 2])
def test_image_threads_follow_cpus(image: str, cpus: int):
    """`docker run --cpus N` (a CFS quota, not a cpuset): the model's threads and concurrent runs become N."""
    host_cpus = usable_cpus()
    if cpus > host_cpus:
        pytest.skip(f"this machine has {host_cpus} CPUs")
    limited = Container(image, "--cpus", str(cpus), env=PINNED)
    try:
        limited.wait_healthy()
        status, body = http_get(f"{limited.url}/model")
        assert status == 200
        runtime = json.loads(body)["runtime"]
        assert runtime["threads"] == cpus and runtime["concurrent_runs"] == cpus, runtime
        # what the service read: the cgroup's CFS quota (v1 or v2), not the host's CPU count
        quota = limited.exec("python", "-c", "from rafd.cpu import cgroup_cpu_limit; print(cgroup_cpu_limit())")
        assert quota == str(cpus)
    finally:
        limited.remove()
