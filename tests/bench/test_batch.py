"""bench.batch times every (runtime, threads, batch) row on a small batchable export and refuses a graph
without a batch axis."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.batch import main
from export.onnx_export import export_onnx
from tests.utils.export_testing import make_checkpoint, small_config


@pytest.fixture(scope="module")
def exports(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("batch_cost")
    checkpoint = make_checkpoint(root / "model.pt", small_config(4))
    dynamic = export_onnx(checkpoint, root / "dynamic.onnx", batch="dynamic", verify=False, log=lambda _: None)
    static = export_onnx(checkpoint, root / "static.onnx", verify=False, log=lambda _: None)
    return dynamic.path, static.path


def test_every_row_is_timed(exports, capsys):
    assert main([str(exports[0]), "--batches", "1,2", "--rounds", "1", "--runtimes", "onnxruntime"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("onnxruntime")]
    assert len(rows) == 6 and all(float(row.split()[-2]) > 0 for row in rows)


def test_a_graph_without_a_batch_axis_is_refused(exports, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([str(exports[1]), "--runtimes", "onnxruntime"])
    assert exit_info.value.code == 2 and "--batch dynamic" in capsys.readouterr().err
