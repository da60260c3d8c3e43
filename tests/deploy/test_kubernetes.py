"""The Kubernetes manifests (deploy/kubernetes/): valid against the Kubernetes API schemas, offline and strictly
(kubernetes-validate), and consistent with the service they run: its port, health routes, shutdown bound, body limit
and timeout, the header it names streams by, and the image's user and HEALTHCHECK. No cluster is needed.
"""

from __future__ import annotations

import copy
import re
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from service.settings import Settings

try:
    import kubernetes_validate
except ImportError:  # the dev extra pins it; without it only the schema validation is skipped
    kubernetes_validate = None

REPO = Path(__file__).resolve().parents[2]
MANIFESTS = REPO / "deploy" / "kubernetes"
KUSTOMIZATION = MANIFESTS / "kustomization.yaml"
# The oldest and the newest Kubernetes versions whose schemas the pinned kubernetes-validate bundles.
KUBERNETES_VERSIONS = ("1.25", "1.37")
HASH_BY = "nginx.ingress.kubernetes.io/upstream-hash-by"

needs_validator = pytest.mark.skipif(
    kubernetes_validate is None,
    reason="kubernetes-validate is not installed (the dev extra pins it: pip install -e '.[dev]')",
)


def manifest_files() -> list[Path]:
    return sorted(path for path in MANIFESTS.glob("*.yaml") if path != KUSTOMIZATION)


def load_resources() -> list[dict[str, Any]]:
    return [doc for path in manifest_files() for doc in yaml.safe_load_all(path.read_text()) if doc]


def resource(kind: str) -> dict[str, Any]:
    found = [doc for doc in load_resources() if doc["kind"] == kind]
    assert len(found) == 1, f"expected one {kind}, found {len(found)}"
    return found[0]


def pod_spec() -> dict[str, Any]:
    return resource("Deployment")["spec"]["template"]["spec"]


def pod_labels() -> dict[str, str]:
    return resource("Deployment")["spec"]["template"]["metadata"]["labels"]


def container() -> dict[str, Any]:
    containers = pod_spec()["containers"]
    assert len(containers) == 1
    return containers[0]


def env() -> dict[str, str]:
    """The container's literal environment (name -> value); a variable taken from elsewhere fails the test."""
    variables = container().get("env", [])
    assert all("value" in var for var in variables), "every variable is a literal (API keys come as a file)"
    return {var["name"]: var["value"] for var in variables}


def setting(name: str) -> Any:
    """A service setting as the pods run it: the Deployment's RAFD_<NAME> when it sets one, else the default."""
    field = Settings.model_fields[name]
    value = env().get(f"RAFD_{name.upper()}")
    return field.default if value is None else type(field.default)(value)


def annotations() -> dict[str, str]:
    return resource("Ingress")["metadata"]["annotations"]


def dockerfile() -> str:
    return (REPO / "Dockerfile").read_text()


def healthcheck_options() -> dict[str, str]:
    line = re.search(r"^HEALTHCHECK (.*?)\\?$", dockerfile(), re.MULTILINE)
    assert line is not None, "the Dockerfile has a HEALTHCHECK"
    return dict(re.findall(r"--([a-z-]+)=(\S+)", line.group(1)))


def seconds(duration: str) -> float:
    """A Dockerfile duration (3s, 1m30s) in seconds."""
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|s|m|h)", duration)
    assert parts and "".join(n + u for n, u in parts) == duration, duration
    return sum(float(n) * {"ms": 0.001, "s": 1, "m": 60, "h": 3600}[u] for n, u in parts)


def nginx_size(text: str) -> int:
    """An nginx size (16m, 512k, 1g, 2621440) in bytes."""
    match = re.fullmatch(r"(\d+)([kKmMgG]?)", text)
    assert match, text
    return int(match.group(1)) * 1024 ** " kmg".index(match.group(2).lower() or " ")


def named_port(ref: int | str) -> int:
    """A pod-side port reference (a number, or the name of the container's port) as a number."""
    if isinstance(ref, int):
        return ref
    numbers = [port["containerPort"] for port in container()["ports"] if port.get("name") == ref]
    assert numbers, f"no container port named {ref!r}"
    return numbers[0]


@pytest.fixture(scope="module")
def openapi() -> dict[str, Any]:
    """The service's own OpenAPI document (the app is built, its model not loaded)."""
    from service.app import create_app

    return create_app(Settings()).openapi()


@pytest.fixture
def no_network(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Any attempt to open a connection fails the test: validation must use the bundled schemas only."""

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("kubernetes-validate tried to reach the network")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    yield


# ---------------------------------------------------------------------------------------------- schema validation
@needs_validator
@pytest.mark.parametrize("version", KUBERNETES_VERSIONS)
def test_every_manifest_validates_strictly_offline(version: str, no_network: None):
    assert kubernetes_validate is not None
    # validate() silently falls back to an older bundled version: make sure the one named is really there.
    assert f"{version}.0" in kubernetes_validate.utils.all_versions()
    resources = load_resources()
    assert {doc["kind"] for doc in resources} >= {"Deployment", "Service", "Ingress"}
    for doc in resources:
        name = f"{doc['kind']}/{doc['metadata']['name']}"
        try:
            validated = kubernetes_validate.validate(doc, version, strict=True)
        except kubernetes_validate.ValidationError as exc:
            path = ".".join(str(part) for part in exc.path)
            pytest.fail(f"{name} is not a valid Kubernetes {version} object: {path}: {exc.message}")
        except kubernetes_validate.SchemaNotFoundError as exc:
            pytest.fail(f"{name}: {exc.message}")
        assert validated == version, (name, validated)


@needs_validator
def test_strict_validation_refuses_a_misspelt_field(no_network: None):
    """Strict mode is what catches a misspelt field (e.g. readinessProbes), which the API server would drop with
    only a warning and the probe would silently be missing."""
    assert kubernetes_validate is not None
    deployment = copy.deepcopy(resource("Deployment"))
    probe = deployment["spec"]["template"]["spec"]["containers"][0].pop("readinessProbe")
    deployment["spec"]["template"]["spec"]["containers"][0]["readinessProbes"] = probe
    kubernetes_validate.validate(deployment, KUBERNETES_VERSIONS[-1], strict=False)  # the lax schema takes it
    with pytest.raises(kubernetes_validate.ValidationError, match="readinessProbes"):
        kubernetes_validate.validate(deployment, KUBERNETES_VERSIONS[-1], strict=True)


def test_kustomization_lists_every_manifest_in_one_namespace():
    kustomization = yaml.safe_load(KUSTOMIZATION.read_text())
    assert sorted(kustomization["resources"]) == sorted(path.name for path in manifest_files())
    for doc in load_resources():
        if doc["kind"] == "Namespace":
            assert doc["metadata"]["name"] == kustomization["namespace"]
        else:  # applied with `kubectl apply -f` too, so each names its namespace itself
            assert doc["metadata"]["namespace"] == kustomization["namespace"], doc["kind"]
    # The API keys are referenced, never shipped: no Secret with values in the repository.
    assert "Secret" not in {doc["kind"] for doc in load_resources()}


# ---------------------------------------------------------------------------------------- the service it runs
def test_container_port_is_the_port_the_image_serves_on():
    from service.cli import build_parser

    port = named_port("http")
    assert port == build_parser().get_default("port")  # rafd-serve --port's default
    assert re.search(rf"^\s*(?:ENV\s+)?RAFD_PORT={port}\b", dockerfile(), re.MULTILINE)  # the image's CMD
    assert re.search(rf"^EXPOSE {port}$", dockerfile(), re.MULTILINE)
    assert env()["RAFD_PORT"] == str(port)
    service = resource("Service")
    assert service["spec"]["selector"].items() <= pod_labels().items()
    (service_port,) = service["spec"]["ports"]
    assert named_port(service_port["targetPort"]) == port
    backend = resource("Ingress")["spec"]["rules"][0]["http"]["paths"][0]["backend"]["service"]
    assert backend["name"] == service["metadata"]["name"]
    assert backend["port"] in ({"name": service_port["name"]}, {"number": service_port["port"]})


def test_every_selector_selects_the_serving_pods():
    """A selector that misses the pods fails quietly: a Service without endpoints, a policy or a budget that guards
    nothing."""
    deployment = resource("Deployment")
    selectors = {
        "Deployment": deployment["spec"]["selector"]["matchLabels"],
        "Service": resource("Service")["spec"]["selector"],
        "NetworkPolicy": resource("NetworkPolicy")["spec"]["podSelector"]["matchLabels"],
        "PodDisruptionBudget": resource("PodDisruptionBudget")["spec"]["selector"]["matchLabels"],
    }
    for i, spread in enumerate(pod_spec().get("topologySpreadConstraints", [])):
        selectors[f"topologySpreadConstraints[{i}]"] = spread["labelSelector"]["matchLabels"]
    for where, labels in selectors.items():
        assert labels and labels.items() <= pod_labels().items(), where


def test_probes_ask_the_health_routes_the_service_serves_without_a_key(openapi: dict[str, Any]):
    from fastapi.testclient import TestClient

    from service.app import create_app

    served = {path for path, methods in openapi["paths"].items() if "get" in methods}
    probes = {kind: container()[kind]["httpGet"] for kind in ("startupProbe", "livenessProbe", "readinessProbe")}
    assert probes["readinessProbe"]["path"] == "/health/ready"  # traffic only once the model is warmed up
    assert probes["livenessProbe"]["path"] == "/health/live"  # a restart only for a process that stopped answering
    # Probes carry no API key: with keys configured (as here, from the Secret), a probe of any other path would
    # get 401 and the pod would never be ready. The app without its lifespan: no model loaded, so /health/ready
    # answers 503 not_ready, never 401.
    client = TestClient(create_app(Settings(api_keys="probe-test:" + "k" * 32)))
    assert client.get("/model").status_code == 401  # keys are enforced on the other routes
    for kind, probe in probes.items():
        assert probe["path"] in served, f"{kind} asks {probe['path']}, which the service does not serve"
        assert named_port(probe["port"]) == named_port("http")
        status = client.get(probe["path"]).status_code
        assert status == (503 if probe["path"] == "/health/ready" else 200), (kind, status)


def test_probe_timing_follows_the_dockerfile_healthcheck():
    check = healthcheck_options()
    assert "/health/ready" in dockerfile().split("HEALTHCHECK", 1)[1].split("\nCMD", 1)[0]
    timeout = seconds(check["timeout"])
    for kind in ("startupProbe", "livenessProbe", "readinessProbe"):
        assert container()[kind]["timeoutSeconds"] == timeout, kind
    liveness = container()["livenessProbe"]
    assert liveness["periodSeconds"] == seconds(check["interval"])
    assert liveness["failureThreshold"] == int(check["retries"])
    # the start period: the liveness probe waits for the startup probe, which allows at least as long
    startup = container()["startupProbe"]
    assert startup["periodSeconds"] * startup["failureThreshold"] >= seconds(check["start-period"])
    # a probe's period is longer than its timeout (probes do not pile up)
    for kind in ("startupProbe", "livenessProbe", "readinessProbe"):
        assert container()[kind]["periodSeconds"] > container()[kind]["timeoutSeconds"], kind


def test_grace_period_covers_the_prestop_sleep_and_the_shutdown_bound():
    """Kubernetes counts the preStop hook inside terminationGracePeriodSeconds: SIGTERM comes after the sleep, and
    the service then takes up to RAFD_SHUTDOWN_TIMEOUT_S before it exits; SIGKILL must not come first."""
    command = container()["lifecycle"]["preStop"]["exec"]["command"]
    assert command[0] == "sleep" and len(command) == 2, command
    sleep_s = float(command[1])
    shutdown_s = setting("shutdown_timeout_s")
    assert shutdown_s == 10.0 or "RAFD_SHUTDOWN_TIMEOUT_S" in env()
    assert sleep_s >= 1  # the endpoint is taken out of ingress-nginx before the server stops accepting
    assert pod_spec()["terminationGracePeriodSeconds"] > sleep_s + shutdown_s


def test_ingress_hashes_on_the_stream_header_the_service_reads(openapi: dict[str, Any]):
    detect = openapi["paths"]["/detect"]["post"]
    (header,) = [p["name"] for p in detect["parameters"] if p["in"] == "header"]
    assert header == "X-Stream-Id"
    variable = "$http_" + header.lower().replace("-", "_")
    assert annotations()[HASH_BY] == variable
    # the compose router hashes on the same header (and, there, also the path form)
    from bench.loopback import NGINX_CONF

    assert re.search(rf"map {re.escape(variable)} \$rafd_stream ", NGINX_CONF.read_text())
    # ingress-nginx must pick the pod itself: through the Service's ClusterIP, kube-proxy would spread a stream
    assert annotations().get("nginx.ingress.kubernetes.io/service-upstream", "false") == "false"
    # no other balancing in the way of the hash (cookie affinity, a canary that splits a stream's frames)
    for key in annotations():
        assert not key.startswith(("nginx.ingress.kubernetes.io/affinity", "nginx.ingress.kubernetes.io/canary")), key


def test_ingress_body_limit_and_timeouts_leave_the_limits_to_the_service():
    from bench.loopback import NGINX_CONF

    body = nginx_size(annotations()["nginx.ingress.kubernetes.io/proxy-body-size"])
    assert body >= setting("max_request_bytes")  # 2.5 MiB: the service answers 413 itself, as JSON
    compose_body = re.search(r"client_max_body_size (\S+);", NGINX_CONF.read_text())
    assert compose_body is not None and body == nginx_size(compose_body.group(1))  # as the compose router
    # streamed to the replica as it arrives: the frame takes its place at arrival, the body rate limit applies
    assert annotations()["nginx.ingress.kubernetes.io/proxy-request-buffering"] == "off"
    assert "proxy_request_buffering off;" in NGINX_CONF.read_text()
    # a slow body is cut by the service (408 at RAFD_BODY_TIMEOUT_S), not by the proxy first
    for name in ("proxy-send-timeout", "proxy-read-timeout"):
        assert float(annotations()[f"nginx.ingress.kubernetes.io/{name}"]) > setting("body_timeout_s"), name


def test_a_replica_is_sized_for_two_cores_with_requests_equal_to_limits():
    resources = container()["resources"]
    assert resources["requests"] == resources["limits"]  # Guaranteed QoS: the quota the service sizes itself by
    assert str(resources["limits"]["cpu"]) == "2"  # whole cores: 2 model threads and 2 concurrent runs
    assert set(resources["limits"]) == {"cpu", "memory"}


def test_pod_runs_as_the_image_user_with_a_read_only_root_and_nothing_extra():
    uid = re.search(r"useradd --uid (\d+)", dockerfile())
    assert uid is not None and re.search(rf"^USER {uid.group(1)}$", dockerfile(), re.MULTILINE)
    pod = pod_spec()["securityContext"]
    assert pod["runAsNonRoot"] is True and pod["runAsUser"] == int(uid.group(1))
    assert pod["seccompProfile"] == {"type": "RuntimeDefault"}
    security = container()["securityContext"]
    assert security["readOnlyRootFilesystem"] is True
    assert security["allowPrivilegeEscalation"] is False
    assert security["capabilities"] == {"drop": ["ALL"]}
    assert security.get("privileged", False) is False
    assert pod_spec()["automountServiceAccountToken"] is False
    # /tmp (the image's working directory) is the only writable path, an emptyDir of bounded size
    volumes = {volume["name"]: volume for volume in pod_spec()["volumes"]}
    writable = [m for m in container()["volumeMounts"] if not m.get("readOnly")]
    assert [m["mountPath"] for m in writable] == ["/tmp"]
    assert re.search(r"^WORKDIR /tmp$", dockerfile(), re.MULTILINE)
    assert "sizeLimit" in volumes[writable[0]["name"]]["emptyDir"]
    assert not any("hostPath" in volume for volume in volumes.values())
    # the namespace enforces the restricted Pod Security Standard, which all of the above satisfies
    assert resource("Namespace")["metadata"]["labels"]["pod-security.kubernetes.io/enforce"] == "restricted"


def test_service_links_are_off_so_no_variable_falls_into_the_settings():
    """A Service named `rafd` would give every pod RAFD_PORT=tcp://10.x.y.z:8000 (and `rafd-foxglove`
    RAFD_FOXGLOVE_PORT): the image's CMD and the service's settings read those names."""
    assert pod_spec()["enableServiceLinks"] is False


def test_every_rafd_variable_is_a_setting_the_service_knows():
    """A misspelt RAFD_* variable would be ignored without a word (RAFD_PORT is the image's, for its CMD)."""
    known = {f"RAFD_{name.upper()}" for name in Settings.model_fields} | {"RAFD_PORT"}
    for name in env():
        if name.startswith("RAFD_"):
            assert name in known, name
    for name, value in env().items():
        if name.startswith("RAFD_") and name != "RAFD_PORT":
            Settings(**{name.removeprefix("RAFD_").lower(): value})  # and a value it accepts


def test_api_keys_come_from_a_secret_file_readable_by_the_pod_only():
    assert "RAFD_API_KEYS" not in env()  # no key in the manifests
    path = Path(env()["RAFD_API_KEYS_FILE"])
    volumes = {volume["name"]: volume for volume in pod_spec()["volumes"]}
    mounts = [m for m in container()["volumeMounts"] if path.parent == Path(m["mountPath"])]
    assert len(mounts) == 1 and mounts[0]["readOnly"] is True
    secret = volumes[mounts[0]["name"]]["secret"]
    assert secret["secretName"] == "rafd-api-keys"
    assert secret.get("optional", False) is False  # no Secret: the pod does not start, rather than serve keyless
    assert [item["path"] for item in secret["items"]] == [path.name]
    assert secret["defaultMode"] & 0o007 == 0, oct(secret["defaultMode"])  # nothing for others
    assert secret["defaultMode"] & 0o040  # the group (fsGroup) reads it: the pod does not run as the file's owner
    assert pod_spec()["securityContext"]["fsGroup"] == pod_spec()["securityContext"]["runAsGroup"]


def test_forwarded_addresses_are_trusted_only_from_the_ingress_controller():
    """The replicas trust X-Forwarded-For only from the pod network (never "*", issue 40: uvicorn then takes the
    leftmost entry, which a client chooses), and the NetworkPolicy lets only the controller connect from there."""
    import ipaddress

    trusted = env()["FORWARDED_ALLOW_IPS"]
    assert "*" not in trusted
    assert all(ipaddress.ip_network(item.strip()) for item in trusted.split(","))
    policy = resource("NetworkPolicy")["spec"]
    assert policy["podSelector"]["matchLabels"].items() <= pod_labels().items()
    assert "Ingress" in policy["policyTypes"]
    for rule in policy["ingress"]:
        assert rule.get("from"), "a rule without `from` admits every peer"
        for peer in rule["from"]:
            assert "ipBlock" not in peer and peer["namespaceSelector"] and peer["podSelector"]
        assert [named_port(port["port"]) for port in rule["ports"]] == [named_port("http")]
    # no egress: the service opens no connection of its own
    assert "Egress" in policy["policyTypes"] and not policy.get("egress")


def test_rollout_replaces_one_pod_at_a_time_and_nothing_scales_on_cpu():
    """maxUnavailable 0 / maxSurge 1: capacity never drops, and each step moves only the streams of the pod that
    joins or leaves the hash ring. No CPU autoscaler: every scaling step remaps streams and restarts their buffers."""
    deployment = resource("Deployment")
    assert deployment["spec"]["strategy"] == {
        "type": "RollingUpdate",
        "rollingUpdate": {"maxSurge": 1, "maxUnavailable": 0},
    }
    assert "HorizontalPodAutoscaler" not in {doc["kind"] for doc in load_resources()}
    assert resource("PodDisruptionBudget")["spec"]["maxUnavailable"] == 1


def test_image_is_the_serving_image_at_a_fixed_tag():
    image = container()["image"]
    name, _, tag = image.rpartition(":")
    assert name.rsplit("/", 1)[-1] == "rafd-serve", image  # the Dockerfile's image (docker build -t rafd-serve)
    assert tag and tag != "latest", "a fixed tag: every replica of a rollout runs the same build"
    assert "docker build -t rafd-serve" in dockerfile()
    # the image's own CMD runs (it serves on $RAFD_PORT): no command or args to keep in step with it
    assert "command" not in container() and "args" not in container()
