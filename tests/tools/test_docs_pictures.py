"""The documentation's pictures: `python -m tools.docs_pictures --quick` still makes every one of them (tiny
settings), as valid and small PNGs with a manifest naming the model; the pictures kept in docs/images are small, all
listed in their manifest, shown by the docs, and made with the shipped model (regenerate them when it changes:
`python -m tools.docs_pictures --out docs/images`)."""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from tools.docs_pictures import MAX_BYTES, OXFORD_ENV, PICTURES, PictureError, write_small_png

REPO = Path(__file__).resolve().parents[2]
IMAGES = REPO / "docs" / "images"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
OXFORD_PICTURE = "detection_oxford.png"
OXFORD_DATA = (OXFORD_PICTURE, "odometry_error.png")  # pictures of the Oxford data (CC BY-NC-SA 4.0)
ALWAYS = sorted(f"{name}.png" for name in PICTURES if f"{name}.png" != OXFORD_PICTURE)


def shipped_model_name() -> str:
    from rafd.assets import default_checkpoint

    return hashlib.sha256(default_checkpoint().read_bytes()).hexdigest()[:8]


def assert_small_valid_png(path: Path) -> None:
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE and data[12:16] == b"IHDR", f"{path.name} is not a PNG"
    assert len(data) <= MAX_BYTES, f"{path.name}: {len(data)} bytes > {MAX_BYTES}"
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None, f"{path.name} does not decode"
    assert min(image.shape[:2]) >= 200, f"{path.name}: {image.shape[1]} x {image.shape[0]} px"
    assert image.std() > 5, f"{path.name} is blank"


@pytest.fixture(scope="module")
def quick(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str, float]:
    """One `python -m tools.docs_pictures --out OUT --quick` run, in this environment (RAFD_OXFORD_SAMPLE as set)
    -> (OUT, its output, seconds)."""
    for module, extra in (("torch", "train"), ("onnxruntime", "serve"), ("matplotlib", "train"), ("fastapi", "serve")):
        pytest.importorskip(module, reason=f"the pictures need the {extra} extra (pip install -e '.[dev]')")
    out = tmp_path_factory.mktemp("pictures")
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "tools.docs_pictures", "--out", str(out), "--quick"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    seconds = time.perf_counter() - start
    assert done.returncode == 0, (done.stdout + done.stderr)[-4000:]
    return out, done.stdout, seconds


@pytest.mark.slow
@pytest.mark.network  # rafd serve on loopback, twice
def test_quick_run_makes_every_picture_valid_and_small(quick):
    out, stdout, seconds = quick
    for name in ALWAYS:
        assert (out / name).is_file(), f"{name} missing:\n{stdout}"
        assert_small_valid_png(out / name)
    print(f"quick run: {seconds:.0f} s")


@pytest.mark.slow
@pytest.mark.network
def test_quick_run_writes_a_manifest_naming_model_commands_date_and_cpu(quick):
    out, _, _ = quick
    pictures = json.loads((out / "manifest.json").read_text())["pictures"]
    written = sorted(p.name for p in out.glob("*.png"))
    assert sorted(pictures) == written
    for name, entry in pictures.items():
        assert entry["model"]["checkpoint_sha256"] == shipped_model_name(), name
        assert entry["quick"] is True and entry["commands"] and entry["bytes"] == (out / name).stat().st_size
        assert re.fullmatch(r"\d{4}-\d\d-\d\d", entry["date"]) and entry["cpu"], name
        assert entry["command"].startswith("python -m tools.docs_pictures --out ")


@pytest.mark.slow
@pytest.mark.network
def test_quick_run_makes_the_oxford_picture_with_its_licence_or_says_why_not(quick):
    out, stdout, _ = quick
    if not os.environ.get(OXFORD_ENV):
        assert f"skipped {OXFORD_PICTURE}: {OXFORD_ENV} is not set" in stdout
        assert not (out / OXFORD_PICTURE).exists()
        pytest.skip(
            f"{OXFORD_ENV} is not set (point it at shared/oxford_radar_sample; .ci/run does): no Oxford picture"
        )
    assert_small_valid_png(out / OXFORD_PICTURE)
    entry = json.loads((out / "manifest.json").read_text())["pictures"][OXFORD_PICTURE]
    assert "CC BY-NC-SA 4.0" in entry["licence"] and "Barnes" in entry["licence"]
    from PIL import Image

    with Image.open(out / OXFORD_PICTURE) as image:
        assert "CC BY-NC-SA 4.0" in image.info["Copyright"]  # the licence travels inside the file too


def test_a_picture_that_cannot_be_made_small_is_refused(tmp_path):
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, (900, 900, 3), dtype=np.uint8)  # incompressible at any palette
    with pytest.raises(PictureError, match="bytes even at"):
        write_small_png(noise, tmp_path / "noise.png")
    assert not (tmp_path / "noise.png").exists()
    size = write_small_png(np.full((300, 400, 3), 40, np.uint8), tmp_path / "flat.png", {"Model": "x"})
    assert size == (tmp_path / "flat.png").stat().st_size < MAX_BYTES


def test_the_kept_pictures_are_small_listed_and_of_the_shipped_model():
    """docs/images: every picture the command makes, each small and valid, in manifest.json with the full (not
    --quick) settings and the shipped model; fails when the shipped model changes until the pictures are remade."""
    manifest = json.loads((IMAGES / "manifest.json").read_text())["pictures"]
    kept = sorted(p.name for p in IMAGES.glob("*.png"))
    assert kept == sorted(f"{name}.png" for name in PICTURES)
    assert sorted(manifest) == kept
    for name in kept:
        assert_small_valid_png(IMAGES / name)
        entry = manifest[name]
        assert entry["quick"] is False, f"{name} was made with --quick"
        assert entry["model"]["checkpoint_sha256"] == shipped_model_name(), (
            f"{name} shows model {entry['model']['checkpoint_sha256']}, not the shipped one: regenerate with "
            "python -m tools.docs_pictures --out docs/images"
        )
        assert entry["bytes"] == (IMAGES / name).stat().st_size, f"{name} changed after its manifest entry"


def test_every_kept_picture_is_shown_and_every_shown_picture_is_kept():
    shown: dict[str, list[str]] = {}
    pages = [*sorted((REPO / "docs").glob("*.md")), REPO / "README.md"]
    for page in pages:
        for alt, target in re.findall(r"!\[([^\]]*)\]\(([^)\s]+)", page.read_text()):
            path = (page.parent / target).resolve()
            assert path.is_file(), f"{page.name} shows {target}, which does not exist"
            shown.setdefault(path.name, []).append(page.name)
            if path.name in OXFORD_DATA:  # the dataset's attribution and licence in the alt text
                assert "CC BY-NC-SA 4.0" in alt and "Barnes" in alt, f"{page.name}: alt text of {target}"
    for name in (p.name for p in IMAGES.glob("*.png")):
        assert name in shown, f"docs/images/{name} is on no page"
    assert sorted(name for name, on in shown.items() if "README.md" in on) == ["detection_sim.png"]


def test_the_model_is_named_by_its_checkpoint_and_found_beside_either_file(tmp_path):
    pytest.importorskip("onnxruntime", reason="reading the ONNX metadata needs the serve extra")
    from rafd.assets import default_checkpoint, default_onnx
    from tools.docs_pictures import resolve_model

    shipped = resolve_model(None)
    assert (shipped.onnx, shipped.checkpoint) == (default_onnx(), default_checkpoint())
    assert shipped.checkpoint_sha256[:8] == shipped_model_name()
    from_pt = resolve_model(default_checkpoint())  # its export beside it
    assert from_pt.onnx == default_onnx()
    alone = tmp_path / "alone.onnx"
    alone.write_bytes(default_onnx().read_bytes())
    from_onnx = resolve_model(alone)  # no checkpoint beside it: named by the one it was exported from
    assert from_onnx.checkpoint is None and from_onnx.checkpoint_sha256 == shipped.checkpoint_sha256
    with pytest.raises(PictureError, match="does not exist"):
        resolve_model(tmp_path / "missing.onnx")
