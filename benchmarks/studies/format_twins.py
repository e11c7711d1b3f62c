"""A simulated survey as PNG, JPEG and 16-bit TIFF twins, each through ``watergan run``: every method in the
tables, and the board and consistency of each against the PNG run's.

    PYTHONPATH=. .venv/bin/python benchmarks/studies/format_twins.py SURVEY OUT [-- RUN OPTIONS...]

SURVEY: a simulated survey folder (images/, right/, camera.json, survey.json, truth/, rgbd/; e.g. a demo
workspace's 00_survey). OUT/{png,jpeg,tiff}/survey: the twins (images and right frames re-encoded: JPEG quality 95,
TIFF 16 bits; survey.json's frame names changed; truth/ and rgbd/ linked, as the simulator wrote them);
OUT/{png,jpeg,tiff}/ws: their workspaces. Prints and writes OUT/formats.json: per twin and method the board's
CIEDE2000 and the consistency per channel, and their ratio to the PNG run's.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2

from pipeline.stages import stage_folder

ROOT = Path(__file__).resolve().parents[2]  # the repository: result files name paths relative to it
FORMATS = {"png": (".png", []), "jpeg": (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 95]), "tiff": (".tif", [])}


def make_twin(survey: Path, out: Path, fmt: str) -> Path:
    """The survey with its frames re-encoded in ``fmt`` (16-bit TIFF: the 8-bit values times 257)."""
    suffix, params = FORMATS[fmt]
    twin = out / fmt / "survey"
    if twin.exists():
        return twin
    for folder in ("images", "right"):
        if not (survey / folder).is_dir():
            continue
        (twin / folder).mkdir(parents=True)
        for path in sorted((survey / folder).iterdir()):
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if fmt == "tiff" and image.dtype == "uint8":
                image = image.astype("uint16") * 257
            cv2.imwrite(str(twin / folder / f"{path.stem}{suffix}"), image, params)
    shutil.copy(survey / "camera.json", twin / "camera.json")
    nav = json.loads((survey / "survey.json").read_text())
    for key in ("frames", "images", "right_images"):
        if isinstance(nav.get(key), list):
            nav[key] = [f"{Path(n).stem}{suffix}" if isinstance(n, str) else n for n in nav[key]]
    (twin / "survey.json").write_text(json.dumps(nav, indent=1))
    for folder in ("truth", "rgbd"):
        if (survey / folder).exists():
            (twin / folder).symlink_to((survey / folder).resolve())
    return twin


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("survey", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("run_options", nargs="*", help="options for `watergan run` (after --)")
    args = parser.parse_args()
    rows = {}
    for fmt in FORMATS:
        twin = make_twin(args.survey, args.out, fmt)
        ws = args.out / fmt / "ws"
        done = subprocess.run([sys.executable, "-m", "pipeline.cli", "run", str(twin), "--workspace", str(ws),
                               "--no-progress", *args.run_options], capture_output=True, text=True)
        if done.returncode != 0:
            print(f"{fmt}: watergan run failed ({done.returncode}):\n{done.stderr[-3000:]}")
            rows[fmt] = {"failed": done.stderr[-3000:]}
            continue
        result = json.loads((stage_folder(ws, "eval") / "result.json").read_text())["result"]
        rows[fmt] = {"board": result["mean_board_ciede2000"], "consistency": result["consistency_variance"],
                     "seconds": json.loads((ws / "run_summary.json").read_text())["seconds"]}
        print(f"{fmt}: methods {sorted(rows[fmt]['board'])}; {rows[fmt]['seconds']:.0f} s", flush=True)
    png = rows.get("png", {})
    for fmt, row in rows.items():
        if "board" not in row or "board" not in png:
            continue
        row["board_vs_png"] = {m: round(v / png["board"][m], 4) for m, v in row["board"].items() if m in png["board"]}
        row["consistency_vs_png"] = {m: [round(a / b, 4) for a, b in zip(v, png["consistency"][m], strict=True)]
                                     for m, v in row["consistency"].items() if m in png["consistency"]}
        for m in sorted(row["board"]):
            print(f"{fmt:5s} {m:24s} board {row['board'][m]:.3f} ({row['board_vs_png'].get(m, float('nan')):.3f} x png)"
                  f"  consistency x png " + "/".join(f"{v:.3f}" for v in row["consistency_vs_png"].get(m, [])))
    (args.out / "formats.json").write_text(json.dumps({"survey": os.path.relpath(args.survey, ROOT),
                                                       "options": args.run_options, "twins": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
