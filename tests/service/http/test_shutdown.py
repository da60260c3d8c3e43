"""Issue 34 finding 8: on SIGTERM the server waited for the slowest client (a trickled body kept the process alive
for the 30 s body timeout: uvicorn's graceful-shutdown timeout was not set). Now service/http/server.py bounds it with
RAFD_SHUTDOWN_TIMEOUT_S: requests still in progress then are dropped and the process exits."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bench.server import free_port, wait_ready

pytestmark = pytest.mark.network

REPO = Path(__file__).resolve().parents[3]
SERVER = """
import sys
from service.app import create_app
from service.http.server import serve
from service.settings import Settings
from tests.utils.fake_runner import FakeRunner

# no minimum body rate and a long body timeout: only the shutdown bound can end the trickled request
settings = Settings(threads=1, shutdown_timeout_s=1.0, min_body_bytes_per_s=0, body_timeout_s=120.0)
serve(create_app(settings, runner=FakeRunner()), settings, "127.0.0.1", int(sys.argv[1]), "info")
"""


def test_sigterm_during_a_trickled_body_exits_within_the_shutdown_bound():
    port = free_port()
    process = subprocess.Popen(
        [sys.executable, "-c", SERVER, str(port)], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )
    try:
        wait_ready(f"http://127.0.0.1:{port}", process, timeout=60.0)
        with socket.create_connection(("127.0.0.1", port)) as sock:
            sock.sendall(
                b"POST /streams/slow/detect HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                b"Content-Length: 100000\r\n\r\n{"
            )
            time.sleep(0.3)  # the request is in progress, its body far from complete
            sock.sendall(b" ")
            start = time.monotonic()
            process.send_signal(signal.SIGTERM)
            output, _ = process.communicate(timeout=60.0)
            exited_after = time.monotonic() - start
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    log = output.decode(errors="replace")
    assert process.returncode in (0, -signal.SIGTERM), log  # uvicorn re-raises the signal it handled
    assert "timeout graceful shutdown exceeded" in log  # it was the bound that ended the request ...
    assert exited_after < 60.0  # ... well before the 120 s body timeout (about RAFD_SHUTDOWN_TIMEOUT_S = 1 s)
