"""The documentation site: `mkdocs build --strict` from the repository, then the built index and the API page
rendered in headless Chromium (Debian's package): the navigation and a table must be on the rendered page.
Skips, saying so, where mkdocs or Chromium is not installed."""

from __future__ import annotations

import contextlib
import functools
import shutil
import subprocess
import sys
import threading
from collections.abc import Iterator
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
# As the library's probe starts it: no background networking (the machine's closed network refuses it), no sandbox
# (root), a fresh profile.
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)

pytestmark = pytest.mark.slow


def chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("mkdocs", reason="mkdocs is not installed (the docs extra: pip install -e '.[docs]')")
    out = tmp_path_factory.mktemp("site")
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "-d", str(out)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    return out


@contextlib.contextmanager
def served(folder: Path) -> Iterator[str]:
    handler = functools.partial(SimpleHTTPRequestHandler, directory=str(folder))
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


def rendered_dom(url: str, profile: Path) -> str:
    """The DOM after Chromium loaded the page and ran its scripts."""
    binary = chromium()
    if binary is None:
        pytest.skip("no Chromium installed (Debian: apt-get install chromium; .ci/run installs it where it may)")
    done = subprocess.run(
        [binary, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--virtual-time-budget=5000", "--dump-dom", url],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def test_every_page_of_the_navigation_is_built(site: Path):
    import yaml

    config = yaml.safe_load((REPO / "mkdocs.yml").read_text().replace("!!python/name:", ""))
    pages = []

    def walk(items: list) -> None:
        for item in items:
            value = next(iter(item.values())) if isinstance(item, dict) else item
            walk(value) if isinstance(value, list) else pages.append(value)

    walk(config["nav"])
    assert len(pages) >= 10
    for page in pages:
        built = site / (page[: -len(".md")] + "/index.html" if page != "index.md" else "index.html")
        assert built.is_file(), f"{page} was not built ({built})"


def test_index_and_api_pages_render_their_navigation_and_tables(site: Path, tmp_path: Path):
    with served(site) as url:
        index = rendered_dom(f"{url}/", tmp_path / "profile-index")
        api = rendered_dom(f"{url}/api/", tmp_path / "profile-api")
    for dom in (index, api):
        assert 'class="md-nav' in dom and "md-nav__link" in dom  # Material's navigation was rendered
        assert "Getting started" in dom  # ... and lists the pages
    assert "<table>" in api and "<td><code>invalid_image</code></td>" in api  # the error-code table rendered
