"""The flags module's process-wide behaviour (rafd/cli/flags.py): SIGTERM ends a command through its `finally`
blocks, so what it wrote to a temporary place is removed."""

from __future__ import annotations

import signal
import subprocess
import sys

# a command's shape: a temporary folder beside its output, removed in `finally`, and a long step under way
COMMAND = """
import shutil, sys, tempfile, time
from rafd.cli.flags import exit_on_sigterm
exit_on_sigterm()
work = tempfile.mkdtemp(dir=sys.argv[1], prefix=".model.onnx.")
try:
    print("ready", flush=True)
    time.sleep(60)
finally:
    shutil.rmtree(work)
"""


def test_sigterm_ends_a_command_through_its_finally_blocks(tmp_path):
    process = subprocess.Popen([sys.executable, "-c", COMMAND, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    assert process.stdout is not None and process.stdout.readline() == "ready\n"
    assert len(list(tmp_path.iterdir())) == 1
    process.send_signal(signal.SIGTERM)
    assert process.wait(timeout=20) == 128 + signal.SIGTERM
    assert list(tmp_path.iterdir()) == []  # without the handler the folder stays (Python's default dies at once)
