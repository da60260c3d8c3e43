"""The shipped nginx.conf: what the loopback harness changes in it, and (where nginx is installed) that nginx
accepts it."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from bench.loopback import NGINX_CONF, loopback_config, nginx_binary


def test_loopback_config_changes_only_addresses_and_temporary_paths(tmp_path: Path):
    shipped = NGINX_CONF.read_text().splitlines()
    used = loopback_config([5001, 5002, 5003, 5004], 6000, tmp_path).splitlines()
    removed = [line.strip() for line in shipped if line not in used]
    added = [line.strip() for line in used if line not in shipped]
    assert sorted(removed) == sorted(
        line.strip() for line in shipped if line.strip().startswith(("server rafd-", "listen "))
    )
    assert len([line for line in removed if line.startswith("server rafd-")]) == 3  # the compose file's replicas
    assert [line for line in added if line.startswith("server ")] == [
        f"server 127.0.0.1:{port} max_fails=3 fail_timeout=10s;" for port in (5001, 5002, 5003, 5004)
    ]
    assert "listen 127.0.0.1:6000;" in added
    assert all(
        line.startswith(("server 127.0.0.1:", "listen 127.0.0.1:")) or "_temp_path " in line for line in added
    ), added


def test_shipped_config_hashes_consistently_on_the_stream():
    text = NGINX_CONF.read_text()
    assert "hash $rafd_stream consistent;" in text
    assert "$http_x_stream_id" in text and "^/streams/" in text


@pytest.mark.skipif(nginx_binary() is None, reason="nginx is not installed (Debian: apt-get install nginx)")
def test_nginx_accepts_the_loopback_config(tmp_path: Path):
    conf = tmp_path / "nginx.conf"
    conf.write_text(loopback_config([5001, 5002, 5003], 6000, tmp_path))
    done = subprocess.run(
        [
            nginx_binary(),
            "-t",
            "-p",
            str(tmp_path),
            "-c",
            str(conf),
            "-e",
            "stderr",
            "-g",
            f"pid {tmp_path / 'nginx.pid'};",
        ],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr


def test_compose_file_places_exactly_the_replicas_nginx_routes_to():
    """compose.yaml's replica services are the `server` lines of nginx.conf (a replica added to one file only
    would get no traffic, or nginx would not start)."""
    import re

    compose = (NGINX_CONF.parent / "compose.yaml").read_text()
    services = re.findall(r"^  (rafd-\d+): \*replica$", compose, re.MULTILINE)
    servers = re.findall(r"^\s*server (rafd-\d+):8000\b", NGINX_CONF.read_text(), re.MULTILINE)
    assert services and services == servers
    assert "./nginx.conf:/etc/nginx/nginx.conf:ro" in compose


def test_replicas_trust_forwarded_addresses_only_from_nginx_and_publish_no_port():
    """Behind nginx every request comes from nginx's address; the replicas trust X-Forwarded-For from nginx's fixed
    address only (never "*", issue 40), so the refusal penalty counts per client and a client that reaches a replica
    otherwise cannot choose its own address; and no replica publishes a port."""
    import ipaddress

    import yaml

    compose = (NGINX_CONF.parent / "compose.yaml").read_text()
    replica = compose.split("x-replica: &replica", 1)[1].split("\nservices:", 1)[0]
    assert "ports:" not in replica
    parsed = yaml.safe_load(compose)
    trusted = parsed["x-replica"]["environment"]["FORWARDED_ALLOW_IPS"]
    nginx = parsed["services"]["nginx"]["networks"]["rafd"]["ipv4_address"]
    assert trusted == nginx and "*" not in trusted
    subnet = parsed["networks"]["rafd"]["ipam"]["config"][0]["subnet"]
    assert ipaddress.ip_address(nginx) in ipaddress.ip_network(subnet)
    assert all(parsed["services"][f"rafd-{k}"]["networks"] == ["rafd"] for k in (1, 2, 3))
    # nginx sets the header to the client's address, replacing the client's own: with every proxy trusted, uvicorn
    # takes the header's first address, which a client could otherwise choose (and so escape its per-client limits)
    assert "X-Forwarded-For $remote_addr;" in NGINX_CONF.read_text()
    assert "$proxy_add_x_forwarded_for" not in NGINX_CONF.read_text()


def test_keep_alive_pairs_the_proxy_below_the_replicas_and_one_failure_keeps_a_replica():
    """Issue 39: the replicas keep idle connections longer than every proxy in front (nginx.conf's upstream
    keepalive_timeout, ingress-nginx's upstream-keepalive-timeout default of 60 s), so the proxy closes first and never
    sends a frame on a connection being closed (a 502 it cannot retry); and one failed request does not mark a
    replica down (max_fails > 1)."""
    import re

    import yaml

    from service.settings import Settings

    text = NGINX_CONF.read_text()
    upstream = text.split("upstream rafd {", 1)[1].split("}", 1)[0]
    proxy_keepalive = re.search(r"^\s*keepalive_timeout (\d+)s;", upstream, re.MULTILINE)
    assert proxy_keepalive is not None, "no keepalive_timeout in the upstream block (nginx's default is 60 s)"
    service_default = Settings(threads=1).keep_alive_timeout_s
    assert service_default > float(proxy_keepalive.group(1))
    compose = yaml.safe_load((NGINX_CONF.parent / "compose.yaml").read_text())
    assert float(compose["x-replica"]["environment"]["RAFD_KEEP_ALIVE_TIMEOUT_S"]) > float(proxy_keepalive.group(1))
    deployment = yaml.safe_load((NGINX_CONF.parent / "kubernetes" / "deployment.yaml").read_text())
    (container,) = deployment["spec"]["template"]["spec"]["containers"]
    env = {e["name"]: e.get("value") for e in container["env"]}
    assert float(env["RAFD_KEEP_ALIVE_TIMEOUT_S"]) > 60.0  # ingress-nginx's upstream-keepalive-timeout default
    fails = [int(m) for m in re.findall(r"max_fails=(\d+)", upstream)]
    assert fails and min(fails) >= 2


def test_nginx_errors_are_json_in_the_service_shape():
    """error_page sends nginx's own 502/503/504 to JSON bodies of the service's shape (checked live by the fault
    drill's test, tests/tools/test_fault_drill.py)."""
    import json
    import re

    text = NGINX_CONF.read_text()
    for status in (502, 503, 504):
        assert f"error_page {status} @rafd_{status};" in text
        block = text.split(f"location @rafd_{status} {{", 1)[1].split("}\n", 1)[0]
        assert "default_type application/json;" in block
        body = re.search(rf"return {status} '(.*)';", block)
        assert body is not None
        error = json.loads(body.group(1).replace("\\n", "").replace("\\'", "'"))["error"]
        assert set(error) == {"code", "message"} and error["code"].startswith("upstream_")
