"""The accuracy gates of `rafd export --gate` and `rafd gate`: every reduced precision this machine runs gated (with
its float32-islands search where the plain precision fails, export.islands_gate), and the verdicts recorded in the
model's metadata, where the runtime's precision choice reads them (rafd.runtime.runners.GATE_KEY).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from export.gate_options import GateOptions
from export.gate_report import GateReport
from export.gate_run import gate_model
from export.islands import replace_dir
from export.islands_gate import search_islands
from rafd.model_files import int8_model_path, islands_dir


def run_export_gates(
    onnx_path: str | Path, options: GateOptions, log: Callable[[str], None] = print
) -> dict[str, GateReport]:
    """The gate of every reduced precision this machine runs (OpenVINO bf16 where the CPU has it); the real
    sample's frames join when RAFD_RADIATE_SAMPLE names a RADIATE sequence."""
    from rafd.runtime import supported_choices

    reduced = [(runtime, precision) for runtime, precision in supported_choices() if precision != "fp32"]
    if not reduced:
        log(
            "accuracy gate: this CPU runs no reduced precision (bf16 needs openvino and avx512_bf16 or AMX, int8 "
            "VNNI or AMX); nothing to gate"
        )
        return {}
    sample = os.environ.get("RAFD_RADIATE_SAMPLE")
    radiate = sample if sample and Path(sample, "Navtech_Cartesian").is_dir() else None
    return {candidate[1]: _gate_precision(onnx_path, candidate, options, radiate, log) for candidate in reduced}


def _gate_precision(
    onnx_path: str | Path,
    candidate: tuple[str, str],
    options: GateOptions,
    radiate: str | None,
    log: Callable[[str], None],
) -> GateReport:
    """One reduced precision's gate, with its islands search where the plain precision fails on enough evidence."""
    calibration = None  # int8's: made once, for the plain model and every islands set
    if candidate[1] == "int8":  # its own model: quantized (again) here, every matrix operation, then judged
        from export.quantize import calibrate, quantize_model

        calibration = calibrate(onnx_path, options.calibration_sequences, options.calibration_frames, log=log)
        quantized = quantize_model(onnx_path, calibration=calibration)
        log(f"int8: wrote {quantized}")
    report = gate_model(
        onnx_path,
        candidate,
        options.sequences,
        options.frames,
        options.seed,
        radiate,
        options.threads,
        options.thresholds,
        log,
    )
    if candidate[1] == "int8":
        from rafd.model_files import file_sha256

        report.judged_sha256 = file_sha256(quantized)
    for line in report.lines():
        log(line)
    if not report.ok and report.too_little() is None and options.islands:
        report = search_islands(
            onnx_path, report, options, radiate, log, precision=candidate[1], calibration=calibration
        )
    return report


def gate_metadata(reports: dict[str, GateReport]) -> dict[str, str]:
    """ONNX metadata entries for the gate verdicts (rafd.runtime.runners.GATE_KEY). The figures also say on which
    CPU and when the gate ran: a verdict on another CPU's bf16 kernels is evidence, not proof, for this one's."""
    import datetime

    from rafd import __version__
    from rafd.cpu import cpu_model_and_flags

    cpu, cpu_flags = cpu_model_and_flags()
    units = [f for f in ("avx512_bf16", "amx_bf16", "amx_int8", "avx512_vnni") if f in cpu_flags]
    made = {
        "cpu": f"{cpu} ({', '.join(units) or 'no bf16 or int8 units'})",
        "date": datetime.date.today().isoformat(),
        "rafd_version": __version__,
    }
    out = {}
    for precision, report in reports.items():
        out[f"gate_{precision}"] = "pass" if report.ok else "fail"
        judged: dict[str, Any] = {"int8_sha256": report.judged_sha256} if report.judged_sha256 else {}
        if report.islands:
            judged["islands"] = list(report.islands)
        if report.islands_sha256:
            judged["islands_sha256"] = report.islands_sha256
        if report.search:
            judged["islands_search"] = report.search
        out[f"gate_{precision}_figures"] = json.dumps(
            {
                "candidate": report.candidate,
                "reference": report.reference,
                "figures": report.figures(),
                **made,
                **judged,
            },
            sort_keys=True,
        )
    return out


def record_gates(onnx_path: str | Path, reports: dict[str, GateReport]) -> dict[str, str]:
    """Write the gate verdicts into an existing ONNX model's metadata, in place, without re-exporting: the graph and
    every other metadata entry are kept; a precision's earlier record is replaced, other precisions' records are kept.
    Atomic (a temporary file beside the model, then a rename). Returns the entries written."""
    import onnx

    path = Path(onnx_path)
    entries = gate_metadata(reports)
    proto = onnx.load(str(path))
    kept = [(p.key, p.value) for p in proto.metadata_props if p.key not in entries]
    del proto.metadata_props[:]
    for key, value in [*kept, *entries.items()]:
        proto.metadata_props.add(key=key, value=value)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        onnx.save(proto, str(tmp))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return entries


def put_in_place(model: Path, target: Path) -> None:
    """Move `model` and the judged files beside it (MODEL.int8.onnx, MODEL.bf16-islands/) to `target`'s names (one
    file system): the files first, the model, whose records name them, last."""
    if int8_model_path(model).is_file():
        os.replace(int8_model_path(model), int8_model_path(target))
    if islands_dir(model).is_dir():
        replace_dir(islands_dir(model), islands_dir(target))
    os.replace(model, target)


def gate_and_record(
    onnx_path: str | Path, options: GateOptions, out: str | Path | None = None, log: Callable[[str], None] = print
) -> dict[str, GateReport]:
    """`rafd gate`: run the gates of an existing model and record them, in place or to `out`. Everything runs on a
    copy in a folder beside the target, the model's judged files with it (MODEL.int8.onnx, MODEL.bf16-islands/,
    which a gate quantizes or writes anew): only once every gate has finished do they and the recorded model take
    their places, so an interrupted gate leaves what was stored as it was, and with `out` the input and its files
    are never written."""
    source = Path(onnx_path)
    target = Path(out) if out is not None else source
    work = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}.gate-"))
    try:
        model = work / target.name
        shutil.copyfile(source, model)
        # the files of the records a gate here does not replace (a precision this CPU lacks) go with them
        if int8_model_path(source).is_file():
            shutil.copyfile(int8_model_path(source), int8_model_path(model))
        if islands_dir(source).is_dir():
            shutil.copytree(islands_dir(source), islands_dir(model))
        reports = run_export_gates(model, options, log)
        if reports:
            record_gates(model, reports)
            put_in_place(model, target)
        return reports
    finally:
        shutil.rmtree(work, ignore_errors=True)
