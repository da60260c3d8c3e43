"""What tracking and velocity cost per scan: rafd.tracking.step on a synthetic stream of 32 vehicles, per velocity
candidate, with the flow of one 256 px crop (the service's answer today: 64 x 64 cells) and of a whole scan's 25
tiles (rafd eval --full-scan's mosaic); and what the tracks add to the answer's JSON per box.

    python -m bench.tracking [--boxes 32] [--frames 400] [--rounds 5]

Times the CPU time of the calling thread (time.thread_time) around each step, so work of other processes on a
shared machine is not counted directly (it still slows a core whose sibling or cache it shares): each case runs
`--rounds` times, interleaved with the others, and prints the lowest and highest of the rounds' median ms per scan
and the p99 of the best round, after a warm-up. Torch-free.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from rafd.cli import flags
from rafd.runtime.view import TileGrid
from rafd.tracking import VELOCITY_MODES, FlowField, FlowGrid, TrackerSettings, TrackerState, step

PERIOD_S = 0.25
CELL_M = 0.694  # the shipped model's flow cells (256 px at 0.1736 m / px, 64 x 64)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m bench.tracking", description=__doc__.splitlines()[0])
    for flag, default, high, what in (
        ("--boxes", 32, 1000, "vehicles (and so boxes) per scan"),
        ("--frames", 400, 100000, "scans timed per case and round (after 20 of warm-up)"),
        ("--rounds", 5, 100, "rounds of every case, interleaved"),
    ):
        parser.add_argument(
            flag, type=flags.int_in(1, high), default=default, metavar="N", help=f"{what} (%%(default)s)"
        )
    flags.add_quiet(parser)
    return parser


def synthetic_stream(boxes: int, frames: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """[frames] (ego boxes [N, 5], world pose [3], time): a third of the vehicles parked, the rest driving at up to
    14 m/s, 0.3 m of detection noise, the ego driving 8 m/s at UTM-sized coordinates."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(-40.0, 40.0, (boxes, 2))
    velocity = rng.uniform(-14.0, 14.0, (boxes, 2)) * (rng.random((boxes, 1)) > 0.33)
    stream = []
    for k in range(frames):
        pose = np.array([6.0e5, 5.7e6 + 8.0 * PERIOD_S * k, 0.0])
        world = start + velocity * PERIOD_S * (k % 40)  # they come round again every 10 s: the crowd stays in view
        ego = world + rng.normal(0.0, 0.3, (boxes, 2)) + np.array([0.0, 0.0])
        rows = np.concatenate([ego, np.tile([1.8, 4.5, 0.0], (boxes, 1))], 1)
        stream.append((rows, pose, 100.0 + PERIOD_S * k))
    return stream


def crop_flow(seed: int = 1) -> FlowField:
    rng = np.random.default_rng(seed)
    grid = FlowGrid.centred(64, 64, CELL_M)
    flow = rng.normal(0.0, 0.3, (2, 64, 64)).astype(np.float32)
    return FlowField(grid, flow, PERIOD_S, np.ones((64, 64), np.float32), reach_m=4.17)


def scan_mosaic(seed: int = 2) -> tuple[FlowField, ...]:
    rng = np.random.default_rng(seed)
    tiles = TileGrid.for_model(256)
    return tuple(
        FlowField(
            FlowGrid.centred(64, 64, CELL_M, (float(x), float(y))),
            rng.normal(0.0, 0.3, (2, 64, 64)).astype(np.float32),
            PERIOD_S,
            np.ones((64, 64), np.float32),
            reach_m=4.17,
        )
        for x, y in tiles.offsets_m
    )


def time_case(stream, settings: TrackerSettings, flow) -> list[float]:
    """-> CPU ms of each step after 20 of warm-up."""
    state = TrackerState.empty()
    times = []
    for k, (boxes, pose, stamp) in enumerate(stream):
        scores = np.full(len(boxes), 0.9)
        start = time.thread_time()
        _, state = step(state, boxes, pose, stamp, scores=scores, flow=flow, settings=settings)
        if k >= 20:
            times.append(1000.0 * (time.thread_time() - start))
    return times


def answer_growth(stream, flow) -> float:
    """Bytes of JSON per box the tracks add (track_id, age, hits, status, velocity, its covariance and source, with
    the service's roundings: 4 decimals)."""
    state = TrackerState.empty()
    answer = None
    for boxes, pose, stamp in stream[:10]:
        answer, state = step(state, boxes, pose, stamp, flow=flow)
    assert answer is not None
    sizes = []
    for record in answer.records():
        added = {
            "track_id": record["track_id"],
            "age": record["age"],
            "hits": record["hits"],
            "status": record["status"],
            "velocity": {k: round(v, 4) for k, v in record["velocity"].items()},
            "velocity_covariance": [[round(v, 4) for v in row] for row in record["velocity_covariance"]],
            "velocity_source": record["velocity_source"],
        }
        sizes.append(len(json.dumps(added, separators=(",", ":"))) + 1)  # + the comma joining it to the box
    return statistics.mean(sizes)


def main(argv: list[str] | None = None) -> int:
    parser, args = flags.parse(build_parser, argv)
    stream = synthetic_stream(args.boxes, args.frames + 20)
    crop, mosaic = crop_flow(), scan_mosaic()
    cases = []
    for mode in VELOCITY_MODES:
        flows = [("one crop (64 x 64)", crop), ("whole scan (25 tiles)", mosaic)]
        cases += [(mode, name, flow) for name, flow in ([("none", None)] if mode == "filter" else flows)]
    rounds: dict[tuple[str, str], list[list[float]]] = {(mode, name): [] for mode, name, _ in cases}
    for _ in range(args.rounds):
        for mode, name, flow in cases:
            rounds[(mode, name)].append(time_case(stream, TrackerSettings(velocity=mode), flow))
    print(
        f"rafd.tracking.step, {args.boxes} boxes per scan, CPU ms per scan (thread time), {args.frames} scans x "
        f"{args.rounds} rounds"
    )
    print(f"{'velocity':<14}{'flow':<26}{'median (best-worst round)':>28}{'p99 (best round)':>18}")
    for (mode, name), times in rounds.items():
        medians = [statistics.median(t) for t in times]
        best = times[int(np.argmin(medians))]
        spread = f"{min(medians):.3f} - {max(medians):.3f}"
        print(f"{mode:<14}{name:<26}{spread:>28}{float(np.percentile(best, 99)):18.3f}")
    print(f"answer growth: {answer_growth(stream, crop):.0f} bytes of JSON per box")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
