"""Choosing float32 islands by measurement (export/islands_gate.py): the ranking, bf16's matrix-free units first,
the growing sets of matrix units, the first that passes kept beside the model with its record, none kept when none
passes; int8's finer units and its quantized file; the search runs only where the plain precision failed on enough
evidence; the files travel with the record (rafd gate --out, rafd export --gate)."""

from __future__ import annotations

import json
import shutil

import pytest

from export import gate as gate_module
from export.gate import gate_metadata
from export.gate_options import GateOptions, GateThresholds
from export.gate_report import GateReport, SourceFigures
from export.islands import search_units
from export.islands_gate import SEARCH_SEED, excess, perturbation, rank, search_islands
from rafd.model_files import ISLANDS_MANIFEST, file_sha256, int8_model_path, islands_dir, islands_sha256
from rafd.runtime.runners import recorded_islands, reduced_unusable

onnx = pytest.importorskip("onnx")

OPTIONS = GateOptions(sequences=12, frames=60, search_sequences=2, search_frames=40)


@pytest.fixture
def model(tmp_path):
    from rafd.assets import default_onnx

    try:
        return shutil.copy(default_onnx(), tmp_path / "model.onnx")
    except FileNotFoundError as error:
        pytest.skip(f"the shipped model is not built: {error}")


def _report(changed: int, frames: int = 699, detections: int = 1909, score: float | None = None) -> GateReport:
    """A report with `changed` detections changed; the matched scores move by `score` (by default, as the flips
    follow them, 1e-5 per changed detection over 0.001)."""
    figures = SourceFigures(frames=frames, reference_detections=detections, candidate_detections=detections)
    figures.changed = changed
    score = 0.001 + 1e-5 * changed if score is None else score
    figures.centre_shifts, figures.score_differences = [0.01] * (detections - changed), [score] * detections
    return GateReport("onnxruntime/fp32", "openvino/bf16", GateThresholds(), {"simulated": figures})


MATRIX_FREE = ("/encoder/normalise/", "/*", "/flow_encode/*", "/propagation/*", "/head/*")  # the shipped model's units
HEATMAP, MATCH = "/head/heatmap/", "/flow_match/*"


class FakeGate:
    """Changed detections by the islands a folder keeps in float32: the matrix-free units together 200 fewer, the
    heatmap 290, the matching 60, any other unit 1; the full gate sees 30 more changes than the short one (other
    drives), so a set can pass short and fail full (2% of 1909 detections is the limit)."""

    HELP = {HEATMAP: 290, MATCH: 60}
    FREE_HELP = 200

    def __init__(self) -> None:
        self.calls: list[tuple[tuple[str, ...], int, int, int]] = []

    def __call__(self, onnx_path, folder, sequences, frames, seed, radiate):
        islands = tuple(json.loads((folder / ISLANDS_MANIFEST).read_text())["islands"])
        self.calls.append((islands, sequences, frames, seed))
        helped = sum(self.HELP.get(u, 1) for u in islands if u not in MATRIX_FREE) + self.FREE_HELP
        return _report(max(0, 520 - helped) + (30 if sequences == 12 else 0))


@pytest.fixture
def manifests_only(monkeypatch):
    """The search's folders as their manifests alone (export/islands.py's own tests write and check segments): a
    search writes a folder per gate."""
    import export.islands_gate

    def write(onnx_path, islands, folder):
        folder.mkdir(exist_ok=True)
        (folder / ISLANDS_MANIFEST).write_text(json.dumps({"islands": list(islands), "segments": []}))
        return folder

    monkeypatch.setattr(export.islands_gate, "write_islands", write)


def test_excess_sums_the_checks_over_their_limits_and_counts_broken_arithmetic_heavily():
    assert excess(_report(0)) < excess(_report(38)) < excess(_report(200))
    broken = _report(0)
    broken.sources["simulated"].centre_shifts = [float("nan")] * 10
    assert excess(broken) >= 1e6


def test_passing_short_gates_rank_first_by_movement_failing_ones_by_how_far_over():
    passing_moved, passing_still = _report(30, score=0.004), _report(35, score=0.002)
    far, farther = _report(300, score=0.001), _report(1400, score=0.001)  # 16% and 73% changed: fail
    ranked = sorted([farther, passing_moved, far, passing_still], key=rank)
    assert ranked == [passing_still, passing_moved, far, farther]


def test_the_short_gates_rank_by_how_far_the_matched_detections_move(model, manifests_only):
    """A short gate's flip counts are a handful of events; the matched quantiles over hundreds of detections are what
    the search ranks by: the neck with 2 flips but scores moved 0.004 loses to the backbone with 6 flips and 0.002."""
    assert perturbation(_report(6, score=0.002)) < perturbation(_report(2, score=0.004))
    assert excess(_report(6, score=0.002)) > excess(_report(2, score=0.004))
    movement = {"/encoder/backbone/": (6, 0.002), "/encoder/neck/": (2, 0.004)}
    calls = []

    def gate(onnx_path, folder, sequences, frames, seed, radiate):
        islands = json.loads((folder / ISLANDS_MANIFEST).read_text())["islands"]
        calls.append((islands, sequences))
        added = [u for u in islands if u in movement]
        changed, score = movement[added[0]] if added else (400, 0.01)
        return _report(changed if sequences == 2 else 0, score=score)

    report = search_islands(model, _report(520), OPTIONS, None, log=lambda _: None, gate=gate)
    assert report.ok and "/encoder/backbone/" in report.islands and "/encoder/neck/" not in report.islands
    assert [e["perturbation"] for e in report.search[:3]][1:] == [
        round(perturbation(_report(400, score=0.01)), 3),
        round(perturbation(_report(6, score=0.002)), 3),
    ]


def test_the_matrix_units_grow_by_forward_selection_and_the_first_set_the_full_gate_passes_is_kept(
    model, manifests_only
):
    matrix_free, matrix = search_units(onnx.load(str(model), load_external_data=False))
    assert tuple(matrix_free) == MATRIX_FREE and HEATMAP in matrix and MATCH in matrix
    ordered = lambda *units: tuple(u for u in matrix_free + matrix if u in units)  # noqa: E731 (graph order)
    fake = FakeGate()
    report = search_islands(model, _report(520), OPTIONS, None, log=lambda _: None, gate=fake)
    short, full = (2, 40, SEARCH_SEED), (12, 60, 7100)  # short gates on other drives than the gate's (its seed)
    assert fake.calls == [
        (MATRIX_FREE, *short),  # the matrix-free units alone: 320 changed
        *[(ordered(*MATRIX_FREE, u), *short) for u in matrix],  # each matrix unit added: the heatmap is best
        (ordered(*MATRIX_FREE, HEATMAP), *full),  # 30 changed short, 60 full: fails
        *[(ordered(*MATRIX_FREE, HEATMAP, u), *short) for u in matrix if u != HEATMAP],
        (ordered(*MATRIX_FREE, HEATMAP, MATCH), *full),  # 30 changed: passes
    ]
    assert report.ok and report.islands == ordered(*MATRIX_FREE, HEATMAP, MATCH)
    folder = islands_dir(model)
    assert tuple(json.loads((folder / ISLANDS_MANIFEST).read_text())["islands"]) == report.islands
    assert report.islands_sha256 == islands_sha256(folder)
    assert [(e["islands"], e["gate"], e["pass"]) for e in report.search][:1] == [([], "full", False)]
    assert [e["gate"] for e in report.search].count("full") == 3 and report.search[-1]["pass"] is True
    assert report.search[-1]["figures"]["simulated"]["changed_fraction"] == round(30 / 1909, 4)
    assert sorted(p.name for p in model.parent.iterdir()) == ["model.bf16-islands", "model.onnx"]  # nothing else left


def test_when_no_set_short_of_all_the_matrix_work_passes_bf16_stays_failed(model, manifests_only):
    class Hopeless(FakeGate):
        HELP = {HEATMAP: 3}
        FREE_HELP = 2

    fake = Hopeless()
    report = search_islands(model, _report(520), OPTIONS, None, log=lambda _: None, gate=fake)
    assert not report.ok and report.islands == () and report.islands_sha256 is None
    _, matrix = search_units(onnx.load(str(model), load_external_data=False))
    steps = range(len(matrix), 1, -1)  # the matrix units left to try at each step, never the last alone
    assert len(report.search) == 1 + 1 + sum(steps) == 1 + len(fake.calls)
    assert max(len(call[0]) for call in fake.calls) == len(MATRIX_FREE) + len(matrix) - 1  # never all of them
    assert all(call[1] == 2 for call in fake.calls)  # no short gate came close: no full gate ran
    assert not islands_dir(model).exists() and sorted(p.name for p in model.parent.iterdir()) == ["model.onnx"]


@pytest.mark.parametrize("precision", ["bf16", "int8"])
@pytest.mark.parametrize("plain, searched", [(_report(520), True), (_report(0), False), (_report(5, frames=20), False)])
def test_the_search_runs_only_where_the_plain_precision_failed_on_enough_evidence(
    model, monkeypatch, fake_quantize, precision, plain, searched
):
    import rafd.runtime

    monkeypatch.setattr(rafd.runtime, "supported_choices", lambda: [("onnxruntime", "fp32"), ("openvino", precision)])
    monkeypatch.setattr(gate_module, "gate_model", lambda *args, **kwargs: plain)
    searches = []
    monkeypatch.setattr(gate_module, "search_islands", lambda *args, **kwargs: searches.append(kwargs) or plain)
    gate_module.run_export_gates(model, OPTIONS, log=lambda _: None)
    assert bool(searches) is searched
    if searched:  # int8's search quantizes with the calibration the plain model was quantized with
        assert searches[0]["precision"] == precision
        assert searches[0]["calibration"] == ("the calibration" if precision == "int8" else None)
        assert fake_quantize == ([1] if precision == "int8" else [])
    searches.clear()
    gate_module.run_export_gates(model, GateOptions(islands=False), log=lambda _: None)  # --no-islands
    assert not searches


INT8_STEM, INT8_HEATMAP, MATCH_INT8 = "/encoder/backbone/stem/", "/head/heatmap/net/", "/flow_match/*"


@pytest.fixture
def fake_quantize(monkeypatch):
    """int8 candidates as JSON files naming their islands (tests/export/test_quantize.py quantizes for real); the
    calibrations made, counted."""
    import export.quantize

    made = []

    def quantize(onnx_path, out=None, islands=(), calibration=None, log=None):
        assert calibration == "the calibration"
        target = out or int8_model_path(onnx_path)
        target.write_text(json.dumps(list(islands)))
        return target

    monkeypatch.setattr(export.quantize, "quantize_model", quantize)
    monkeypatch.setattr(export.quantize, "calibrate", lambda *a, **k: made.append(1) or "the calibration")
    return made


def test_int8_quantizes_the_least_sensitive_units_first_and_the_passing_file_replaces_the_plain_one(
    model, fake_quantize
):
    """int8's units lie a level below bf16's (the backbone's stem alone); each quantized alone ranks them; least
    sensitive first, a unit joins the quantized set while the short gate's accuracy holds; the full gate returns the
    last one joined to float32 while it fails; one calibration serves every set, and the passing set's file becomes
    MODEL.int8.onnx, named in the record by its sha256."""
    from export.islands_gate import INT8_UNIT_DEPTH

    _, matrix = search_units(onnx.load(str(model), load_external_data=False), INT8_UNIT_DEPTH)
    assert INT8_STEM in matrix and INT8_HEATMAP in matrix and "/encoder/backbone/" not in matrix
    int8_model_path(model).write_text("the plain int8 model")
    # detections changed per unit quantized (2% of 1909 is 38): the stem and the heatmap fail alone, the matching
    # passes alone and with the rest on a short gate (17 + 20), not on the full one (5 more)
    damage = {INT8_STEM: 200, INT8_HEATMAP: 290, MATCH_INT8: 20}
    calls = []

    def gate(onnx_path, candidate, sequences, frames, seed, radiate):
        quantized = [u for u in matrix if u not in json.loads(candidate.read_text())]
        calls.append((tuple(quantized), sequences))
        return _report(sum(damage.get(u, 1) for u in quantized) + (5 if sequences == 12 else 0))

    report = search_islands(model, _report(520), OPTIONS, None, log=lambda _: None, gate=gate, precision="int8")
    ordered = lambda *units: tuple(u for u in matrix if u in units)  # noqa: E731 (graph order)
    light = [u for u in matrix if u not in damage]
    assert calls[: len(matrix)] == [((u,), 2) for u in matrix]  # each unit quantized alone
    joined = [(ordered(*light[: k + 1]), 2) for k in range(1, len(light))]  # least sensitive first
    tried = [(ordered(*light, MATCH_INT8), 2)] + [
        (ordered(*light, MATCH_INT8, u), 2) for u in (INT8_STEM, INT8_HEATMAP)
    ]
    assert calls[len(matrix) :] == joined + tried + [(ordered(*light, MATCH_INT8), 12), (ordered(*light), 12)]
    assert report.ok and report.islands == ordered(INT8_STEM, MATCH_INT8, INT8_HEATMAP)
    assert json.loads(int8_model_path(model).read_text()) == list(report.islands)
    assert report.judged_sha256 == file_sha256(int8_model_path(model)) and report.islands_sha256 is None
    assert fake_quantize == [1]  # calibrated once
    assert sorted(p.name for p in model.parent.iterdir()) == ["model.int8.onnx", "model.onnx"]
    recorded = json.loads(gate_metadata({"int8": report})["gate_int8_figures"])
    assert recorded["islands"] == list(report.islands) and recorded["int8_sha256"] == report.judged_sha256
    assert "islands_sha256" not in recorded and [e["gate"] for e in recorded["islands_search"]].count("full") == 3


def test_when_no_int8_set_passes_the_plain_int8_file_stays_the_judged_one(model, fake_quantize):
    int8_model_path(model).write_text("the plain int8 model")
    plain = _report(520)
    plain.judged_sha256 = file_sha256(int8_model_path(model))
    report = search_islands(
        model, plain, OPTIONS, None, log=lambda _: None, gate=lambda *args: _report(520), precision="int8"
    )
    assert not report.ok and report.islands == () and report.judged_sha256 == plain.judged_sha256
    assert int8_model_path(model).read_text() == "the plain int8 model"
    assert sorted(p.name for p in model.parent.iterdir()) == ["model.int8.onnx", "model.onnx"]


def test_the_record_names_the_islands_and_out_takes_their_folder(model, tmp_path, monkeypatch):
    import export.gate
    from export.gate import gate_and_record
    from export.islands import write_islands

    report = _report(0)
    report.islands = ("/head/",)
    report.search = [{"islands": [], "gate": "full", "pass": False}]

    def gates(onnx_path, options, log):  # the search's pass: its folder written beside the model it gates
        report.islands_sha256 = islands_sha256(write_islands(onnx_path, report.islands))
        return {"bf16": report}

    monkeypatch.setattr(export.gate, "run_export_gates", gates)
    out = tmp_path / "elsewhere" / "gated.onnx"
    out.parent.mkdir()
    gate_and_record(model, OPTIONS, out, log=lambda _: None)
    entries = gate_metadata({"bf16": report})
    recorded = json.loads(entries["gate_bf16_figures"])
    assert recorded["islands"] == ["/head/"] and recorded["islands_sha256"] == report.islands_sha256
    assert recorded["islands_search"] == report.search and recorded_islands(entries) == ("/head/",)
    assert islands_sha256(islands_dir(out)) == report.islands_sha256 and not islands_dir(model).exists()
    metadata = {p.key: p.value for p in onnx.load(str(out)).metadata_props}
    assert reduced_unusable(out, "bf16", metadata) is None


def test_export_gate_puts_the_judged_files_beside_the_output(tmp_path, monkeypatch):
    """rafd export --gate judges a temporary file: the int8 model and the islands it judged must end beside the
    output under the output's name, and nothing temporary stays."""
    import export.onnx_export
    from export.cli import main
    from export.islands import write_islands
    from tests.utils.export_testing import make_checkpoint, small_config

    pytest.importorskip("torch")

    def fake_gates(onnx_path, options, log):
        folder = write_islands(onnx_path, ("/head/",))
        shutil.copy(onnx_path, int8_model_path(onnx_path))
        bf16 = _report(0)
        bf16.islands, bf16.islands_sha256 = ("/head/",), islands_sha256(folder)
        return {"bf16": bf16}

    monkeypatch.setattr(export.onnx_export, "run_export_gates", fake_gates)
    checkpoint = make_checkpoint(tmp_path / "model.pt", small_config(4))
    output = tmp_path / "gated.onnx"
    assert main([str(checkpoint), str(output), "--no-verify", "--gate"]) == 0
    metadata = {p.key: p.value for p in onnx.load(str(output)).metadata_props}
    assert recorded_islands(metadata) == ("/head/",) and reduced_unusable(output, "bf16", metadata) is None
    assert int8_model_path(output).is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["model.pt", "gated.onnx", "gated.int8.onnx", "gated.bf16-islands"]
    )


def test_a_real_islands_gate_judges_the_segments(model):
    """The gate of one islands set on this CPU's OpenVINO bf16 (a small sample: its verdict is not what is tested)."""
    from export.gate_run import gate_model
    from export.islands import write_islands
    from rafd.runtime.openvino_backend import openvino_supports_bf16

    pytest.importorskip("torch")
    if not openvino_supports_bf16():
        pytest.skip("this CPU has no bf16 (avx512_bf16 or AMX): the islands cannot be gated here")
    folder = write_islands(model, ("/propagation/", "/head/"))
    report = gate_model(model, ("openvino", "bf16"), sequences=1, frames=16, threads=1, islands=folder)
    assert report.candidate == "openvino/bf16" and report.pooled.frames == 16 - 3
    assert report.ok == all(ok for *_, ok in report.checks())
