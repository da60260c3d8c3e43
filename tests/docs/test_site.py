"""The documentation site: `mkdocs build --strict` from the repository, then the built index and the API page
rendered in headless Chromium (Debian's package): the navigation and a table must be on the rendered page, and every
image of every page must load in the browser (the pictures of docs/images). Skips, saying so, where mkdocs or
Chromium is not installed."""

from __future__ import annotations

import contextlib
import functools
import html
import json
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


def rendered_dom(url: str, profile: Path, budget_ms: int = 5000) -> str:
    """The DOM after Chromium loaded the page and ran its scripts."""
    binary = chromium()
    if binary is None:
        pytest.skip("no Chromium installed (Debian: apt-get install chromium; .ci/run installs it where it may)")
    done = subprocess.run(
        [
            binary,
            *CHROMIUM_FLAGS,
            f"--user-data-dir={profile}",
            f"--virtual-time-budget={budget_ms}",
            "--dump-dom",
            url,
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def nav_pages() -> list[str]:
    """The Markdown pages of mkdocs.yml's navigation, in order."""
    import yaml

    config = yaml.safe_load((REPO / "mkdocs.yml").read_text().replace("!!python/name:", ""))
    pages: list[str] = []

    def walk(items: list) -> None:
        for item in items:
            value = next(iter(item.values())) if isinstance(item, dict) else item
            walk(value) if isinstance(value, list) else pages.append(value)

    walk(config["nav"])
    return pages


def built_path(page: str) -> str:
    """A page's address in the built site, relative to its root ("" for the index)."""
    return "" if page == "index.md" else page[: -len(".md")] + "/"


def test_every_page_of_the_navigation_is_built(site: Path):
    pages = nav_pages()
    assert len(pages) >= 10
    for page in pages:
        built = site / built_path(page) / "index.html"
        assert built.is_file(), f"{page} was not built ({built})"


# Fetches each built page, finds its <img> elements, loads each image from the page's address in the browser and
# writes what each one loaded (naturalWidth: 0 when it did not) into #result, which --dump-dom prints. CONTROL, an
# image that does not exist, must come back 0: the check can fail. (Opening the pages themselves in iframes stalls
# headless Chromium's virtual time; Material's scripts add no image.)
IMAGE_CHECK = """<!doctype html><html><body><pre id="result">pending</pre><script>
const pages = PAGES;
function load(src) {
  return new Promise((resolve) => {
    const img = new Image();
    img.onload = () => resolve(img.naturalWidth);
    img.onerror = () => resolve(0);
    img.src = src;
  });
}
async function check(page) {
  const text = await (await fetch(page)).text();
  const doc = new DOMParser().parseFromString(text, "text/html");
  const found = [];
  for (const img of Array.from(doc.images)) {
    const src = img.getAttribute("src");
    found.push({src: src, width: await load(new URL(src, new URL(page, location.href)).href)});
  }
  return {page: page, images: found};
}
(async () => {
  const results = [];
  for (const page of pages) results.push(await check(page));
  const control = await load("CONTROL");
  document.getElementById("result").textContent = JSON.stringify({pages: results, control: control});
})().catch((error) => { document.getElementById("result").textContent = "error: " + error; });
</script></body></html>
"""


def test_every_image_on_every_page_loads_in_the_browser(site: Path, tmp_path: Path):
    pages = ["/" + built_path(p) for p in nav_pages()]
    check = IMAGE_CHECK.replace("PAGES", json.dumps(pages)).replace("CONTROL", "/images/no-such-picture.png")
    (site / "image-check.html").write_text(check)
    with served(site) as url:
        dom = rendered_dom(f"{url}/image-check.html", tmp_path / "profile-images", budget_ms=20000)
    text = html.unescape(dom.split('<pre id="result">', 1)[1].split("</pre>", 1)[0])
    assert text.startswith("{"), f"the image check did not finish: {text[:500]}"
    result = json.loads(text)
    assert result["control"] == 0  # a missing image reads 0: the check sees failures
    assert [r["page"] for r in result["pages"]] == pages
    shown: dict[str, list[str]] = {}
    for page in result["pages"]:
        for image in page["images"]:
            assert image["width"] > 0, f"{page['page']}: image {image['src']} did not load"
            shown.setdefault(Path(image["src"]).name, []).append(page["page"])
    kept = sorted(p.name for p in (REPO / "docs" / "images").glob("*.png"))
    assert kept and set(kept) <= set(shown), f"pictures on no rendered page: {set(kept) - set(shown)}"


def test_index_and_api_pages_render_their_navigation_and_tables(site: Path, tmp_path: Path):
    with served(site) as url:
        index = rendered_dom(f"{url}/", tmp_path / "profile-index")
        api = rendered_dom(f"{url}/api/", tmp_path / "profile-api")
    for dom in (index, api):
        assert 'class="md-nav' in dom and "md-nav__link" in dom  # Material's navigation was rendered
        assert "Getting started" in dom  # ... and lists the pages
    assert "<table>" in api and "<td><code>invalid_image</code></td>" in api  # the error-code table rendered
