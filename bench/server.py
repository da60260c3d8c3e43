"""A `rafd-serve` process on loopback for benchmarks, harnesses and tests: start it, wait until it is ready, read
its memory and CPU, stop it. Standard library only (the service runs in its own process)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, cast

LOOPBACK = "127.0.0.1"


def free_port(host: str = LOOPBACK) -> int:
    """A TCP port nothing listens on right now (the OS picks it)."""
    with socket.socket() as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def http_get(url: str, timeout: float = 2.0) -> tuple[int, bytes]:
    """(status, body) of a GET; an HTTP error status is an answer, not an exception."""
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def wait_ready(url: str, process: subprocess.Popen[bytes], timeout: float = 120.0, path: str = "/health/ready") -> None:
    """Poll `url + path` until it answers 200; RuntimeError when the process exits first or time runs out."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            program = cast("Sequence[str]", process.args)[0]  # started from an argument list (serve_command)
            raise RuntimeError(f"{program} exited with {process.returncode} before {url} was ready")
        try:
            if http_get(url + path, timeout=1.0)[0] == 200:
                return
        except OSError:
            pass
        time.sleep(0.1)
    raise RuntimeError(f"{url}{path} not ready after {timeout} s")


def serve_command(
    port: int,
    host: str = LOOPBACK,
    model: Path | None = None,
    threads: int | None = None,
    log_level: str = "warning",
    extra: Sequence[str] = (),
) -> list[str]:
    """The `rafd-serve` command line (through this interpreter, so the same environment serves)."""
    command = [sys.executable, "-m", "service.cli", "--host", host, "--port", str(port), "--log-level", log_level]
    if model is not None:
        command += ["--model", str(model)]
    if threads is not None:
        command += ["--threads", str(threads)]
    return command + list(extra)


@dataclass
class ServerProcess:
    """One started `rafd-serve`: its process and base URL. A context manager that stops it on exit."""

    process: subprocess.Popen[bytes]
    url: str

    @property
    def pid(self) -> int:
        return self.process.pid

    def stop(self, timeout: float = 30.0) -> None:
        if self.process.poll() is None:
            self.process.terminate()
        try:
            self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()

    def __enter__(self) -> ServerProcess:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.stop()


def start_server(
    model: Path | None = None,
    threads: int | None = None,
    env: Mapping[str, str] | None = None,
    clean_env: bool = False,
    port: int | None = None,
    ready_timeout: float = 300.0,
    output: IO[bytes] | None = None,
    extra: Sequence[str] = (),
) -> ServerProcess:
    """`rafd-serve` on loopback with `env` on top of this process's environment (`clean_env`: without any RAFD_*
    variable of this one, i.e. the defaults); returns once it is ready."""
    port = port or free_port()
    base = {k: v for k, v in os.environ.items() if not (clean_env and k.startswith("RAFD_"))}
    process = subprocess.Popen(
        serve_command(port, model=model, threads=threads, extra=extra),
        env={**base, **(env or {})},
        stdout=output,
        stderr=subprocess.STDOUT if output is not None else None,
    )
    server = ServerProcess(process, f"http://{LOOPBACK}:{port}")
    try:
        wait_ready(server.url, process, timeout=ready_timeout)
    except BaseException:
        server.stop()
        raise
    return server


def rss_bytes(pid: int) -> int:
    """Resident memory of a process (Linux /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")


def cpu_seconds(pid: int) -> float:
    """User + system CPU time a process has used so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
