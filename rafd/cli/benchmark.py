"""rafd-benchmark: the fixed simulated benchmark (data), its Table 1/2-style comparison (run) and a paired
bootstrap between two of its models (compare)."""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Sequence

log = logging.getLogger("rafd.benchmark")

MANIFEST = "benchmark.json"


@dataclass(frozen=True)
class SplitSpec:
    split: str
    sequences: int
    frames: int
    seed: int
    size: int  # simulated scan side in pixels (radar at the centre)


# Fixed benchmark: full RADIATE-sized scans (1152 px) of the street-grid simulator, so a model can be scored on the
# protocol's 256 px centre crop and on whole scans (rafd-eval --full-scan). Held-out test seeds. The training split is
# decoded once into a scan cache (rafd-prepare) under the data root.
BENCHMARK_SPLITS = (
    SplitSpec(split="train", sequences=40, frames=40, seed=1000, size=1152),
    SplitSpec(split="test", sequences=10, frames=30, seed=2000, size=1152),
    # for choosing a model's operating threshold (never the test seeds, never the real sample's labels)
    SplitSpec(split="val", sequences=6, frames=30, seed=3000, size=1152),
)
BENCHMARK_INPUT_SIZE = 256
SCORED_HISTORY = 4  # frames: every variant is scored on the frames the 4-frame model scores
BENCHMARK_RECIPE = "default"
CACHE = "cache"
DETECTIONS = "test_detections.npz"  # each variant's test detections, for rafd-benchmark compare


@dataclass(frozen=True)
class Variant:
    name: str
    description: str
    frames: int = 4
    enhancement: bool = True
    flow_supervision: bool = True
    flow_guidance: bool = True
    # Targets before issue 11: (sin yaw, cos yaw) and sizes as labelled, heatmap radius overlap 0.7 / floor 1.
    legacy_targets: bool = False
    flow_stride: int | None = None  # None: the recipe's (8); 4 = the paper's flow branch
    enhance_window: int | None = None  # None: the recipe's (16); 0 = the paper's Hf/2 windows
    propagation_norm: str | None = None  # None: the recipe's ("pre"); "post" = Deformable DETR's blocks
    # Two-stage training: start from the weights of this variant's model in the same out_dir (rafd-train --init).
    init: str | None = None
    freeze: tuple[str, ...] = ()  # parts that do not train (rafd-train --freeze)

    def train_flags(self) -> list[str]:
        flags = ["--frames", str(self.frames)]
        if self.flow_stride is not None:
            flags += ["--flow-stride", str(self.flow_stride)]
        if self.enhance_window is not None:
            flags += ["--enhance-window", str(self.enhance_window)]
        if self.propagation_norm is not None:
            flags += ["--propagation-norm", self.propagation_norm]
        if self.legacy_targets:
            flags += ["--box-encoding", "as_labelled", "--heatmap-min-overlap", "0.7", "--heatmap-min-radius", "1"]
        if not self.enhancement:
            flags.append("--no-enhancement")
        if not self.flow_supervision:
            flags.append("--no-flow-supervision")
        if not self.flow_guidance:
            flags.append("--no-flow-guidance")
        if self.freeze:
            flags += ["--freeze", *self.freeze]
        return flags


# Only the fresh parts train: the propagation starts as the identity, so the model starts as the single-frame model
# and can only add what its past frames show to the features the single-frame head reads (the shipped recipe).
FRESH_ONLY = Variant("rafd4_from_single_fresh_only", "RaFD, 4 frames, from the single-frame model, only its flow branch "
                     "and propagation trained", init="single", freeze=("encoder", "head"))

# Table 1 (frames) and leave-one-out ablations; "baseline"/"enh_only" + no_guidance + rafd4 give the
# paper's cumulative Table 2 (baseline -> + enhancement -> + flow estimation -> + flow guidance).
VARIANTS = {
    v.name: v
    for v in (
        Variant("rafd4", "RaFD, 4 frames"),
        Variant("rafd4_post_norm", "RaFD, 4 frames, post-norm propagation blocks (Deformable DETR's)",
                propagation_norm="post"),
        # Second stage of a two-stage recipe: run after `single` in the same out_dir; `single_continued` gives the
        # single-frame model the same extra epochs, so the pair compares equal budgets.
        Variant("rafd4_from_single", "RaFD, 4 frames, initialised from the single-frame model", init="single"),
        Variant("rafd4_from_single_frozen", "RaFD, 4 frames, from the single-frame model, its encoder frozen",
                init="single", freeze=("encoder",)),
        FRESH_ONLY,
        # The shipped recipe with the paper's flow branch (stride 4 instead of 8): the accuracy the speed option costs.
        replace(FRESH_ONLY, name="rafd4_from_single_fresh_only_flow4",
                description=FRESH_ONLY.description + ", flow at stride 4 (the paper's)", flow_stride=4),
        Variant("rafd2_from_single", "RaFD, 2 frames, initialised from the single-frame model", frames=2, init="single"),
        Variant("no_guidance_from_single", "4 frames, vanilla deformable attention, initialised from the single-frame "
                "model", flow_guidance=False, init="single"),
        Variant("single_continued", "single frame, continued from the single-frame model", frames=1, init="single"),
        Variant("rafd4_legacy_targets", "RaFD, 4 frames, targets as labelled (sin/cos yaw, radius 0.7 / 1)",
                legacy_targets=True),
        Variant("rafd4_paper_flow", "RaFD, 4 frames, flow branch at stride 4 (the paper's)", flow_stride=4),
        Variant("rafd4_paper_windows", "RaFD, 4 frames, Hf/2 x Wf/2 attention windows (the paper's)", enhance_window=0),
        Variant("rafd2", "RaFD, 2 frames", frames=2),
        Variant("single", "single frame (CenterFormer-style)", frames=1),
        Variant("no_enh", "4 frames, without feature enhancement", enhancement=False),
        Variant("no_flow_sup", "4 frames, flow not supervised (weight 0)", flow_supervision=False),
        Variant("no_guidance", "4 frames, vanilla deformable attention (= + flow estimation)", flow_guidance=False),
        Variant("enh_only", "4 frames, + enhancement only", flow_supervision=False, flow_guidance=False),
        Variant(
            "baseline", "4 frames, vanilla deformable attention, no enhancement, no flow loss",
            enhancement=False, flow_supervision=False, flow_guidance=False,
        ),
    )
}
DEFAULT_VARIANTS = ("rafd4", "rafd2", "single", "no_guidance")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rafd-benchmark", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    data = commands.add_parser("data", help="simulate the fixed benchmark's train and test sequences")
    data.add_argument("out_root", type=Path)
    data.add_argument("--scale", type=float, default=1.0, help="multiply sequence counts (smoke tests: < 1)")
    data.add_argument("--frames", type=int, help="override frames per sequence (smoke tests)")
    run = commands.add_parser("run", help="train every variant with the same budget and seed, evaluate on test")
    run.add_argument("data_root", type=Path)
    run.add_argument("out_dir", type=Path)
    run.add_argument("--variants", default=",".join(DEFAULT_VARIANTS), help=f"comma list of {sorted(VARIANTS)}")
    run.add_argument("--epochs", type=int, help="default: the recipe's")
    run.add_argument("--batch-size", type=int, help="default: the recipe's")
    run.add_argument("--lr", type=float, help="default: the recipe's")
    run.add_argument("--seed", type=int, default=0)
    run.add_argument("--config", default=BENCHMARK_RECIPE, help="training recipe (rafd.train.recipes)")
    run.add_argument("--full-scan", action="store_true", help="also score every variant on whole test scans")
    run.add_argument("--device", default="auto")
    run.add_argument("--precision", choices=("fp32", "bf16", "fp16"), default="fp32", help="training autocast")
    run.add_argument("--max-windows", type=int, help="cap training windows (smoke tests)")
    run.add_argument("--max-steps-per-epoch", type=int, help="cap steps per epoch (smoke tests)")
    run.add_argument("--resume", action="store_true",
                     help="continue each variant already in OUT_DIR from its last finished epoch (rafd-train --resume) "
                          "instead of training it again; a finished variant is only evaluated")
    compare = commands.add_parser(
        "compare", help="paired bootstrap over drives: is CANDIDATE better than BASELINE on the same frames?")
    compare.add_argument("baseline", type=Path, help="detections (.npz from rafd-eval --detections, or a variant's "
                                                     "folder of a run, which holds test_detections.npz)")
    compare.add_argument("candidate", type=Path, help="the same for the other model")
    compare.add_argument("--resamples", type=int, default=2000)
    compare.add_argument("--seed", type=int, default=0)
    compare.add_argument("--json", type=Path, help="write the comparison here")
    return parser


def make_data(out_root: Path, scale: float, frames: int | None) -> Path:
    """Simulate every split of BENCHMARK_SPLITS under out_root and write the manifest."""
    from rafd.sim import simulate_dataset

    out_root.mkdir(parents=True, exist_ok=True)
    specs = [
        SplitSpec(s.split, max(1, round(s.sequences * scale)), frames or s.frames, s.seed, s.size)
        for s in BENCHMARK_SPLITS
    ]
    for spec in specs:
        log.info("simulating %s: %d sequences x %d frames (seed %d, %d px)", spec.split, spec.sequences, spec.frames, spec.seed, spec.size)
        simulate_dataset(out_root, sequences=spec.sequences, frames=spec.frames, seed=spec.seed, split=spec.split, size=spec.size)
    from rafd.cli.prepare import main as prepare_main

    if prepare_main([str(out_root), str(out_root / CACHE), "--crop", str(max(s.size for s in specs))]) != 0:
        raise RuntimeError(f"rafd-prepare failed on {out_root}")
    manifest = {
        "splits": [asdict(s) for s in specs],
        "input_size": BENCHMARK_INPUT_SIZE,
        "cache": CACHE,
        "train_split": "train",
        "test_split": "test",
        "val_split": "val",
    }
    path = out_root / MANIFEST
    path.write_text(json.dumps(manifest, indent=2))
    return path


def read_manifest(data_root: Path) -> dict:
    path = data_root / MANIFEST
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: create the benchmark with `rafd-benchmark data {data_root}`")
    return json.loads(path.read_text())


TABLE_COLUMNS = (("mAP@0.3", 2), ("mAP@0.5", 2), ("mAP@0.7", 2), ("centre_AP", 2), ("recall_at_1fp", 1),
                 ("epe_all", 4), ("epe_foreground", 4), ("full_mAP@0.5", 2), ("full_centre_AP", 2),
                 ("full_recall_at_1fp", 1), ("train_seconds", 0))


def markdown_table(rows: list[dict]) -> str:
    """Rows of {variant, description, metrics...} -> a Markdown table like the paper's (absent columns dropped)."""
    columns = [(name, digits) for name, digits in TABLE_COLUMNS if any(name in row for row in rows)]
    lines = ["| variant | description | " + " | ".join(name for name, _ in columns) + " |",
             "|" + "---|" * (2 + len(columns))]

    def fmt(value: object, digits: int) -> str:
        return f"{value:.{digits}f}" if isinstance(value, float) and value == value else "-"

    for row in rows:
        cells = " | ".join(fmt(row.get(name), digits) for name, digits in columns)
        lines.append(f"| {row['variant']} | {row['description']} | {cells} |")
    return "\n".join(lines)


def run_benchmark(args: argparse.Namespace) -> int:
    from rafd.cli import evaluate as eval_cli
    from rafd.cli import train as train_cli
    from rafd.train.trainer import history_path, optimizer_state_path

    manifest = read_manifest(args.data_root)
    names = [n.strip() for n in args.variants.split(",") if n.strip()]
    unknown = [n for n in names if n not in VARIANTS]
    if unknown or not names:
        raise ValueError(f"unknown variants {unknown}; choose from {sorted(VARIANTS)}")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in names:
        variant = VARIANTS[name]
        ckpt = args.out_dir / name / "model.pt"
        init_flags: list[str] = []
        # --resume: a variant stopped mid-run goes on from its last finished epoch (rafd-train refuses another
        # config or --freeze); one that finished is only evaluated
        resumed = args.resume and ckpt.is_file() and optimizer_state_path(ckpt).is_file()
        if resumed:
            init_flags = ["--resume", str(ckpt)]
            log.info("variant %s: resuming %s", name, ckpt)
        elif variant.init is not None:
            init_ckpt = args.out_dir / variant.init / "model.pt"
            if not init_ckpt.is_file():
                raise FileNotFoundError(f"variant {name} starts from {init_ckpt}: train variant {variant.init} into "
                                        f"{args.out_dir} first")
            init_flags = ["--init", str(init_ckpt)]
        train_argv = [
            "--data", str(args.data_root), "--split", manifest["train_split"], "--config", args.config,
            "--out", str(ckpt), "--seed", str(args.seed), "--device", args.device, "--precision", args.precision,
            *[flag for name, value in (("--epochs", args.epochs), ("--batch-size", args.batch_size), ("--lr", args.lr))
              if value is not None for flag in (name, str(value))],
            "--input-size", str(manifest["input_size"]), "--val-every", "0", "--no-progress",
            *(["--cache", str(args.data_root / manifest["cache"])] if manifest.get("cache") else []),
            *variant.train_flags(), *init_flags,
        ]
        if args.max_windows:
            train_argv += ["--max-windows", str(args.max_windows)]
        if args.max_steps_per_epoch:
            train_argv += ["--max-steps-per-epoch", str(args.max_steps_per_epoch)]
        log.info("variant %s: training", name)
        start = time.perf_counter()
        if train_cli.main(train_argv) != 0:
            raise RuntimeError(f"training variant {name} failed")
        seconds = time.perf_counter() - start
        if resumed:  # the whole run's training time, earlier invocations included
            seconds = sum(epoch["seconds"] for epoch in json.loads(history_path(ckpt).read_text()))
        metrics_path = args.out_dir / name / "test_metrics.json"
        # every variant scores the same frames: those a 4-frame model scores (a drive's first 3 have no window)
        common = [str(ckpt), "--data", str(args.data_root), "--split", manifest["test_split"], "--device", args.device,
                  "--no-progress", "--like-frames", str(SCORED_HISTORY),
                  *(["--cache", str(args.data_root / manifest["cache"])] if manifest.get("cache") else [])]
        detections = ["--detections", str(args.out_dir / name / DETECTIONS)]
        if eval_cli.main(common + ["--json", str(metrics_path), "--examples", "0", *detections]) != 0:
            raise RuntimeError(f"evaluating variant {name} failed")
        overall = json.loads(metrics_path.read_text())["overall"]
        row = {"variant": name, "description": variant.description, "train_seconds": seconds, "epochs": args.epochs,
               "init": variant.init, "resumed": bool(resumed), **overall}
        if args.full_scan:
            full_path = args.out_dir / name / "test_full_scan.json"
            if eval_cli.main(common + ["--full-scan", "--json", str(full_path)]) != 0:
                raise RuntimeError(f"full-scan evaluation of variant {name} failed")
            full = json.loads(full_path.read_text())["overall"]
            row.update({f"full_{k}": v for k, v in full.items()})
        rows.append(row)
    # rows of variants trained by earlier runs into the same out_dir are kept (two-stage recipes run twice)
    results_path = args.out_dir / "results.json"
    earlier = json.loads(results_path.read_text()).get("rows", []) if results_path.is_file() else []
    rows = [row for row in earlier if row.get("variant") not in names] + rows
    results = {"manifest": manifest, "seed": args.seed, "config": args.config, "rows": rows}
    results_path.write_text(json.dumps(results, indent=2, default=lambda v: None))
    table = markdown_table(rows)
    (args.out_dir / "results.md").write_text(table + "\n")
    print(table)
    return 0


def compare_models(args: argparse.Namespace) -> int:
    from rafd.compare import format_comparison, load_detections, paired_bootstrap

    def detections_of(path: Path) -> tuple[str, list]:
        file = path / DETECTIONS if path.is_dir() else path
        if not file.is_file():
            raise FileNotFoundError(f"{file} does not exist (rafd-eval --detections writes it; rafd-benchmark run "
                                    f"writes {DETECTIONS} into each variant's folder)")
        return (path.name if path.is_dir() else path.stem), load_detections(file)

    (name_a, frames_a), (name_b, frames_b) = detections_of(args.baseline), detections_of(args.candidate)
    result = paired_bootstrap(frames_a, frames_b, resamples=args.resamples, seed=args.seed)
    drives = len({f.sequence for f in frames_a})
    print(format_comparison(result, name_a, name_b, drives, args.resamples))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"baseline": str(args.baseline), "candidate": str(args.candidate),
                                         "drives": drives, "frames": len(frames_a), "resamples": args.resamples,
                                         "seed": args.seed, "metrics": result}, indent=2))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        if args.command == "data":
            print(make_data(args.out_root, args.scale, args.frames))
            return 0
        if args.command == "compare":
            return compare_models(args)
        return run_benchmark(args)
    except (FileNotFoundError, ValueError, RuntimeError) as error:
        print(f"rafd-benchmark: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
