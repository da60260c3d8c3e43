"""bf16 with float32 islands at run time: the record that names them is read, served only with the folder it judged
(else a reason, and plain or no bf16), and the islands really run in float32 (the compiled model's per-node runtime
precision)."""

from __future__ import annotations

import json
import logging
import shutil

import numpy as np
import pytest

from rafd.model_files import ISLANDS_MANIFEST, islands_dir
from rafd.runtime import OnnxRunner, create_runner, open_runner
from rafd.runtime.runners import precision_choice, recorded_islands, reduced_unusable

pytest.importorskip("openvino", reason="the serve extra installs openvino")
onnx = pytest.importorskip("onnx")
from rafd.runtime.openvino_backend import openvino_supports_bf16, runtime_precisions  # noqa: E402
from rafd.runtime.openvino_islands import OpenVinoIslandsBackend, read_manifest  # noqa: E402
from tests.utils.islands_model import islands_record, make_islands_model  # noqa: E402

ISLANDS = ("/propagation/", "/head/")
ALL = [("onnxruntime", "fp32"), ("openvino", "bf16"), ("openvino", "fp32")]
needs_bf16 = pytest.mark.skipif(not openvino_supports_bf16(), reason="this CPU has no bf16 (avx512_bf16 or AMX)")


@pytest.fixture
def islands_model(ungated_onnx, tmp_path):
    """The shipped model with a passed bf16 record naming islands /propagation/, /head/ and their folder beside it."""
    return make_islands_model(ungated_onnx, tmp_path / "model.onnx", ISLANDS)


def _metadata(model) -> dict[str, str]:
    return {p.key: p.value for p in onnx.load(str(model), load_external_data=False).metadata_props}


def test_the_record_names_the_islands_and_plain_records_name_none():
    assert recorded_islands(islands_record(ISLANDS, "0" * 64)) == ISLANDS
    assert recorded_islands({}) == () and recorded_islands({"gate_bf16_figures": "not json"}) == ()
    assert reduced_unusable("m.onnx", "bf16", {"gate_bf16": "pass", "gate_bf16_figures": "{}"}) is None  # plain


def test_only_the_judged_folder_is_served(islands_model):
    metadata = _metadata(islands_model)
    assert reduced_unusable(islands_model, "bf16", metadata) is None
    choice = precision_choice(islands_model, metadata, ("auto", "auto"), ("openvino", "bf16"), {}, ALL)
    assert choice["allowed_precisions"] == ["fp32", "bf16"]
    assert "bf16 capable, gate passed with float32 islands /propagation/, /head/" in choice["reason"]
    folder = islands_dir(islands_model)
    with open(folder / "segment_1.onnx", "ab") as file:
        file.write(b"\0")
    assert "model.bf16-islands/ is not the folder its bf16 gate judged" in reduced_unusable(
        islands_model, "bf16", metadata
    )
    shutil.rmtree(folder)
    missing = precision_choice(islands_model, metadata, ("auto", "auto"), ("openvino", "fp32"), {}, ALL)
    assert missing["allowed_precisions"] == ["fp32"]
    assert (
        "gate passed but the float32 islands it passed with (model.bf16-islands/) are not beside it"
        in (missing["reason"])
    )


def test_a_broken_manifest_or_a_folder_of_another_graph_is_refused(islands_model):
    folder = islands_dir(islands_model)
    manifest = json.loads((folder / ISLANDS_MANIFEST).read_text())
    (folder / ISLANDS_MANIFEST).write_text(json.dumps({"segments": [{"file": "x.onnx", "precision": "fp16"}]}))
    with pytest.raises(ValueError, match="is not a bf16-islands manifest"):
        read_manifest(folder)
    manifest["segments"] = manifest["segments"][1:]  # the float32 segment alone: reads what nothing produced
    manifest["segments"][0]["precision"] = "fp32"
    (folder / ISLANDS_MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="segment segment_1.onnx reads .*never produced"):
        OpenVinoIslandsBackend(islands_model, folder, threads=1)


@pytest.mark.skipif(openvino_supports_bf16(), reason="this CPU has bf16: the refusal is for CPUs without it")
def test_without_bf16_the_islands_are_refused_with_the_reason(islands_model):
    with pytest.raises(ValueError, match="no bf16 support"):
        open_runner(islands_model, "openvino", "bf16", threads=1)


@needs_bf16
def test_the_islands_run_in_float32_and_the_rest_in_bf16(islands_model):
    runner = open_runner(islands_model, "openvino", "bf16", threads=1)  # the record says islands
    assert runner.precision == "bf16" and runner.islands == ISLANDS
    assert runner.describe()["float32_islands"] == list(ISLANDS)
    (_, bf16), (_, island) = runner.backend.segments
    in_bf16, in_fp32 = runtime_precisions(bf16.single), runtime_precisions(island.single)
    assert in_bf16[("Convolution", "bf16")] > 0 and ("Convolution", "f32") not in in_bf16
    # every convolution and matrix product of the islands in float32, none in bf16
    assert in_fp32[("Convolution", "f32")] > 0 and in_fp32[("FullyConnected", "f32")] > 0
    assert not [key for key in in_fp32 if key[1] == "bf16" and key[0] in ("Convolution", "FullyConnected")]
    reference = OnnxRunner(islands_model, threads=1)
    rng = np.random.default_rng(0)
    states = [reference.new_state(), runner.new_state()]
    size = reference.config.input_size
    for k in range(5):
        frame, pose = (rng.random((size, size)) * 0.4).astype(np.float32), np.array([1.0 * k, 0.0, 0.01 * k])
        ref, states[0] = reference.step(states[0], frame[None], pose[None])
        got, states[1] = runner.step(states[1], frame[None], pose[None])
    assert np.abs(got.scores - ref.scores).max() < 0.05 and np.isfinite(got.boxes).all()
    plain = open_runner(islands_model, "openvino", "bf16", threads=1, islands=False)
    assert plain.islands == () and len(plain.describe()["float32_islands"]) == 0


@needs_bf16
def test_a_changed_folder_serves_plain_bf16_only_when_asked_and_auto_skips_it(islands_model, caplog):
    with open(islands_dir(islands_model) / "segment_0.onnx", "ab") as file:
        file.write(b"\0")
    with caplog.at_level(logging.WARNING):
        asked = open_runner(islands_model, "openvino", "bf16", threads=1)
    assert asked.islands == () and "bf16 runs plain, without the islands its gate passed with" in caplog.text
    with pytest.raises(ValueError, match="is not the folder its bf16 gate judged"):
        open_runner(islands_model, "openvino", "bf16", threads=1, islands=True)
    with caplog.at_level(logging.INFO):
        auto = create_runner(islands_model, "openvino", "auto", threads=1, timer=lambda runner: 0.0)
    assert auto.precision != "bf16" and "openvino/bf16 not considered: model.bf16-islands/ is not the folder" in (
        caplog.text
    )
