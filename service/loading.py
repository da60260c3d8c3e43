"""Open the ONNX runner and warm it up (runs in a worker thread from the app's lifespan)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rafd.config import RaFDConfig
from rafd.geometry import RADIATE_SCAN_SIZE
from rafd.runtime.view import View
from rafd.scans.cartesian import accepted_sizes
from service.settings import Settings

if TYPE_CHECKING:  # the runtime (onnxruntime, OpenVINO) is imported when the model loads, never at service import
    from rafd.runtime import Runner, StreamRunner

log = logging.getLogger(__name__)


def resolve_model_path(settings: Settings) -> Path:
    """RAFD_MODEL_PATH, or the model shipped in the package."""
    if settings.model_path is not None:
        path = Path(settings.model_path)
        if not path.is_file():
            raise FileNotFoundError(f"RAFD_MODEL_PATH={path} is not a file")
        return path
    from rafd.assets import default_onnx  # lazy: the shipped asset is optional at import time

    return Path(default_onnx())


def open_runner(settings: Settings) -> StreamRunner:
    """A rafd.runtime.StreamRunner on the configured runtime and precision (imported here, never at service
    import); "auto" picks the fastest this CPU supports for this model."""
    path = resolve_model_path(settings)
    from rafd.runtime import create_runner

    log.info(
        "loading %s (runtime %s, precision %s, %d threads per run, %d concurrent runs)",
        path,
        settings.runtime,
        settings.precision,
        settings.threads,
        settings.concurrent_runs,
    )
    from rafd.runtime.runners import time_runner

    def timer(runner: StreamRunner) -> float:
        """A candidate's run at the tiles of the view a full scan is detected over: what the service runs most."""
        view = full_scan_view(runner.config, settings.detect_range_m)
        return time_runner(runner, views=1 if view is None else len(view.tiles))

    runner = create_runner(
        path,
        settings.runtime,
        settings.precision,
        threads=settings.threads,
        concurrent_runs=settings.concurrent_runs,
        timer=timer,
    )
    log.info("serving on %s", runner.describe())
    if runner.precision_choice:
        log.info("precision: %s", runner.precision_choice["reason"])
    return runner


def check_buffer_length(settings: Settings, runner: Runner) -> None:
    """The per-stream buffer is the model's temporal window: the two must agree."""
    frames = runner.config.num_frames
    if settings.buffer_length is not None and settings.buffer_length != frames:
        raise ValueError(f"RAFD_BUFFER_LENGTH={settings.buffer_length} but the model takes {frames} frames")


def full_scan_view(config: RaFDConfig, range_m: float | None) -> View | None:
    """What a full RADIATE scan (posted, or converted from a polar or native scan) is detected over; None for a model
    that takes none (not at RADIATE's resolution)."""
    if RADIATE_SCAN_SIZE not in accepted_sizes(config.input_size, config.resolution):
        return None
    cell_px = config.input_size // config.feature_size
    return View.of(RADIATE_SCAN_SIZE, config.input_size, config.resolution, cell_px, range_m)


def warm_up(runner: Runner, settings: Settings) -> None:
    """One step on a blank frame, and for the service's StreamRunner every graph run a request can take: each of its
    backends (a lone run's, and the crowd's that concurrent streams use) at one view and at a whole scan's tiles.
    First-run allocations, kernel choices and OpenVINO's static-shape compilations happen before traffic; left to
    the first concurrent requests, they cost the first load level after start-up streams (`rafd bench capacity`)."""
    from rafd.runtime.streaming import StreamRunner

    size = runner.config.input_size
    runner.step(runner.new_state(), np.zeros((1, size, size), np.float32), np.zeros((1, 3)))
    if isinstance(runner, StreamRunner):
        view = full_scan_view(runner.config, settings.detect_range_m)
        runner.warm((1,) if view is None else (1, len(view.tiles)))
