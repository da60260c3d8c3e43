"""/docs and /redoc work without internet: the service serves Swagger UI's and ReDoc's assets itself (fastapi-offline),
and headless Chromium (Debian's package), with every host but loopback unresolvable, renders the operations from a
service on loopback. Skips, saying so, where no Chromium is installed."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from tests.docs.test_site import CHROMIUM_FLAGS, chromium
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import serve_in_thread

# Every host name resolves to nothing but loopback: a page that needs a CDN loads no script.
OFFLINE = "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1"


def rendered_offline(url: str, profile: Path) -> str:
    binary = chromium()
    if binary is None:
        pytest.skip("no Chromium installed (Debian: apt-get install chromium; .ci/run installs it where it may)")
    done = subprocess.run(
        [
            binary,
            *CHROMIUM_FLAGS,
            OFFLINE,
            f"--user-data-dir={profile}",
            "--virtual-time-budget=15000",
            "--dump-dom",
            url,
        ],
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def test_the_docs_pages_load_nothing_from_other_hosts():
    with TestClient(create_app(Settings(threads=1), runner=FakeRunner())) as client:
        for page in ("/docs", "/redoc"):
            html = client.get(page).text
            sources = re.findall(r'(?:src|href)="([^"]+)"', html)
            assert sources and all(s.startswith("/static-offline-docs/") for s in sources), (page, sources)
            assert "https://" not in html and "http://" not in html
            for source in sources:
                asset = client.get(source)
                assert asset.status_code == 200 and len(asset.content) > 1000, source


@pytest.mark.slow
@pytest.mark.network
def test_swagger_ui_and_redoc_render_the_operations_with_no_network(tmp_path):
    app = create_app(Settings(threads=1), runner=FakeRunner())
    with serve_in_thread(app) as url:
        swagger = rendered_offline(f"{url}/docs", tmp_path / "profile-docs")
        redoc = rendered_offline(f"{url}/redoc", tmp_path / "profile-redoc")
    # Swagger UI drew one block per operation, /detect among them
    assert 'class="opblock opblock-post' in swagger, swagger[:2000]
    assert 'data-path="/detect"' in swagger and 'data-path="/streams/{stream_id}/detect"' in swagger
    # ReDoc drew the API's title and the /detect operation
    assert "RaFD radar detection service" in redoc and "/detect" in redoc, redoc[:2000]
