"""The README's curl example, reproduced in process: frames 1 then 2 of a RADIATE sequence to a fresh stream.

    python -m tools.readme_example "$RAFD_RADIATE_SAMPLE"                    # print the answer block
    python -m tools.readme_example "$RAFD_RADIATE_SAMPLE" --write README.md  # rewrite README.md's block

The answer block in README.md sits between the EXAMPLE_BEGIN / EXAMPLE_END markers; tests/tools/test_readme_example.py
checks it against `example_answer` on the shipped model. Regenerate it whenever the
shipped model or the odometry changes (the answer carries the odometry's pose of frame 2). Needs the dev extra
(FastAPI's TestClient uses httpx); imports no torch.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

EXAMPLE_BEGIN = "<!-- readme-example:begin (python -m tools.readme_example SAMPLE --write README.md) -->"
EXAMPLE_END = "<!-- readme-example:end -->"
STREAM_ID = "demo"
FRAMES = (1, 2)  # Navtech_Cartesian/000001.png then 000002.png, posted with timestamps 1 and 2
QUERY = "?flow=false"
LINE_WIDTH = 116


def example_answer(sample: Path, model: Path | None = None, threads: int = 1) -> dict[str, Any]:
    """What the README's two curl calls answer (the second answer), on `model` (default: the shipped one)."""
    from fastapi.testclient import TestClient

    from rafd.runtime import OnnxRunner
    from service.app import create_app
    from service.settings import Settings

    if model is None:
        from rafd.assets import default_onnx

        model = Path(default_onnx())
    app = create_app(Settings(threads=threads), runner=OnnxRunner(model, threads=threads))
    answer: dict[str, Any] = {}
    with TestClient(app) as client:
        for _ in range(600):
            if client.get("/health/ready").status_code == 200:
                break
            time.sleep(0.1)
        for frame in FRAMES:
            path = Path(sample) / "Navtech_Cartesian" / f"{frame:06d}.png"
            response = client.post(
                f"/detect{QUERY}",
                data={"stream_id": STREAM_ID, "timestamp": str(frame)},
                files={"image": (path.name, path.read_bytes(), "image/png")},
            )
            if response.status_code != 200:
                raise RuntimeError(f"{path}: {response.status_code} {response.text}")
            answer = response.json()
    return answer


def shown(answer: dict[str, Any]) -> dict[str, Any]:
    """The answer as the README shows it: pose to 0.1 mm, the checkpoint hash shortened, timings to 0.1 ms."""
    out = dict(answer)
    out["pose"] = {k: round(v, 4) for k, v in answer["pose"].items()}
    out["model"] = {**answer["model"], "checkpoint_sha256": answer["model"]["checkpoint_sha256"][:8] + "..."}
    out["timing"] = {k: round(v, 1) for k, v in answer["timing"].items()}
    return out


def _dump(value: Any) -> str:
    return json.dumps(value, separators=(", ", ": "))


def _box_lines(box: dict[str, Any], indent: str) -> list[str]:
    """One box as two lines: its fields, then its polygon."""
    fields = ", ".join(f"{_dump(k)}: {_dump(v)}" for k, v in box.items() if k != "polygon")
    return [f"{indent}{{{fields},", f'{indent} "polygon": {_dump(box["polygon"])}}}']


def render(answer: dict[str, Any]) -> str:
    """The shown answer as a json code block: fields packed into lines of at most LINE_WIDTH, each box on two."""
    lines: list[str] = []
    current = ""
    for key, value in shown(answer).items():
        if key == "boxes" and value:
            if current:
                lines.append(current + ",")
            boxes = [_box_lines(box, " " * 11) for box in value]
            boxes[0][0] = ' "boxes": [' + boxes[0][0].lstrip()
            for box in boxes[:-1]:
                box[-1] += ","
            boxes[-1][-1] += "],"
            lines += [line for box in boxes for line in box]
            current = ""
            continue
        item = f"{_dump(key)}: {_dump(value)}"
        if current and len(current) + len(item) + 2 > LINE_WIDTH:
            lines.append(current + ",")
            current = ""
        current = f"{current}, {item}" if current else " " + item
    lines.append(current)
    lines[0] = "{" + lines[0][1:]
    return "```json\n" + "\n".join(lines) + "}\n```"


def replace_block(readme: str, block: str) -> str:
    begin, end = readme.index(EXAMPLE_BEGIN) + len(EXAMPLE_BEGIN), readme.index(EXAMPLE_END)
    return readme[:begin] + "\n" + block + "\n" + readme[end:]


def read_block(readme: str) -> dict[str, Any]:
    """The JSON answer shown in README.md between the markers."""
    begin, end = readme.index(EXAMPLE_BEGIN) + len(EXAMPLE_BEGIN), readme.index(EXAMPLE_END)
    text = readme[begin:end].strip()
    return json.loads(text.removeprefix("```json").removesuffix("```"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.readme_example", description=__doc__.splitlines()[0])
    parser.add_argument("sample", type=Path, help="a RADIATE sequence folder (tiny_foggy)")
    parser.add_argument("--model", type=Path, default=None, help="ONNX model (default: the shipped one)")
    parser.add_argument("--write", type=Path, default=None, help="rewrite the block in this README")
    args = parser.parse_args(argv)
    block = render(example_answer(args.sample, args.model))
    if args.write is None:
        print(block)
        return 0
    args.write.write_text(replace_block(args.write.read_text(), block))
    print(f"rewrote the example answer in {args.write}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
