"""The shipped scale-out (deploy/nginx.conf) on loopback: N `rafd-serve` processes behind Debian's nginx.

Used by tests/deploy/test_scaleout.py and `python -m tools.fault_drill`. The nginx configuration is the
shipped one with only the addresses changed (the replicas' loopback ports, nginx's own port) and, because it
runs unprivileged here, its temporary files and pid in a work folder. Standard library and bench.server only.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from bench.server import free_port, serve_command, wait_ready

NGINX_CONF = Path(__file__).resolve().parents[1] / "deploy" / "nginx.conf"
REPLICA_LINE = re.compile(r"^([ \t]*)server rafd-\d+:8000( [^;]*)?;[ \t]*\n", re.MULTILINE)
LISTEN_LINE = re.compile(r"^([ \t]*)listen 8080;[ \t]*$", re.MULTILINE)


def nginx_binary() -> str | None:
    """Debian's nginx, on PATH or in /usr/sbin (not on a normal user's PATH)."""
    return shutil.which("nginx") or shutil.which("nginx", path="/usr/sbin:/usr/local/sbin")


def loopback_config(replica_ports: list[int], listen_port: int, work: Path, conf: Path = NGINX_CONF) -> str:
    """The shipped nginx.conf with its upstream servers on 127.0.0.1:<replica_ports>, listening on listen_port,
    temporary files under `work`. Raises ValueError when the shipped file no longer has the lines it replaces."""
    text = conf.read_text()
    replicas = list(REPLICA_LINE.finditer(text))
    if not replicas or not LISTEN_LINE.search(text):
        raise ValueError(f"{conf}: no `server rafd-N:8000 ...;` lines or no `listen 8080;` to put on loopback")
    indent, options = replicas[0].group(1), replicas[0].group(2) or ""
    servers = "".join(f"{indent}server 127.0.0.1:{port}{options};\n" for port in replica_ports)
    # The first replica line becomes the loopback servers, the other replica lines go.
    text = (
        text[: replicas[0].start()]
        + servers
        + "".join(text[a.end() : b.start()] for a, b in zip(replicas, replicas[1:]))
        + text[replicas[-1].end() :]
    )
    text = LISTEN_LINE.sub(rf"\g<1>listen 127.0.0.1:{listen_port};", text)
    temp = "\n".join(
        f"    {kind}_temp_path {work / kind};" for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi")
    )
    return text.replace("http {\n", "http {\n" + temp + "\n", 1)


@dataclass
class LoopbackCluster:
    """`replicas` rafd-serve processes (environment `env` on top of this one's) behind nginx, in `work`."""

    replicas: int
    work: Path
    env: dict[str, str] = field(default_factory=dict)
    replica_ports: list[int] = field(default_factory=list)
    processes: list[subprocess.Popen] = field(default_factory=list)
    nginx: subprocess.Popen | None = None
    url: str = ""

    def __enter__(self) -> LoopbackCluster:
        binary = nginx_binary()
        if binary is None:
            raise RuntimeError("nginx is not installed (Debian: apt-get install nginx)")
        self.work.mkdir(parents=True, exist_ok=True)
        try:
            env = {**os.environ, **self.env}
            for index in range(self.replicas):
                port = free_port()
                log = (self.work / f"replica-{index}.log").open("wb")
                self.processes.append(
                    subprocess.Popen(serve_command(port), env=env, stdout=log, stderr=subprocess.STDOUT)
                )
                self.replica_ports.append(port)
            for port, process in zip(self.replica_ports, self.processes):
                wait_ready(f"http://127.0.0.1:{port}", process)
            listen = free_port()
            conf = self.work / "nginx.conf"
            conf.write_text(loopback_config(self.replica_ports, listen, self.work))
            log = (self.work / "nginx.log").open("wb")
            self.nginx = subprocess.Popen(
                [
                    binary,
                    "-p",
                    str(self.work),
                    "-c",
                    str(conf),
                    "-e",
                    "stderr",
                    "-g",
                    f"daemon off; pid {self.work / 'nginx.pid'};",
                ],
                stdout=log,
                stderr=subprocess.STDOUT,
            )
            self.url = f"http://127.0.0.1:{listen}"
            wait_ready(self.url, self.nginx, timeout=10.0, path="/health/live")
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def replica_address(self, index: int) -> str:
        """How nginx names a replica in X-RaFD-Replica ($upstream_addr)."""
        return f"127.0.0.1:{self.replica_ports[index]}"

    def kill(self, index: int) -> None:
        """SIGKILL one replica (a crash: nothing is handed over) and wait for it to be gone."""
        process = self.processes[index]
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=10.0)

    def terminate(self, index: int, timeout: float = 30.0) -> None:
        """SIGTERM one replica (a graceful stop: requests in progress finish) and wait for it to exit."""
        process = self.processes[index]
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=timeout)

    def restart(self, index: int, timeout: float = 120.0) -> None:
        """Start a stopped replica again on its own port (a fresh process: no streams) and wait until it is ready."""
        if self.processes[index].poll() is None:
            raise RuntimeError(f"replica {index} is still running")
        port = self.replica_ports[index]
        log = (self.work / f"replica-{index}.log").open("ab")
        env = {**os.environ, **self.env}
        self.processes[index] = subprocess.Popen(serve_command(port), env=env, stdout=log, stderr=subprocess.STDOUT)
        wait_ready(f"http://127.0.0.1:{port}", self.processes[index], timeout=timeout)

    def __exit__(self, *exc_info: object) -> None:
        for process in [self.nginx, *self.processes]:
            if process is not None and process.poll() is None:
                process.terminate()
        for process in [self.nginx, *self.processes]:
            if process is None:
                continue
            try:
                process.wait(timeout=10.0)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
