"""The documentation's pictures and plots, made by one command from the project's own commands:

    python -m tools.docs_pictures --out docs/images                   # every picture, on the shipped model
    python -m tools.docs_pictures --out docs/images --model M.onnx    # another model (M.pt beside it for rafd eval)
    python -m tools.docs_pictures --out /tmp/pictures --quick         # tiny settings: checks that the command runs

Regenerate docs/images with it whenever the shipped model changes (the pictures show what the model answers).

- detection_sim.png: `rafd simulate` (held-out test drives), `rafd serve` and `rafd client --out`: the picture a
  user gets of an answer (boxes, ground truth, flow), of the first drive's frame with the most labelled vehicles
  in the covered area (chosen on the labels alone);
- detection_oxford.png: the same on real Oxford Radar RobotCar scans ($RAFD_OXFORD_SAMPLE with the project's labels,
  `rafd label link`; frame 11, the last of its consecutive frames 1-11; CC BY-NC-SA 4.0, the attribution drawn
  into the picture and written into its metadata);
- pr_curve.png: `rafd eval --plots` on the simulated test drives (the protocol's 256 px crop);
- recall_by_range.png: `rafd eval --full-scan --json` on the same drives (`--quick`: the crop's), drawn here;
- capacity_latency.png: `rafd bench capacity --json` on the first simulated drive, drawn here;
- odometry_error.png: the errors `rafd odometry --evaluate --per-pair` prints against the Oxford ground truth
  (`--quick` without the sample: a simulated drive's true poses), drawn here.

Each picture is shrunk to a palette PNG (at most MAX_BYTES); OUT/manifest.json says for each which commands, model
(the first 8 hex digits of its checkpoint's sha256, as the project names models), date and CPU made it. Without
RAFD_OXFORD_SAMPLE the Oxford pictures are skipped, saying so (`--quick` falls back to a simulated drive for the
odometry plot). Never reads the RADIATE test sample. Needs the dev extra (torch for rafd eval, the serve extra,
matplotlib).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rafd.model_files import file_sha256

REPO = Path(__file__).resolve().parents[1]
PICTURES = {
    "detection_sim": "a simulated test drive's scan as `rafd client --out` draws the service's answer",
    "detection_oxford": "a real Oxford Radar RobotCar scan as `rafd client --out` draws the service's answer",
    "pr_curve": "precision-recall curves of `rafd eval --plots` on simulated test drives",
    "recall_by_range": "recall and false positives by range from the radar, `rafd eval --json`",
    "capacity_latency": "p50 / p99 latency against streams, `rafd bench capacity --json`",
    "odometry_error": "radar odometry's error per consecutive pair against the ground truth",
}
MAX_BYTES = 150_000
PALETTE_COLOURS = (128, 64, 32)  # tried in turn until the PNG fits MAX_BYTES
DPI = 90
OXFORD_ENV = "RAFD_OXFORD_SAMPLE"
OXFORD_LABELS = REPO / "labels" / "oxford" / "oxford_radar_sample.json"
OXFORD_FRAMES = (1, 11)  # the consecutive 4 Hz run of the sample; the picture shows its last frame
OXFORD_CREDIT = (
    "Scan: Oxford Radar RobotCar Dataset (Barnes et al., ICRA 2020), CC BY-NC-SA 4.0, non-commercial; "
    "labels: this project's, same licence"
)
OXFORD_LICENCE = (
    'Radar scan from the Oxford Radar RobotCar Dataset (D. Barnes, M. Gadd, P. Murcutt, P. Newman, I. Posner, "The '
    'Oxford Radar RobotCar Dataset: A Radar Extension to the Oxford RobotCar Dataset", ICRA 2020), sequence '
    "2019-01-10-14-36-48-radar-oxford-10k-partial, licensed CC BY-NC-SA 4.0 (non-commercial use); the vehicle labels "
    "are the project's (labels/oxford/), same licence"
)
SIM_SEED = 2000  # the shipped model's held-out simulated check (default_model.json: simulated_check)


class PictureError(RuntimeError):
    """A picture could not be made; the message says which command failed and why."""


@dataclass(frozen=True)
class Sizes:
    """How much each picture's command does: the full pictures, or tiny settings that only check the command."""

    sim_sequences: int
    sim_frames: int
    full_scan_windows: int | None  # recall by range on whole scans, at most this many windows; None: the crop's
    capacity_inputs: str
    capacity_seconds: float
    capacity_max_streams: int


FULL = Sizes(4, 30, 16, "scans,crops", 10.0, 4)
QUICK = Sizes(1, 8, None, "crops", 1.0, 2)


@dataclass(frozen=True)
class Model:
    onnx: Path | None  # what the service serves (None: the detection and capacity pictures are skipped)
    checkpoint: Path | None  # what rafd eval scores (None: the evaluation pictures are skipped)
    checkpoint_sha256: str  # the project's name of a model: its checkpoint's sha256 (first 8 hex digits shown)
    onnx_sha256: str | None

    def describe(self) -> dict[str, Any]:
        return {
            "checkpoint_sha256": self.checkpoint_sha256[:8],
            "checkpoint": None if self.checkpoint is None else _shown_path(self.checkpoint),
            "onnx": None if self.onnx is None else _shown_path(self.onnx),
            "onnx_sha256": None if self.onnx_sha256 is None else self.onnx_sha256[:8],
        }


def _shown_path(path: Path) -> str:
    """A path as the manifest shows it: relative to the repository where it lies inside it."""
    path = Path(path).resolve()
    try:
        return str(path.relative_to(REPO))
    except ValueError:
        return str(path)


def onnx_metadata(path: Path) -> dict[str, str]:
    """The metadata every RaFD export carries (rafd.runtime.contract.METADATA_KEYS)."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return dict(session.get_modelmeta().custom_metadata_map)


def resolve_model(model: Path | None) -> Model:
    """The ONNX model to serve and the checkpoint to evaluate: the shipped pair by default; for MODEL.onnx its
    MODEL.pt beside it (else no evaluation pictures); for MODEL.pt its export MODEL.onnx beside it (same checkpoint
    sha256; `rafd export MODEL.pt` makes it)."""
    from rafd.model_files import file_kind

    checkpoint: Path | None
    if model is None:
        from rafd.assets import default_checkpoint, default_onnx

        onnx, checkpoint = Path(default_onnx()), Path(default_checkpoint())
    elif not model.is_file():
        raise PictureError(f"--model {model} does not exist")
    elif file_kind(model) == "onnx":
        onnx, beside = model, model.with_suffix(".pt")
        checkpoint = beside if beside.is_file() and file_kind(beside) == "checkpoint" else None
        if checkpoint is None:
            print(
                f"no checkpoint {beside} beside the ONNX model: the rafd eval pictures (pr_curve, recall_by_range) "
                "will be skipped (pass --model MODEL.pt to make them)"
            )
    elif file_kind(model) == "checkpoint":
        checkpoint, beside = model, model.with_suffix(".onnx")
        if not (beside.is_file() and onnx_metadata(beside).get("checkpoint_sha256") == file_sha256(model)):
            raise PictureError(f"no export of {model} beside it: run `rafd export {model} --out {beside}` first")
        onnx = beside
    else:
        raise PictureError(f"--model {model} is neither an ONNX model nor a checkpoint")
    onnx_sha = file_sha256(onnx)
    if checkpoint is not None:
        checkpoint_sha = file_sha256(checkpoint)
        exported_from = onnx_metadata(onnx).get("checkpoint_sha256")
        if exported_from and exported_from != checkpoint_sha:
            raise PictureError(
                f"{onnx} was exported from checkpoint {exported_from[:8]}, not from {checkpoint} ({checkpoint_sha[:8]})"
            )
    else:
        checkpoint_sha = onnx_metadata(onnx).get("checkpoint_sha256", "")
        if not checkpoint_sha:
            raise PictureError(f"{onnx} carries no checkpoint_sha256 in its metadata: not a RaFD export")
    return Model(onnx, checkpoint, checkpoint_sha, onnx_sha)


# ---------------------------------------------------------------------------------------------- running commands
def run_command(shown: str, main: Callable[[list[str]], int], argv: list[str], log_dir: Path) -> str:
    """One rafd command in this process (`main(argv)`, what `rafd ...` runs) -> its stdout; PictureError with its
    output's end when it fails."""
    print(f"$ {shown} {' '.join(argv)}", flush=True)
    out, err = io.StringIO(), io.StringIO()
    start = time.perf_counter()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            status = main(argv)
        except SystemExit as exit_:  # argparse refused the arguments
            status = int(exit_.code or 0) if not isinstance(exit_.code, str) else 2
    log_dir.mkdir(parents=True, exist_ok=True)
    name = shown.replace(" ", "_")
    (log_dir / f"{name}.log").write_text(out.getvalue() + err.getvalue())
    if status != 0:
        raise PictureError(
            f"`{shown} {' '.join(argv)}` exited with {status}:\n{(out.getvalue() + err.getvalue())[-3000:]}"
        )
    print(f"  done in {time.perf_counter() - start:.1f} s", flush=True)
    return out.getvalue()


def simulate(work: Path, sizes: Sizes) -> Path:
    """The held-out simulated test drives (the shipped model's simulated check: seed 2000, split test)."""
    from rafd.cli.simulate import main

    root = work / "sim"
    argv = ["--out", str(root), "--sequences", str(sizes.sim_sequences), "--sequence-frames", str(sizes.sim_frames)]
    run_command("rafd simulate", main, [*argv, "--seed", str(SIM_SEED), "--split", "test", "--quiet"], work / "logs")
    return root


def first_drive(root: Path) -> Path:
    return root / f"sim_{SIM_SEED}_0"


@contextlib.contextmanager
def served(onnx: Path):
    """`rafd serve --model ONNX` on loopback (onnxruntime fp32, the reference runtime; the service's own defaults
    otherwise) -> its URL."""
    from bench.server import start_server

    print(f"$ RAFD_RUNTIME=onnxruntime rafd serve --model {onnx}  (loopback, a free port)", flush=True)
    with start_server(onnx, env={"RAFD_RUNTIME": "onnxruntime"}, clean_env=True) as server:
        yield server.url


def client_run(url: str, sequence: Path, frames: int, work: Path, name: str) -> tuple[Path, list[dict[str, Any]]]:
    """`rafd client SEQ --url URL --out DIR --limit FRAMES`: the first FRAMES frames posted to a fresh stream ->
    (DIR, the answers in order)."""
    from rafd.cli.client import main

    out = work / name
    run_command(
        "rafd client",
        main,
        [str(sequence), "--url", url, "--out", str(out), "--limit", str(frames), "--quiet"],
        work / "logs",
    )
    answers = [json.loads(line) for line in (out / "answers.jsonl").read_text().splitlines()]
    if len(answers) != frames:
        raise PictureError(f"rafd client answered {len(answers)} of {frames} frames into {out}")
    return out, answers


def client_picture(out: Path, number: int) -> Path:
    """The picture `rafd client --out OUT` drew of frame `number`."""
    picture = out / "frames" / f"{number:06d}.png"
    if not picture.is_file():
        raise PictureError(f"rafd client drew no picture of frame {number} into {out}")
    return picture


def busiest_frame(sequence: Path, answers: list[dict[str, Any]]) -> tuple[int, int, int]:
    """The frame to show, chosen on the labels alone (never on what the model answered): of the frames answered
    with a full window, the one with the most labelled vehicles whose centre lies in what the answer covered (the
    earliest of equals) -> (its index in the answers, its frame number, those vehicles)."""
    from rafd.cli.client import read_frames
    from rafd.data.labels import IGNORE_CLASS

    read = read_frames(sequence)
    best = (-1, -1, -1)
    for index, (frame, answer) in enumerate(zip(read.frames, answers)):
        if answer["frames_used"] < answer["num_frames"]:
            continue
        half_m = answer["input"]["covered"]["side_px"] * read.resolution / 2  # the covered square, metres
        inside = sum(
            1
            for o in frame.source.objects
            if o.class_name != IGNORE_CLASS and abs(o.box[0]) < half_m and abs(o.box[1]) < half_m
        )
        if inside > best[2]:
            best = (index, frame.number, inside)
    if best[0] < 0:
        raise PictureError(f"no frame of {sequence} was answered with a full window")
    return best


def oxford_sequence(sample: Path, work: Path) -> Path:
    """`rafd label link` of the sample's consecutive frames with the project's labels, without the labelled area's
    outside ignore regions, and without the labels' ignore regions: the picture's ground truth is the labelled
    vehicles only (rafd client draws every labelled object in the ground truth's colour)."""
    from rafd.cli.label import main
    from rafd.data.labels import IGNORE_CLASS

    out = work / "oxford_radar_sample"
    first, last = OXFORD_FRAMES
    argv = [
        "link",
        str(sample),
        str(OXFORD_LABELS),
        str(out),
        "--split",
        "train",
        "--frame-numbers",
        f"{first}-{last}",
        "--labelled-half-m",
        "0",
    ]
    run_command("rafd label", main, argv, work / "logs")
    annotations = out / "annotations" / "annotations.json"
    objects = json.loads(annotations.read_text())
    annotations.write_text(json.dumps([o for o in objects if o.get("class_name") != IGNORE_CLASS]))
    return out


# ------------------------------------------------------------------------------------------------- PNG files
def _palette_png(image: Any, colours: int) -> bytes:
    from PIL import Image

    quantised = image.quantize(colors=colours, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE)
    buffer = io.BytesIO()
    quantised.save(buffer, "PNG", optimize=True, pnginfo=_png_info(image.info.get("_text", {})))
    return buffer.getvalue()


def _png_info(text: dict[str, str]) -> Any:
    from PIL.PngImagePlugin import PngInfo

    info = PngInfo()
    for key, value in text.items():
        info.add_itxt(key, value)
    return info


def write_small_png(source: Path | np.ndarray, target: Path, text: dict[str, str] | None = None) -> int:
    """A picture (a PNG file, or a BGR / grey uint8 array) -> `target` as a palette PNG of at most MAX_BYTES (the
    first of PALETTE_COLOURS that fits), with `text` as its iTXt chunks -> its size in bytes."""
    import cv2
    from PIL import Image

    if isinstance(source, np.ndarray):
        array = source if source.ndim == 2 else cv2.cvtColor(source, cv2.COLOR_BGR2RGB)
        image = Image.fromarray(array).convert("RGB")
    else:
        image = Image.open(source).convert("RGB")
    image.info["_text"] = {"Software": "python -m tools.docs_pictures", **(text or {})}
    data = b""
    for colours in PALETTE_COLOURS:
        data = _palette_png(image, colours)
        if len(data) <= MAX_BYTES:
            break
    else:
        raise PictureError(f"{target.name}: {len(data)} bytes even at {PALETTE_COLOURS[-1]} colours (> {MAX_BYTES})")
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.with_suffix(".png.partial")
    partial.write_bytes(data)
    partial.replace(target)
    return len(data)


def with_credit_strip(picture: Path, credit: str) -> np.ndarray:
    """The picture with a strip below it carrying `credit` (the data's attribution and licence), so that it stays
    with the picture wherever the picture goes."""
    import cv2

    from rafd.viz.drawing import FONT, PANEL_COLOUR, TEXT_COLOUR

    image = cv2.imread(str(picture), cv2.IMREAD_COLOR)
    if image is None:
        raise PictureError(f"cannot read {picture}")
    scale = 0.42
    words, lines, line = credit.split(), [], ""
    for word in words:
        candidate = f"{line} {word}".strip()
        if cv2.getTextSize(candidate, FONT, scale, 1)[0][0] > image.shape[1] - 16 and line:
            lines.append(line)
            line = word
        else:
            line = candidate
    lines.append(line)
    step = 18
    strip = np.full((step * len(lines) + 8, image.shape[1], 3), PANEL_COLOUR, np.uint8)
    for k, text in enumerate(lines):
        cv2.putText(strip, text, (8, step * (k + 1)), FONT, scale, TEXT_COLOUR, 1, cv2.LINE_AA)
    return np.concatenate([image, strip], axis=0)


def _figure(width: float = 6.4, height: float = 4.0) -> Any:
    """A matplotlib figure on the Agg canvas (no pyplot state), as rafd.viz.plots draws."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width, height), dpi=DPI)
    FigureCanvasAgg(figure)
    return figure


def _figure_array(figure: Any) -> np.ndarray:
    """The drawn figure as an RGB uint8 array."""
    figure.tight_layout()
    figure.canvas.draw()
    rgba = np.asarray(figure.canvas.buffer_rgba())
    return np.ascontiguousarray(rgba[..., 2::-1])  # -> BGR, as write_small_png takes arrays


# ---------------------------------------------------------------------------------------------- the plots
def plot_recall_by_range(overall: dict[str, Any], where: str, model_name: str) -> np.ndarray:
    """rafd eval's overall["by_range_at_threshold"] -> bars of recall per range band (vehicles in each written
    on it) beside the false positives per frame in the band."""
    bands = [b for b in overall["by_range_at_threshold"] if b["vehicles"] or b["fp_per_frame"]]
    bands = bands or overall["by_range_at_threshold"][:-1]  # nothing anywhere: every band up to 100 m, empty
    names = [
        f"{b['from_m']:.0f}-{b['to_m']:.0f} m" if b["to_m"] is not None else f">{b['from_m']:.0f} m" for b in bands
    ]
    recall = [b["recall"] if b["recall"] is not None else 0.0 for b in bands]
    figure = _figure(6.4, 3.6)
    left, right = figure.add_subplot(1, 2, 1), figure.add_subplot(1, 2, 2)
    x = np.arange(len(bands))
    left.bar(x, recall, color="#2a7fba")
    for k, band in enumerate(bands):
        left.text(k, recall[k] + 1.5, f"{band['vehicles']} vehicles", ha="center", fontsize=7)
    left.set_xticks(x, names, fontsize=8)
    left.set_ylim(0, 105)
    left.set_ylabel("recall (%)")
    left.set_title("vehicles found", fontsize=10)
    false_positives = [b["fp_per_frame"] for b in bands]
    right.bar(x, false_positives, color="#d1495b")
    right.set_ylim(0, max(0.1, 1.15 * max(false_positives)))
    right.set_xticks(x, names, fontsize=8)
    right.set_ylabel("false positives per frame")
    right.set_title("false positives", fontsize=10)
    for axes in (left, right):
        axes.grid(True, axis="y", alpha=0.3)
        axes.set_xlabel("range from the radar")
    threshold, far = overall.get("score_threshold"), overall.get("far_score_threshold")
    beyond = f" ({far['threshold']:.3f} from {far['from_m']:g} m)" if far else ""
    figure.suptitle(
        f"model {model_name}, {where}, {overall['frames']} frames, threshold {threshold:.3f}{beyond}", fontsize=9
    )
    return _figure_array(figure)


CAPACITY_BUDGET_MS = 250.0  # rafd bench capacity's default p99 budget: the one the plot draws and counts at
CAPACITY_RUN_BUDGET_MS = 5000.0  # the budget the bench runs with here: it climbs past 250 ms, so the curve goes on


def held_within(levels: list[dict[str, Any]], budget_ms: float) -> int:
    """The most streams of a rising run of levels (sorted by streams) that held `budget_ms` at p99 with only 200
    answers, every smaller level holding too (bench.capacity's rule); 0: not even one."""
    held = 0
    for level in levels:
        if {str(status) for status in level["statuses"]} != {"200"} or level["p99_ms"] > budget_ms:
            break
        held = level["streams"]
    return held


def plot_capacity(report: dict[str, Any], budget_ms: float, model_name: str) -> np.ndarray:
    """rafd bench capacity's --json -> p50 (dashed) and p99 (solid) latency against the number of streams, one
    colour per input form, with the p99 budget and the streams held within it."""
    figure = _figure(6.4, 4.4)
    axes = figure.add_subplot(1, 1, 1)
    colours = ("#2a7fba", "#d1495b", "#3b9b5b", "#8e6bb8")
    highest = 1
    for colour, (label, entry) in zip(colours, report["levels"].items()):
        levels = sorted(entry["levels"], key=lambda level: level["streams"])
        if not levels:
            continue
        streams = [level["streams"] for level in levels]
        highest = max(highest, *streams)
        short = label.removeprefix("default, ")
        count = held_within(levels, budget_ms)
        held = f"{count} stream{'s' if count != 1 else ''} held"
        axes.plot(streams, [lv["p99_ms"] for lv in levels], "-s", color=colour, label=f"{short}: p99 ({held})")
        axes.plot(streams, [lv["p50_ms"] for lv in levels], "--o", color=colour, label=f"{short}: p50")
        for level in levels:  # latencies are of the answered frames: say where frames were refused
            refused = sum(n for status, n in level["statuses"].items() if str(status) != "200")
            if refused:
                share = 100 * refused / max(1, sum(level["statuses"].values()))
                axes.annotate(
                    f"{share:.0f}% refused",
                    (level["streams"], level["p99_ms"]),
                    textcoords="offset points",
                    xytext=(-8, 6),
                    ha="right",
                    fontsize=7,
                    color=colour,
                )
    axes.axhline(budget_ms, color="grey", linestyle=":", label=f"p99 budget {budget_ms:g} ms")
    axes.set_xlabel("streams posting at 4 Hz")
    axes.set_ylabel("latency per frame (ms)")
    axes.set_xticks(range(1, highest + 1))
    axes.set_yscale("log")  # a held level's tens of ms and an overloaded one's seconds on one axis
    low, high = axes.get_ylim()
    axes.set_ylim(low, high * 1.5)  # room for the refusals' notes above the highest point
    axes.set_yticks([t for t in (20, 50, 100, 250, 500, 1000, 2500, 5000, 10000, 25000) if low <= t <= high])
    axes.set_yticklabels([f"{t:g}" for t in axes.get_yticks()])
    axes.minorticks_off()
    axes.grid(True, alpha=0.3)
    axes.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2, frameon=False)
    machine = str(report["machine"]).removesuffix(", 0 threads")  # 0: the service's default, its CPUs
    axes.set_title(f"model {model_name}, rafd serve on {machine}", fontsize=8)
    return _figure_array(figure)


@dataclass(frozen=True)
class OdometryErrors:
    pairs: list[str]  # "1-2", ... (frame numbers; only pairs one scan period apart)
    translation_m: np.ndarray  # [P] |estimated - true| of the relative translation
    yaw_deg: np.ndarray  # [P] estimated - true relative yaw
    ms_per_pair: float


def odometry_errors(sequence: Path) -> OdometryErrors:
    """What `rafd odometry SEQ --evaluate --per-pair` prints, as arrays: the same functions (rafd.data.ego_motion)."""
    from rafd.data.ego_motion import consecutive_pairs, estimate, signed_errors

    print(f"$ rafd odometry {sequence} --evaluate --per-pair  (its functions: rafd.data.ego_motion)", flush=True)
    numbers, stamps, _, relatives, seconds = estimate(sequence)
    error = signed_errors(sequence, numbers, relatives)
    keep = consecutive_pairs(stamps)
    pairs = [f"{numbers[k]}-{numbers[k + 1]}" for k in range(len(numbers) - 1) if keep[k]]
    return OdometryErrors(
        pairs,
        np.hypot(error[keep, 0], error[keep, 1]),
        np.rad2deg(error[keep, 2]),
        1e3 * float(np.mean(np.asarray(seconds)[keep])) if keep.any() else float("nan"),
    )


def plot_odometry(errors: OdometryErrors, where: str) -> np.ndarray:
    figure = _figure(6.4, 3.8)
    top, bottom = figure.add_subplot(2, 1, 1), figure.add_subplot(2, 1, 2, sharex=None)
    x = np.arange(len(errors.pairs))
    top.bar(x, 100 * errors.translation_m, color="#2a7fba")
    top.set_ylabel("translation\nerror (cm)", fontsize=8)
    top.set_title(
        f"{where}: mean {100 * errors.translation_m.mean():.1f} cm, {np.abs(errors.yaw_deg).mean():.2f} deg per pair "
        f"({errors.ms_per_pair:.0f} ms per pair)",
        fontsize=8,
    )
    bottom.bar(x, errors.yaw_deg, color="#d1495b")
    bottom.axhline(0, color="black", linewidth=0.6)
    bottom.set_ylabel("yaw error\n(deg, signed)", fontsize=8)
    bottom.set_xlabel("pair of consecutive scans (frame numbers)", fontsize=8)
    for axes in (top, bottom):
        axes.set_xticks(x, errors.pairs, fontsize=7)
        axes.grid(True, axis="y", alpha=0.3)
    return _figure_array(figure)


# ------------------------------------------------------------------------------------------------- the run
@dataclass
class Run:
    out: Path
    work: Path
    sizes: Sizes
    model: Model
    quick: bool
    command: str
    oxford: Path | None
    entries: dict[str, dict[str, Any]]
    skipped: dict[str, str]

    @property
    def model_name(self) -> str:
        return self.model.checkpoint_sha256[:8]

    def save(self, name: str, picture: Path | np.ndarray, commands: list[str], data: str, **extra: Any) -> None:
        target = self.out / f"{name}.png"
        text = {"Description": PICTURES[name], "Model": self.model_name}
        if "licence" in extra:
            text["Copyright"] = extra["licence"]
        size = write_small_png(picture, target, text)
        from PIL import Image

        with Image.open(target) as image:
            width, height = image.size
        self.entries[f"{name}.png"] = {
            "what": PICTURES[name],
            "commands": commands,
            "data": data,
            "model": self.model.describe(),
            "quick": self.quick,
            "bytes": size,
            "pixels": [width, height],
            **extra,
        }
        print(f"wrote {target} ({size / 1e3:.0f} kB, {width} x {height})", flush=True)

    def skip(self, name: str, why: str) -> None:
        self.skipped[f"{name}.png"] = why
        print(f"skipped {name}.png: {why}", flush=True)


def make_detections(run: Run, wanted: set[str], sim_root: Path | None) -> None:
    if not wanted & {"detection_sim", "detection_oxford"}:
        return
    if run.model.onnx is None:
        for name in wanted & {"detection_sim", "detection_oxford"}:
            run.skip(name, "no ONNX model to serve")
        return
    if "detection_oxford" in wanted and run.oxford is None:
        run.skip("detection_oxford", f"{OXFORD_ENV} is not set (the Oxford Radar RobotCar sample's folder)")
        if "detection_sim" not in wanted:
            return
    with served(run.model.onnx) as url:
        if "detection_sim" in wanted and sim_root is not None:
            posted = run.sizes.sim_frames
            out, answers = client_run(url, first_drive(sim_root), posted, run.work, "client_sim")
            index, frame, vehicles = busiest_frame(first_drive(sim_root), answers)
            run.save(
                "detection_sim",
                client_picture(out, frame),
                [
                    f"rafd simulate --out SIM --sequences {run.sizes.sim_sequences} --sequence-frames "
                    f"{run.sizes.sim_frames} --seed {SIM_SEED} --split test",
                    "RAFD_RUNTIME=onnxruntime rafd serve --model MODEL.onnx",
                    f"rafd client SIM/sim_{SIM_SEED}_0 --url URL --out OUT --limit {posted}",
                ],
                f"simulated test drive sim_{SIM_SEED}_0, frame {frame} of {posted}: of the frames answered with a full "
                f"window, the one with the most labelled vehicles in the covered area ({vehicles})",
                frame=frame,
                answer=_answer_summary(answers[index]),
            )
        if "detection_oxford" in wanted and run.oxford is not None:
            sequence = oxford_sequence(run.oxford, run.work)
            first, last = OXFORD_FRAMES
            out, answers = client_run(url, sequence, last - first + 1, run.work, "client_oxford")
            run.save(
                "detection_oxford",
                with_credit_strip(client_picture(out, last - first + 1), OXFORD_CREDIT),
                [
                    f"rafd label link $RAFD_OXFORD_SAMPLE labels/oxford/oxford_radar_sample.json OXF --split train "
                    f"--frame-numbers {first}-{last} --labelled-half-m 0  (then the labels' ignore regions removed)",
                    "RAFD_RUNTIME=onnxruntime rafd serve --model MODEL.onnx",
                    f"rafd client OXF --url URL --out OUT --limit {last - first + 1}",
                ],
                f"Oxford Radar RobotCar sample, frame {last} of its consecutive frames {first}-{last} (the shipped "
                "model's fine-tuning scans are frames 1-11)",
                licence=OXFORD_LICENCE,
                frame=last,
                answer=_answer_summary(answers[-1]),
            )


def _answer_summary(answer: dict[str, Any]) -> dict[str, Any]:
    return {
        "frames_used": answer["frames_used"],
        "boxes": len(answer["boxes"]),
        "scores": [round(float(b["score"]), 3) for b in answer["boxes"]],
        "runtime": f"{answer['model']['runtime']} {answer['model']['precision']}",
    }


def make_evaluation(run: Run, wanted: set[str], sim_root: Path | None) -> None:
    names = wanted & {"pr_curve", "recall_by_range"}
    if not names or sim_root is None:
        return
    if run.model.checkpoint is None:
        for name in sorted(names):
            run.skip(name, "rafd eval scores a checkpoint: none beside the ONNX model (pass --model MODEL.pt)")
        return
    from rafd.cli.evaluate import main

    checkpoint = str(run.model.checkpoint)
    plots, metrics = run.work / "eval_plots", run.work / "eval_crop.json"
    argv = [checkpoint, str(sim_root), "--split", "test", "--device", "cpu", "--quiet"]
    crop_argv = [*argv, "--plots", str(plots), "--examples", "0", "--json", str(metrics)]
    run_command("rafd eval", main, crop_argv, run.work / "logs")
    data = f"{run.sizes.sim_sequences} simulated test drives x {run.sizes.sim_frames} frames (seed {SIM_SEED})"
    sim = (
        f"rafd simulate --out SIM --sequences {run.sizes.sim_sequences} --sequence-frames {run.sizes.sim_frames} "
        f"--seed {SIM_SEED} --split test"
    )
    crop = json.loads(metrics.read_text())["overall"]
    if "pr_curve" in names:
        run.save(
            "pr_curve",
            plots / "precision_recall.png",
            [sim, "rafd eval MODEL.pt SIM --split test --plots PLOTS --examples 0  (PLOTS/precision_recall.png)"],
            f"{data}, the protocol's 256 px centre crop",
            figures={k: round(crop[k], 2) for k in ("mAP@0.3", "mAP@0.5", "mAP@0.7", "centre_AP") if k in crop},
        )
    if "recall_by_range" not in names:
        return
    if run.sizes.full_scan_windows is None:
        overall, where, how = crop, "256 px crop", "rafd eval MODEL.pt SIM --split test --json METRICS"
    else:
        full = run.work / "eval_full_scan.json"
        windows = str(run.sizes.full_scan_windows)
        run_command(
            "rafd eval", main, [*argv, "--full-scan", "--max-windows", windows, "--json", str(full)], run.work / "logs"
        )
        overall, where = json.loads(full.read_text())["overall"], "whole scans"
        how = f"rafd eval MODEL.pt SIM --split test --full-scan --max-windows {windows} --json METRICS"
    run.save(
        "recall_by_range",
        plot_recall_by_range(overall, f"simulated test drives, {where}", run.model_name),
        [sim, how],
        f"{data}, {where}",
        by_range=overall["by_range_at_threshold"],
    )


def make_capacity(run: Run, wanted: set[str], sim_root: Path | None) -> None:
    if "capacity_latency" not in wanted or sim_root is None:
        return
    if run.model.onnx is None:
        run.skip("capacity_latency", "no ONNX model to serve")
        return
    from bench.capacity_cli import main

    report_path = run.work / "capacity.json"
    sizes = run.sizes
    options = [
        "--configs",
        "default",
        "--inputs",
        sizes.capacity_inputs,
        "--seconds",
        f"{sizes.capacity_seconds:g}",
        "--max-streams",
        str(sizes.capacity_max_streams),
        "--budget-ms",
        f"{CAPACITY_RUN_BUDGET_MS:g}",
    ]
    argv = [str(first_drive(sim_root)), "--model", str(run.model.onnx), *options, "--json", str(report_path), "--quiet"]
    run_command("rafd bench capacity", main, argv, run.work / "logs")
    report = json.loads(report_path.read_text())
    run.save(
        "capacity_latency",
        plot_capacity(report, CAPACITY_BUDGET_MS, run.model_name),
        [f"rafd bench capacity SIM/sim_{SIM_SEED}_0 --model MODEL.onnx {' '.join(options)} --json REPORT"],
        f"simulated drive sim_{SIM_SEED}_0's 1152 px scans, looped",
        levels={label: entry["levels"] for label, entry in report["levels"].items()},
        held_at_250_ms={
            label: held_within(sorted(entry["levels"], key=lambda lv: lv["streams"]), CAPACITY_BUDGET_MS)
            for label, entry in report["levels"].items()
        },
    )


def make_odometry(run: Run, wanted: set[str], sim_root: Path | None) -> None:
    if "odometry_error" not in wanted:
        return
    if run.oxford is not None:
        sequence, where, licence = run.oxford, "Oxford Radar RobotCar sample", OXFORD_LICENCE
    elif run.quick and sim_root is not None:
        print(f"{OXFORD_ENV} is not set: --quick draws the odometry plot on a simulated drive instead", flush=True)
        sequence, where, licence = first_drive(sim_root), f"simulated drive sim_{SIM_SEED}_0", None
    else:
        run.skip("odometry_error", f"{OXFORD_ENV} is not set (the Oxford Radar RobotCar sample's folder)")
        return
    errors = odometry_errors(sequence)
    extra: dict[str, Any] = {"licence": licence} if licence else {}
    run.save(
        "odometry_error",
        plot_odometry(errors, where),
        [f"rafd odometry {'$RAFD_OXFORD_SAMPLE' if run.oxford else f'SIM/sim_{SIM_SEED}_0'} --evaluate --per-pair"],
        f"{where}: {len(errors.pairs)} pairs one scan apart, against "
        + ("the dataset's ground-truth radar odometry (gt/radar_odometry.csv)" if run.oxford else "the true poses"),
        translation_m=[round(float(v), 4) for v in errors.translation_m],
        yaw_deg=[round(float(v), 4) for v in errors.yaw_deg],
        **extra,
    )


def write_manifest(run: Run, load_average: float) -> Path:
    """OUT/manifest.json: per picture what made it; pictures not made this time keep their entry while their file
    is there."""
    from bench.machine import machine_description
    from rafd.cpu import usable_cpus

    path = run.out / "manifest.json"
    previous: dict[str, Any] = {}
    if path.is_file():
        with contextlib.suppress(ValueError):
            previous = json.loads(path.read_text()).get("pictures", {})
    common = {
        "command": run.command,
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"),
        "cpu": machine_description(usable_cpus()),
        "load_average_at_start": round(load_average, 2),  # other work on the CPU bends the timings
        "commit": _commit(),
    }
    pictures = {name: entry for name, entry in previous.items() if (run.out / name).is_file()}
    for name, entry in run.entries.items():
        pictures[name] = {**entry, **common}
    manifest = {
        "about": "Pictures of the documentation, made by `python -m tools.docs_pictures --out docs/images` "
        "(regenerate them when the shipped model changes). model.checkpoint_sha256: the first 8 hex digits of the "
        "checkpoint's sha256, the project's name of a model.",
        "pictures": dict(sorted(pictures.items())),
    }
    path.write_text(json.dumps(manifest, indent=2) + "\n")
    return path


def _commit() -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    except OSError:
        return None
    return done.stdout.strip() or None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m tools.docs_pictures",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--out", type=Path, required=True, help="folder receiving the pictures (docs/images)")
    parser.add_argument(
        "--model",
        type=Path,
        default=None,
        metavar="MODEL.onnx|.pt",
        help="the model to picture (default: the shipped one): an ONNX model (its checkpoint MODEL.pt beside it for "
        "the rafd eval plots) or a checkpoint (its export MODEL.onnx beside it)",
    )
    parser.add_argument("--quick", action="store_true", help="tiny settings: checks that every step runs (CI)")
    parser.add_argument(
        "--only", default=None, metavar="NAMES", help=f"comma list of pictures to make: {', '.join(PICTURES)}"
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    wanted = set(PICTURES) if not args.only else {n.strip().removesuffix(".png") for n in args.only.split(",")}
    unknown = sorted(wanted - set(PICTURES))
    if unknown:
        print(f"docs_pictures: unknown pictures {unknown}; known: {', '.join(PICTURES)}", file=sys.stderr)
        return 2
    start, load = time.perf_counter(), os.getloadavg()[0]
    sample = os.environ.get(OXFORD_ENV)
    oxford = Path(sample) if sample else None
    if oxford is not None and not oxford.is_dir():
        print(f"docs_pictures: {OXFORD_ENV}={sample} is not a folder", file=sys.stderr)
        return 2
    shown_argv = " ".join(["python -m tools.docs_pictures", *(argv if argv is not None else sys.argv[1:])])
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="rafd-docs-pictures-") as tmp:
        work = Path(tmp)
        try:
            model = resolve_model(args.model)
        except (PictureError, OSError, ValueError, RuntimeError) as error:
            print(f"docs_pictures: error: {error}", file=sys.stderr)
            return 1
        run = Run(args.out, work, QUICK if args.quick else FULL, model, args.quick, shown_argv, oxford, {}, {})
        try:
            print(
                f"model {run.model_name} ({_shown_path(model.onnx) if model.onnx else 'no ONNX'}); "
                f"{'quick' if args.quick else 'full'} settings; pictures into {args.out}",
                flush=True,
            )
            needs_sim = wanted & {"detection_sim", "pr_curve", "recall_by_range", "capacity_latency"} or (
                "odometry_error" in wanted and oxford is None and args.quick
            )
            sim_root = simulate(work, run.sizes) if needs_sim else None
            make_detections(run, wanted, sim_root)
            make_evaluation(run, wanted, sim_root)
            make_capacity(run, wanted, sim_root)
            make_odometry(run, wanted, sim_root)
        except (PictureError, OSError, ValueError, RuntimeError) as error:
            print(f"docs_pictures: error: {error}", file=sys.stderr)
            return 1
        finally:
            manifest = write_manifest(run, load)  # the pictures written before a failure keep their record
    seconds = time.perf_counter() - start
    print(f"{len(run.entries)} pictures written, {len(run.skipped)} skipped, manifest {manifest}; {seconds:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
