"""Leave-one-group-out cross-validation of the real fine-tune: a less optimistic real figure than 3 validation scans
scored at a threshold calibrated on themselves (issue 37 item 3).

    python -m tools.real_cv REAL --groups g111,g1213,gmvd --single SIM_SINGLE.pt --multi SIM_MULTI.pt \
        --config cpu --mix-data SIM --mix-cache SIMCACHE --out runs/cv_cpu [--threads 1]

REAL holds the labelled real sequences, each folder's meta.json `set` naming its group. A group is scans that share
vehicles (consecutive scans of one drive): a vehicle seen in training is never scored in the same fold. For every
group G:
1. fine-tune SIM_SINGLE (the simulation-trained single-frame stage) on the other groups exactly as the shipped model
   was (docs/finetuning.md: simulated windows mixed in 1:1, 100 epochs at lr 1e-3, rotations and tile shifts);
2. put it back into SIM_MULTI's flow branch and propagation (tools.assemble_model);
3. choose the operating threshold on the fold's training scans (the lowest score with at most 1 false positive per
   scan: rafd eval --calibrate 1, whole scans, warm-up windows);
4. score G's scans at that threshold (rafd eval --detections).
The held-out scans of all folds are then pooled: recall of the vehicles within 2 m at each fold's threshold, false
positives per scan, and a bootstrap interval over scans. Each step is the documented command line, run as a
subprocess, so the folds are exactly what a user would run.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FINETUNE_SETTINGS = (
    "model.num_frames=1 data.mix_share=0.5 data.augment.max_rotation_deg=180 data.augment.shift_max_m=20 "
    "data.augment.shift_probability=0.5 train.lr=1e-3 train.epochs=100 train.batch_size=4 train.seed=0 "
    "train.num_workers=0 --quiet"
).split()
SCORING_FLAGS = ["--full-scan", "--warm-up-windows", "--quiet"]


@dataclass(frozen=True)
class ScanCounts:
    """One held-out scan at its fold's threshold."""

    fold: str
    sequence: str
    frame: int
    vehicles: int
    found: int
    false_positives: int


def folds(groups: Sequence[str]) -> list[tuple[str, list[str]]]:
    """-> [(held-out group, training groups)], one fold per group."""
    if len(set(groups)) != len(groups) or len(groups) < 2:
        raise ValueError(f"need at least two distinct groups, got {list(groups)}")
    return [(held, [g for g in groups if g != held]) for held in groups]


def scan_counts(fold: str, detections: Path, threshold: float) -> list[ScanCounts]:
    """A fold's held-out detections (rafd eval --detections) -> per-scan vehicles found and false positives at the
    threshold (centre within 2 m, greedy by score within each scan: rafd.eval.metrics.match_centres)."""
    from rafd.eval.compare import load_detections
    from rafd.eval.metrics import match_centres
    from rafd.protocol import CENTRE_DISTANCE_M

    out = []
    for frame in load_detections(detections):
        kept = frame.predictions[frame.predictions[:, 5] >= threshold]
        matches = match_centres([kept], [frame.ground_truth], CENTRE_DISTANCE_M)
        found = int(matches.true_positive.sum())
        out.append(ScanCounts(fold, frame.sequence, frame.frame, len(frame.ground_truth), found, len(kept) - found))
    return out


def pooled(scans: Sequence[ScanCounts], resamples: int = 2000, seed: int = 0) -> dict[str, float]:
    """Pooled recall and false positives per scan, with 95% bootstrap intervals over scans (a scan's vehicles and
    false positives stay together)."""
    vehicles = np.array([s.vehicles for s in scans], np.float64)
    found = np.array([s.found for s in scans], np.float64)
    false = np.array([s.false_positives for s in scans], np.float64)
    if vehicles.sum() == 0:
        raise ValueError("the held-out scans hold no vehicles")
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, len(scans), size=(resamples, len(scans)))
    with np.errstate(invalid="ignore", divide="ignore"):
        recalls = found[draws].sum(1) / vehicles[draws].sum(1)  # a resample without vehicles has none: dropped
    recalls = recalls[np.isfinite(recalls)]
    fps = false[draws].mean(1)
    return {
        "scans": len(scans),
        "vehicles": int(vehicles.sum()),
        "found": int(found.sum()),
        "recall": float(100.0 * found.sum() / vehicles.sum()),
        "recall_low": float(100.0 * np.percentile(recalls, 2.5)),
        "recall_high": float(100.0 * np.percentile(recalls, 97.5)),
        "fp_per_scan": float(false.mean()),
        "fp_per_scan_low": float(np.percentile(fps, 2.5)),
        "fp_per_scan_high": float(np.percentile(fps, 97.5)),
    }


def calibrated_threshold(checkpoint: Path) -> float:
    """The operating threshold rafd eval --calibrate wrote into the checkpoint's meta."""
    from rafd.model.checkpoint import read_checkpoint
    from rafd.protocol import OPERATING_THRESHOLD_KEY

    return float(read_checkpoint(checkpoint)[2][OPERATING_THRESHOLD_KEY])


def _run(command: list[str], log: Path) -> None:
    with open(log, "a") as out:
        out.write("$ " + " ".join(command) + "\n")
        out.flush()
        done = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed with status {done.returncode}: see {log}")


def run_fold(args: argparse.Namespace, held: str, training: list[str]) -> list[ScanCounts]:
    rafd = [sys.executable, "-m", "rafd.cli.main"]
    fold_dir = args.out / held
    fold_dir.mkdir(parents=True, exist_ok=True)
    log = fold_dir / "commands.log"
    single, model = fold_dir / "single.pt", fold_dir / "model.pt"
    threads = ["--threads", str(args.threads)]
    if not single.is_file():
        _run(
            rafd
            + ["train", str(args.real), "--split", ",".join(training), "--config", args.config, "--init"]
            + [str(args.single), "--mix-data", str(args.mix_data), "--mix-split", "train", "--out", str(single)]
            + (["--mix-cache", str(args.mix_cache)] if args.mix_cache else [])
            + FINETUNE_SETTINGS
            + [f"train.threads={args.threads}"],
            log,
        )
    _run([sys.executable, "-m", "tools.assemble_model", str(single), str(args.multi), "--out", str(model)], log)
    _run(
        rafd
        + ["eval", str(model), str(args.real), "--split", ",".join(training), "--calibrate", "1"]
        + ["--json", str(fold_dir / "calibration.json")]
        + SCORING_FLAGS
        + threads,
        log,
    )
    threshold = calibrated_threshold(model)
    detections = fold_dir / "held_out_detections.npz"
    _run(
        rafd
        + ["eval", str(model), str(args.real), "--split", held, "--json", str(fold_dir / "held_out.json")]
        + ["--detections", str(detections)]
        + SCORING_FLAGS
        + threads,
        log,
    )
    return scan_counts(held, detections, threshold)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.real_cv", description=__doc__.splitlines()[0])
    parser.add_argument("real", type=Path, help="data root of the labelled real sequences")
    parser.add_argument("--groups", required=True, help="comma list of meta.json set names, one per group")
    parser.add_argument("--single", type=Path, required=True, help="simulation-trained single-frame checkpoint")
    parser.add_argument("--multi", type=Path, required=True, help="simulation-trained multi-frame checkpoint")
    parser.add_argument("--config", required=True, help="the recipe of both (rafd train --config)")
    parser.add_argument("--mix-data", type=Path, required=True, help="simulated drives replayed in training")
    parser.add_argument("--mix-cache", type=Path, help="their scan cache (rafd prepare)")
    parser.add_argument("--out", type=Path, required=True, help="folder: one sub-folder per fold, cv.json")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    for path in (args.real, args.single, args.multi, args.mix_data):
        if not path.exists():
            parser.error(f"{path} does not exist")
    try:
        plan = folds([g for g in args.groups.split(",") if g])
    except ValueError as error:
        parser.error(str(error))
    args.out.mkdir(parents=True, exist_ok=True)
    scans: list[ScanCounts] = []
    try:
        for held, training in plan:
            scans += run_fold(args, held, training)
    except RuntimeError as error:
        print(f"real_cv: {error}", file=sys.stderr)
        return 1
    result = {
        "single": str(args.single),
        "multi": str(args.multi),
        "config": args.config,
        "folds": [{"held_out": h, "training": t} for h, t in plan],
        "scans": [s.__dict__ for s in scans],
        "pooled": pooled(scans),
    }
    (args.out / "cv.json").write_text(json.dumps(result, indent=2))
    p = result["pooled"]
    print(
        f"{p['scans']} held-out scans, {p['vehicles']} vehicles: recall {p['recall']:.1f}% "
        f"[{p['recall_low']:.1f}, {p['recall_high']:.1f}] ({p['found']} found) at "
        f"{p['fp_per_scan']:.2f} FP per scan [{p['fp_per_scan_low']:.2f}, {p['fp_per_scan_high']:.2f}]"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
