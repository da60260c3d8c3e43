"""Opening a RaFD graph on a runtime: OnnxRunner (the fp32 reference), OpenVinoRunner, and create_runner, which
picks the fastest runtime and precision this CPU supports by timing them on the model itself."""

from __future__ import annotations

import json
import logging
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import numpy as np

from rafd.cpu import usable_cpus
from rafd.model_files import checkpoint_given_for_onnx, file_sha256, int8_model_path, islands_dir, islands_sha256
from rafd.protocol import GATE_MIN_FRAMES, GATE_MIN_REFERENCE_DETECTIONS
from rafd.runtime.backend import DYNAMIC, PRECISIONS, RUNTIMES, shapes_at
from rafd.runtime.ort_backend import OrtBackend
from rafd.runtime.streaming import StreamRunner

log = logging.getLogger(__name__)

# Metadata key `rafd gate` and rafd-export --gate write ("pass"/"fail" per reduced precision): precision "auto"
# picks a reduced precision only where this model's gate passed (fp32 is the reference and needs no gate).
GATE_KEY = "gate_{precision}"


def gate_passed(metadata: dict[str, str], precision: str) -> bool:
    """fp32, or a reduced precision whose accuracy gate passed for this model on enough evidence: a "pass" verdict
    whose recorded figures (GATE_KEY + "_figures") compared at least rafd.protocol.GATE_MIN_FRAMES windows and
    GATE_MIN_REFERENCE_DETECTIONS reference detections (a file gated before the gate refused to judge too little
    may say "pass" on nothing)."""
    if precision == "fp32":
        return True
    key = GATE_KEY.format(precision=precision)
    if metadata.get(key) != "pass":
        return False
    frames, detections = gate_evidence(metadata.get(key + "_figures"))
    return frames >= GATE_MIN_FRAMES and detections >= GATE_MIN_REFERENCE_DETECTIONS


def gate_evidence(figures_json: str | None) -> tuple[int, int]:
    """(compared windows, reference detections) of all sources together from a gate's recorded figures; (0, 0)
    when absent or unreadable."""
    try:
        figures = json.loads(figures_json or "")["figures"]
        pooled = figures["all"] if "all" in figures else next(iter(figures.values()))
        return int(pooled["frames"]), int(pooled["reference_detections"])
    except (ValueError, KeyError, TypeError, StopIteration):
        return 0, 0


def gate_record(metadata: dict[str, str], precision: str) -> str:
    """What the model records for a reduced precision's accuracy gate: "pass" (on enough evidence, as gate_passed),
    "fail", "pass on too little evidence" (a file gated before the gate refused to judge too little) or "none"."""
    verdict = metadata.get(GATE_KEY.format(precision=precision))
    if verdict is None:
        return "none"
    if verdict != "pass":
        return "fail"
    return "pass" if gate_passed(metadata, precision) else "pass on too little evidence"


def _recorded(metadata: dict[str, str], precision: str) -> dict[str, Any]:
    """A reduced precision's recorded gate figures as a dict ({} when absent or unreadable)."""
    try:
        recorded = json.loads(metadata.get(GATE_KEY.format(precision=precision) + "_figures") or "")
    except ValueError:
        return {}
    return recorded if isinstance(recorded, dict) else {}


def recorded_islands(metadata: dict[str, str], precision: str = "bf16") -> tuple[str, ...]:
    """The units a reduced precision's gate record keeps in float32 (its "islands"; export/islands_gate.py), () for
    the plain precision: the service serves bf16 as those islands' segments (MODEL.bf16-islands/) when the record
    names any; int8's are left unquantized in MODEL.int8.onnx, the file the record judged."""
    islands = _recorded(metadata, precision).get("islands") or []
    return tuple(str(scope) for scope in islands) if isinstance(islands, list) else ()


def gate_origin(metadata: dict[str, str], precision: str) -> str:
    """ " (made on CPU, date)" from a gate record's figures (rafd gate and rafd export --gate write them), else ""."""
    try:
        figures = json.loads(metadata.get(GATE_KEY.format(precision=precision) + "_figures") or "")
        made = [str(figures[key]) for key in ("cpu", "date") if figures.get(key)]
    except (ValueError, TypeError, AttributeError):
        return ""
    return f" (made on {', '.join(made)})" if made else ""


def precision_choice(
    model_path: str | os.PathLike[str],
    metadata: dict[str, str],
    requested: tuple[str, str],
    served: tuple[str, str],
    selection: dict[str, float],
    supported: list[tuple[str, str]],
) -> dict[str, object]:
    """Why `served` (runtime, precision) serves this model: the precisions this CPU could run (`supported`, as
    supported_choices), what the model's gate records say of each reduced one, which precisions they allow, and one
    sentence saying why (rafd serve logs it at start-up; GET /model reports all of it)."""
    cpu = sorted({p for _, p in supported}, key=PRECISIONS.index)
    reduced = [p for p in cpu if p != "fp32"]
    records = {p: gate_record(metadata, p) for p in PRECISIONS if p != "fp32"}
    unusable = {p: reduced_unusable(model_path, p, metadata) for p in records if records[p] == "pass"}
    allowed = [p for p in cpu if p == "fp32" or (records[p] == "pass" and not unusable.get(p))]
    runtime, precision = served
    serving = f"serving {runtime}/{precision}"
    islands = {p: ", ".join(recorded_islands(metadata, p)) for p in records}
    if precision in islands and islands[precision] and records[precision] == "pass" and not unusable[precision]:
        # as open_runner runs it (a failed record names no islands)
        serving += f" with float32 islands {islands[precision]}"
    if len(selection) > 1:
        others = ", ".join(f"{name} {ms:g} ms" for name, ms in selection.items() if name != f"{runtime}/{precision}")
        serving += f", the fastest timed at start-up ({selection[f'{runtime}/{precision}']:g} ms a run; {others})"
    if requested[1] != "auto":
        if precision != "fp32" and records.get(precision) != "pass":
            reason = f"precision {precision} set by the operator, without a passed accuracy gate: {serving}"
        else:
            reason = f"precision {precision} set by the operator: {serving}"
    elif not reduced:
        reason = (
            "this CPU runs no reduced precision (bf16 needs the openvino package and avx512_bf16 or AMX, int8 VNNI or "
            "AMX): " + serving
        )
    else:
        parts = []
        for p in reduced:
            record = records[p]
            origin = gate_origin(metadata, p)
            if record == "none":
                parts.append(f"{p} capable, no gate record for this model")
            elif record == "pass" and unusable.get(p):
                parts.append(f"{p} capable, gate passed{origin} but {unusable[p]}")
            elif record == "pass" and islands[p]:
                parts.append(f"{p} capable, gate passed{origin} with float32 islands {islands[p]}")
            elif record == "pass":
                parts.append(f"{p} capable, gate passed{origin}")
            else:
                parts.append(f"{p} capable, gate record {record}{origin}")
        reason = "; ".join(parts) + ": " + serving
        missing = [p for p in reduced if records[p] in ("none", "pass on too little evidence")]
        if missing and precision == "fp32":
            reason += f"; run `rafd gate {model_path}`"
    return {"cpu_precisions": cpu, "gate_records": records, "allowed_precisions": allowed, "reason": reason}


def crowd_threads(threads: int, concurrent_runs: int) -> int | None:
    """Threads per run while several run at once (the cores shared out), None when no second compilation is
    needed (one run at a time, or already one thread per run)."""
    if concurrent_runs <= 1 or threads <= 1:
        return None
    return max(1, threads // concurrent_runs)


class OnnxRunner(StreamRunner):
    """StreamRunner over onnxruntime, float32 (the reference path). `threads`: intra-op threads of a run alone;
    with concurrent_runs > 1, runs that overlap use a second session of threads // concurrent_runs threads."""

    def __init__(
        self, model_path: str | os.PathLike[str], threads: int | None = None, concurrent_runs: int = 1
    ) -> None:
        threads = threads or usable_cpus()
        shared = crowd_threads(threads, concurrent_runs)
        # With overlapping runs, a finished run's pool threads must not spin on the cores the others need.
        spinning = concurrent_runs == 1
        super().__init__(
            OrtBackend(model_path, threads, 1 if shared else concurrent_runs, spinning),
            OrtBackend(model_path, shared, concurrent_runs, spinning) if shared else None,
        )

    @property
    def session(self) -> Any:  # onnxruntime.InferenceSession: an untyped library, not imported at module level
        return cast(OrtBackend, self.backend).session  # __init__ gives it an OrtBackend


class OpenVinoRunner(StreamRunner):
    """StreamRunner over OpenVINO's CPU plugin in `precision` ("bf16", "int8" or "fp32"); threads and concurrent runs
    as OnnxRunner (the overlapping runs use one compilation with concurrent_runs CPU streams). `islands`: a
    bf16-islands folder (export/islands.py) to run bf16 as its segments, the islands in float32. `quantized`: the
    int8 model to run instead of MODEL.int8.onnx. `islands` (the attribute): the units kept in float32, by either."""

    def __init__(
        self,
        model_path: str | os.PathLike[str],
        precision: str = "bf16",
        threads: int | None = None,
        concurrent_runs: int = 1,
        islands: str | os.PathLike[str] | None = None,
        quantized: str | os.PathLike[str] | None = None,
    ) -> None:
        from rafd.runtime.openvino_backend import OpenVinoBackend
        from rafd.runtime.openvino_islands import OpenVinoIslandsBackend

        if islands is not None and precision != "bf16":
            raise ValueError(f"float32 islands are a form of bf16, not of {precision!r}")
        threads = threads or usable_cpus()
        shared = crowd_threads(threads, concurrent_runs)

        def backend(threads: int, runs: int) -> OpenVinoBackend | OpenVinoIslandsBackend:
            if islands is not None:
                return OpenVinoIslandsBackend(model_path, islands, threads, runs)
            return OpenVinoBackend(model_path, precision, threads, runs, quantized)

        super().__init__(
            backend(threads, 1 if shared else concurrent_runs), backend(shared, concurrent_runs) if shared else None
        )
        self.islands: tuple[str, ...] = getattr(self.backend, "islands", ())


def supported_choices() -> list[tuple[str, str]]:
    """(runtime, precision) pairs this machine can run: onnxruntime fp32 always; OpenVINO when installed, bf16 only
    where the CPU computes it (avx512_bf16 or AMX), int8 only where it has int8 dot-product units (VNNI or AMX)."""
    from rafd.cpu import INT8_UNITS, has_units
    from rafd.runtime.openvino_backend import openvino_supports_bf16

    choices = [("onnxruntime", "fp32")]
    try:
        import openvino  # noqa: F401
    except ImportError:
        return choices
    if openvino_supports_bf16():
        choices.append(("openvino", "bf16"))
    if has_units(INT8_UNITS):
        choices.append(("openvino", "int8"))
    choices.append(("openvino", "fp32"))
    return choices


def reduced_unusable(model_path: str | os.PathLike[str], precision: str, metadata: dict[str, str]) -> str | None:
    """Why the files a passed gate judged, beside `model_path`, may not be served as that precision, or None. The
    record in MODEL.onnx names them by sha256, so a file replaced or made again after the gate is not taken for the
    one that passed: int8 the quantized MODEL.int8.onnx; bf16 with float32 islands the MODEL.bf16-islands/ folder
    (plain bf16 runs MODEL.onnx itself and needs nothing beside it)."""
    if precision == "bf16":
        return _islands_unusable(model_path, metadata) if recorded_islands(metadata) else None
    if precision != "int8":
        return None
    quantized = int8_model_path(model_path)
    if not quantized.is_file():
        return f"no quantized model {quantized.name} beside it"
    try:
        judged = json.loads(metadata.get(GATE_KEY.format(precision="int8") + "_figures") or "")["int8_sha256"]
    except (ValueError, KeyError, TypeError):
        return "its int8 gate record names no quantized file"
    if judged != file_sha256(quantized):
        return f"{quantized.name} is not the file its int8 gate judged (sha256 differs)"
    return None


def _islands_unusable(model_path: str | os.PathLike[str], metadata: dict[str, str]) -> str | None:
    folder = islands_dir(model_path)
    if not folder.is_dir():
        return f"the float32 islands it passed with ({folder.name}/) are not beside it"
    try:
        digest = islands_sha256(folder)
    except (OSError, ValueError, KeyError, TypeError) as error:
        return f"{folder.name}/ is not a readable bf16-islands folder ({error})"
    if digest != _recorded(metadata, "bf16").get("islands_sha256"):
        return f"{folder.name}/ is not the folder its bf16 gate judged (sha256 differs)"
    return None


def open_runner(
    model_path: str | os.PathLike[str],
    runtime: str,
    precision: str,
    threads: int | None = None,
    concurrent_runs: int = 1,
    islands: bool | None = None,
) -> StreamRunner:
    """One explicit (runtime, precision). OpenVINO bf16 runs as float32 islands and bf16 segments where `islands`
    is True (the folder beside the model must be the one its bf16 gate judged, else a ValueError), plain where it is
    False, and as the model's bf16 gate record says where None (plain, with a warning, if the recorded islands'
    folder is missing or changed)."""
    wrong_kind = checkpoint_given_for_onnx(model_path)
    if wrong_kind:
        raise ValueError(wrong_kind)
    if runtime == "onnxruntime":
        if precision != "fp32":
            raise ValueError(f"onnxruntime runs RaFD in fp32 only, not {precision!r} (use runtime openvino)")
        return OnnxRunner(model_path, threads, concurrent_runs)
    if runtime == "openvino":
        try:
            import openvino  # noqa: F401
        except ImportError as error:
            raise ValueError("runtime openvino needs the `openvino` package (pip install 'rafd[serve]')") from error
        return OpenVinoRunner(
            model_path, precision, threads, concurrent_runs, _islands_folder(model_path, precision, islands)
        )
    raise ValueError(f"runtime must be one of {RUNTIMES} or 'auto', got {runtime!r}")


def _islands_folder(model_path: str | os.PathLike[str], precision: str, islands: bool | None) -> Path | None:
    """The bf16-islands folder open_runner runs (None: plain)."""
    if precision != "bf16" or islands is False:
        return None
    from rafd.runtime.openvino_backend import describe

    metadata = describe(model_path)[0]
    if not recorded_islands(metadata):
        if islands:
            raise ValueError(f"{model_path}'s bf16 gate record names no float32 islands (rafd gate {model_path})")
        return None
    unusable = _islands_unusable(model_path, metadata)
    if unusable and islands:
        raise ValueError(f"{model_path}: {unusable}")
    if unusable:
        log.warning("%s: %s; bf16 runs plain, without the islands its gate passed with", model_path, unusable)
        return None
    return islands_dir(model_path)


def time_runner(runner: StreamRunner, repeats: int = 3, warmup: int = 1, seed: int = 0, views: int = 1) -> float:
    """Median seconds of one graph run of `views` rows (a whole scan's tiles step as one run) on random inputs of the
    graph's shapes (frames in [0, 1])."""
    rng = np.random.default_rng(seed)
    batch = views if runner.batch == DYNAMIC else 1
    feeds = {
        name: rng.random(shape, dtype=np.float32)
        for name, shape in shapes_at(runner.backend.input_shapes, batch).items()
    }
    for _ in range(warmup):
        runner.run(feeds)
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        runner.run(feeds)
        samples.append(time.perf_counter() - start)
    return statistics.median(samples)


def _name(runner: StreamRunner) -> str:
    return f"{runner.runtime}/{runner.precision}"


def _interleaved_medians(
    runners: list[StreamRunner], timer: Callable[[StreamRunner], float], rounds: int
) -> dict[str, float]:
    """Median of `rounds` timings per runner, taken round-robin (each round times every runner once)."""
    samples: dict[str, list[float]] = {_name(r): [] for r in runners}
    for _ in range(rounds):
        for runner in runners:
            samples[_name(runner)].append(timer(runner))
    return {name: statistics.median(values) for name, values in samples.items()}


def create_runner(
    model_path: str | os.PathLike[str],
    runtime: str = "auto",
    precision: str = "auto",
    threads: int | None = None,
    concurrent_runs: int = 1,
    timer: Callable[[StreamRunner], float] = time_runner,
    rounds: int = 3,
) -> StreamRunner:
    """Open the model on the given runtime and precision; "auto" (either) times every supported candidate on this
    model and keeps the fastest. With precision "auto" a reduced precision is a candidate only when the model's
    accuracy gate passed for it (metadata GATE_KEY); an explicit precision is the operator's choice (logged
    when ungated).

    The chosen runner's `selection` maps "runtime/precision" to the measured median ms of one run: the median of
    `rounds` calls of `timer`, the candidates interleaved, so that a slow second of a shared machine falls on all of
    them rather than on whichever was timed then.
    """
    if runtime not in RUNTIMES + ("auto",):
        raise ValueError(f"runtime must be one of {RUNTIMES} or 'auto', got {runtime!r}")
    if precision not in PRECISIONS + ("auto",):
        raise ValueError(f"precision must be one of {PRECISIONS} or 'auto', got {precision!r}")
    supported = supported_choices()
    if runtime != "auto" and precision != "auto":
        runner = open_runner(model_path, runtime, precision, threads, concurrent_runs)
        if not gate_passed(runner.metadata, runner.precision):
            log.warning("%s runs in %s without a passed accuracy gate (rafd gate)", model_path, precision)
        runner.precision_choice = precision_choice(
            model_path, runner.metadata, (runtime, precision), (runner.runtime, runner.precision), {}, supported
        )
        return runner
    candidates = [(r, p) for r, p in supported if runtime in ("auto", r) and precision in ("auto", p)]
    if not candidates:
        raise ValueError(
            f"no supported runtime for runtime={runtime!r}, precision={precision!r} on this machine "
            f"(supported: {supported})"
        )
    runners: list[StreamRunner] = []
    metadata: dict[str, str] | None = None  # known after the first candidate is open
    for candidate in candidates:
        if precision == "auto" and metadata is not None and not gate_passed(metadata, candidate[1]):
            log.info("%s/%s not considered: no passed accuracy gate for this model in that precision", *candidate)
            continue
        if candidate[1] != "fp32" and metadata is not None and precision == "auto":
            unusable = reduced_unusable(model_path, candidate[1], metadata)
            if unusable:
                log.info("%s/%s not considered: %s", *candidate, unusable)
                continue
        runner = open_runner(model_path, *candidate, threads, concurrent_runs)
        metadata = runner.metadata
        if precision == "auto" and not gate_passed(metadata, runner.precision):
            log.info("%s/%s not considered: no passed accuracy gate for this model in that precision", *candidate)
            continue
        unusable = reduced_unusable(model_path, candidate[1], metadata) if precision == "auto" else None
        if unusable:  # the first candidate opened: its files were not checked before
            log.info("%s/%s not considered: %s", *candidate, unusable)
            continue
        runners.append(runner)
    if not runners:
        raise ValueError(
            f"no runtime for runtime={runtime!r}, precision={precision!r}: {model_path} has no passed "
            "accuracy gate for a reduced precision (rafd gate MODEL), and fp32 was excluded"
        )
    selection = _interleaved_medians(runners, timer, rounds) if len(runners) > 1 else {_name(runners[0]): 0.0}
    best = min(runners, key=lambda r: selection[_name(r)])
    selection = {name: round(seconds * 1e3, 3) for name, seconds in selection.items()}
    log.info("runtime %s/%s (median ms per run: %s)", best.runtime, best.precision, selection)
    best.selection = selection
    best.precision_choice = precision_choice(
        model_path, best.metadata, (runtime, precision), (best.runtime, best.precision), selection, supported
    )
    return best
