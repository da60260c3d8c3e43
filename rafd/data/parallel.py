"""One job per sequence folder in parallel processes (odometry over a data root, preparing its scan cache)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

from rafd.progress import bar


def run_per_sequence(
    job: Callable[[Path], Any], folders: Sequence[Path], workers: int, desc: str, progress: bool = True
) -> tuple[list[tuple[Path, Any]], list[str]]:
    """job(folder) for every folder in up to `workers` processes (job must pickle: a module-level function or a
    functools.partial of one) -> ([(folder, result)] in completion order, ["folder: error"] of the jobs that raised
    OSError or ValueError; the others still run)."""
    results, failures = [], []
    with ProcessPoolExecutor(max_workers=min(workers, len(folders))) as pool:
        jobs = {pool.submit(job, folder): folder for folder in folders}
        for done in bar(
            as_completed(jobs), total=len(jobs), desc=f"{desc} {len(jobs)} sequences", unit="seq", enabled=progress
        ):
            try:
                results.append((jobs[done], done.result()))
            except (OSError, ValueError) as error:
                failures.append(f"{jobs[done]}: {error}")
    return results, failures
