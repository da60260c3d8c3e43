"""The synthetic accuracy benchmark (`rafd bench accuracy`): the fixed simulated data (make_data), its Table 1/2-style
comparison of the variants (run_benchmark, bench.variants) and a paired bootstrap between two models
(compare_models)."""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from bench.variants import DEFAULT_VARIANTS, VARIANTS
from rafd.progress import is_quiet, stage

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
DETECTIONS = "test_detections.npz"  # each variant's test detections, for rafd bench accuracy compare


def make_data(out_root: Path, scale: float, frames: int | None) -> Path:
    """Simulate every split of BENCHMARK_SPLITS under out_root and write the manifest."""
    from rafd.sim import simulate_dataset

    out_root.mkdir(parents=True, exist_ok=True)
    specs = [
        SplitSpec(s.split, max(1, round(s.sequences * scale)), frames or s.frames, s.seed, s.size)
        for s in BENCHMARK_SPLITS
    ]
    for spec in specs:
        log.info(
            "simulating %s: %d sequences x %d frames (seed %d, %d px)",
            spec.split,
            spec.sequences,
            spec.frames,
            spec.seed,
            spec.size,
        )
        simulate_dataset(
            out_root, sequences=spec.sequences, frames=spec.frames, seed=spec.seed, split=spec.split, size=spec.size
        )
    from rafd.data.prepare import prepare_root

    prepared = prepare_root(out_root, out_root / CACHE, crop=max(s.size for s in specs))
    if prepared.failures:
        raise RuntimeError(f"preparing the cache of {out_root} failed: {prepared.failures[0]}")
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
        raise FileNotFoundError(f"{path} is missing: create the benchmark with `rafd bench accuracy data {data_root}`")
    return json.loads(path.read_text())


TABLE_COLUMNS = (
    ("mAP@0.3", 2),
    ("mAP@0.5", 2),
    ("mAP@0.7", 2),
    ("centre_AP", 2),
    ("recall_at_1fp", 1),
    ("epe_all", 4),
    ("epe_foreground", 4),
    ("full_mAP@0.5", 2),
    ("full_centre_AP", 2),
    ("full_recall_at_1fp", 1),
    ("train_seconds", 0),
)


def markdown_table(rows: list[dict]) -> str:
    """Rows of {variant, description, metrics...} -> a Markdown table like the paper's (absent columns dropped)."""
    columns = [(name, digits) for name, digits in TABLE_COLUMNS if any(name in row for row in rows)]
    lines = [
        "| variant | description | " + " | ".join(name for name, _ in columns) + " |",
        "|" + "---|" * (2 + len(columns)),
    ]

    def fmt(value: object, digits: int) -> str:
        return f"{value:.{digits}f}" if isinstance(value, float) and value == value else "-"

    for row in rows:
        cells = " | ".join(fmt(row.get(name), digits) for name, digits in columns)
        lines.append(f"| {row['variant']} | {row['description']} | {cells} |")
    return "\n".join(lines)


@dataclass(frozen=True)
class BenchmarkRun:
    """How `run_benchmark` trains every variant: the same recipe, budget and seed for all (None: the recipe's)."""

    data_root: Path
    out_dir: Path
    variants: tuple[str, ...] = DEFAULT_VARIANTS
    epochs: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    seed: int = 0
    config: str = BENCHMARK_RECIPE
    full_scan: bool = False
    device: str = "auto"
    precision: str = "fp32"
    max_windows: int | None = None
    max_steps_per_epoch: int | None = None
    resume: bool = False  # continue each variant already in out_dir from its last finished epoch


def run_benchmark(bench: BenchmarkRun) -> list[dict[str, Any]]:
    """Train every variant with the same budget and seed (rafd.train.run.train), score each on the test split's
    frames that a 4-frame model scores (rafd.eval.run.evaluate) -> the rows; writes results.json / results.md and
    each variant's model, figures and detections under out_dir."""
    from rafd.eval.run import EvalRun, evaluate, jsonable
    from rafd.train.recipes import recipe_config
    from rafd.train.run import DataSource, TrainRun, train
    from rafd.train.trainer import history_path, optimizer_state_path

    manifest = read_manifest(bench.data_root)
    unknown = [n for n in bench.variants if n not in VARIANTS]
    if unknown or not bench.variants:
        raise ValueError(f"unknown variants {unknown}; choose from {sorted(VARIANTS)}")
    bench.out_dir.mkdir(parents=True, exist_ok=True)
    cache = bench.data_root / manifest["cache"] if manifest.get("cache") else None
    budget = {"train.epochs": bench.epochs, "train.batch_size": bench.batch_size, "train.lr": bench.lr}
    config = recipe_config(bench.config).overridden(
        {
            "model.input_size": manifest["input_size"],
            "train.seed": bench.seed,
            "train.device": bench.device,
            "train.precision": bench.precision,
            "train.val_every": 0,
            "train.progress": not is_quiet(),  # one bar per epoch, titled with the epoch
            "train.max_steps_per_epoch": bench.max_steps_per_epoch,
            "data.max_windows": bench.max_windows,
            **{key: value for key, value in budget.items() if value is not None},  # None: the recipe's
        }
    )
    rows = []
    for position, name in enumerate(bench.variants):
        variant = VARIANTS[name]
        ckpt = bench.out_dir / name / "model.pt"
        base = TrainRun(
            config=config,
            data=DataSource(bench.data_root, (manifest["train_split"],), cache),
            out=ckpt,
            recipe=bench.config,
        )
        run = variant.apply(base)
        # resume: a variant stopped mid-run goes on from its last finished epoch (training refuses another config
        # or --freeze); one that finished is only evaluated
        resumed = bench.resume and ckpt.is_file() and optimizer_state_path(ckpt).is_file()
        if resumed:
            run = replace(run, resume=True)
            log.info("variant %s: resuming %s", name, ckpt)
        elif variant.init is not None:
            init_ckpt = bench.out_dir / variant.init / "model.pt"
            if not init_ckpt.is_file():
                raise FileNotFoundError(
                    f"variant {name} starts from {init_ckpt}: train variant {variant.init} into {bench.out_dir} first"
                )
            run = replace(run, init=init_ckpt)
        stage(f"variant {name} ({position + 1} of {len(bench.variants)}): training")
        start = time.perf_counter()
        train(run)
        seconds = time.perf_counter() - start
        if resumed:  # the whole run's training time, earlier invocations included
            seconds = sum(epoch["seconds"] for epoch in json.loads(history_path(ckpt).read_text()))
        # every variant scores the same frames: those a 4-frame model scores (a drive's first 3 have no window)
        scoring = EvalRun(
            checkpoint=ckpt,
            data=bench.data_root,
            split=(manifest["test_split"],),
            cache=cache,
            device=bench.device,
            progress=not is_quiet(),
            like_frames=SCORED_HISTORY,
        )
        report = evaluate(
            replace(
                scoring,
                json=bench.out_dir / name / "test_metrics.json",
                examples=0,
                detections=bench.out_dir / name / DETECTIONS,
            )
        )
        row = {
            "variant": name,
            "description": variant.description,
            "train_seconds": seconds,
            "epochs": bench.epochs,
            "init": variant.init,
            "resumed": bool(resumed),
            **jsonable(report["overall"]),
        }
        if bench.full_scan:
            full = evaluate(replace(scoring, full_scan=True, json=bench.out_dir / name / "test_full_scan.json"))
            row.update({f"full_{k}": v for k, v in jsonable(full["overall"]).items()})
        rows.append(row)
    # rows of variants trained by earlier runs into the same out_dir are kept (two-stage recipes run twice)
    results_path = bench.out_dir / "results.json"
    earlier = json.loads(results_path.read_text()).get("rows", []) if results_path.is_file() else []
    rows = [row for row in earlier if row.get("variant") not in bench.variants] + rows
    results = {"manifest": manifest, "seed": bench.seed, "config": bench.config, "rows": rows}
    results_path.write_text(json.dumps(results, indent=2, default=lambda v: None))
    (bench.out_dir / "results.md").write_text(markdown_table(rows) + "\n")
    return rows


def compare_models(
    baseline: Path, candidate: Path, resamples: int = 2000, seed: int = 0, json_path: Path | None = None
) -> str:
    """Paired bootstrap over drives between two models' detections on the same frames -> the printed comparison
    (and the JSON at json_path). A path is a detections file or a variant's folder of a benchmark run."""
    from rafd.eval.compare import format_comparison, load_detections, paired_bootstrap

    def detections_of(path: Path) -> tuple[str, list[Any]]:
        file = path / DETECTIONS if path.is_dir() else path
        if not file.is_file():
            raise FileNotFoundError(
                f"{file} does not exist (rafd-eval --detections writes it; rafd bench accuracy "
                f"run writes {DETECTIONS} into each variant's folder)"
            )
        return (path.name if path.is_dir() else path.stem), load_detections(file)

    (name_a, frames_a), (name_b, frames_b) = detections_of(baseline), detections_of(candidate)
    result = paired_bootstrap(frames_a, frames_b, resamples=resamples, seed=seed)
    drives = len({f.sequence for f in frames_a})
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(
            json.dumps(
                {
                    "baseline": str(baseline),
                    "candidate": str(candidate),
                    "drives": drives,
                    "frames": len(frames_a),
                    "resamples": resamples,
                    "seed": seed,
                    "metrics": result,
                },
                indent=2,
            )
        )
    return format_comparison(result, name_a, name_b, drives, resamples)
