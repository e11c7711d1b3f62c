"""Draw a labels file's objects (:mod:`eval.objects`) on the frames they are labelled in, so that anyone can check them.

    .venv/bin/python benchmarks/draw_objects.py --survey ../shared/data/subvo-pool \
        --labels benchmarks/data/subvo_objects.json --out DIR [--object NAME ...] [--sheet-width 320]

Writes ``DIR/<frame stem>.png`` per labelled frame (each region outlined in its kind's colour, with the object's
name), ``DIR/contact_sheet.png`` (every drawn frame downscaled, in name order, its name written on it) and, when the
survey folder holds a ``README.md`` or ``LICENSE`` (the data's notice), copies of them beside the drawings. The labels
file is checked first (:func:`eval.objects.load_object_labels`: regions inside the frame, known frame names).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: BGR outline colour per object kind.
KIND_BGR = {"white": (255, 255, 255), "red": (0, 0, 255), "yellow": (0, 255, 255), "cyan": (255, 255, 0),
            "dark": (255, 0, 255), "tiles_wall": (0, 165, 255), "tiles_floor": (0, 255, 0)}


def images_folder(survey: Path) -> Path:
    """The survey's frames: ``survey/images`` when it exists, else ``survey`` itself."""
    return survey / "images" if (survey / "images").is_dir() else survey


def draw_frame(image_bgr: np.ndarray, regions: list[tuple[str, str, np.ndarray]], scale_xy: tuple[float, float]
               ) -> np.ndarray:
    """A copy of the frame with each (name, kind, polygon) outlined and named."""
    import cv2

    out = image_bgr.copy()
    for name, kind, polygon in regions:
        points = np.rint(polygon * np.asarray(scale_xy)).astype(np.int32)
        colour = KIND_BGR.get(kind, (0, 255, 0))
        cv2.polylines(out, [points], True, (0, 0, 0), 3)
        cv2.polylines(out, [points], True, colour, 1)
        x, y = int(points[:, 0].min()), int(points[:, 1].min())
        org = (max(x, 2), max(y - 5, 14))
        cv2.putText(out, name, org, cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, name, org, cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)
    return out


def contact_sheet(drawn: list[tuple[str, np.ndarray]], width_px: int, columns: int = 4) -> np.ndarray:
    """The drawn frames downscaled to ``width_px`` each, ``columns`` a row, each with its name."""
    import cv2

    tiles = []
    for name, image in drawn:
        h, w = image.shape[:2]
        tile = cv2.resize(image, (width_px, max(1, round(h * width_px / w))), interpolation=cv2.INTER_AREA)
        cv2.putText(tile, Path(name).stem, (4, tile.shape[0] - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3)
        cv2.putText(tile, Path(name).stem, (4, tile.shape[0] - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 255, 255), 1)
        tiles.append(tile)
    height = max(t.shape[0] for t in tiles)
    tiles = [np.pad(t, ((0, height - t.shape[0]), (0, 0), (0, 0))) for t in tiles]
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % columns)
    return np.vstack([np.hstack(tiles[i:i + columns]) for i in range(0, len(tiles), columns)])


def draw_objects(survey: Path, labels_path: Path, out: Path, objects: list[str] | None = None,
                 sheet_width_px: int = 320) -> list[Path]:
    """Draw the labels on the survey's frames into ``out`` (see the module docstring); returns the files written."""
    import cv2

    from eval.objects import load_object_labels
    from watergan.errors import UserInputError
    from watergan.io import atomic_write_bytes, frame_file, read_bgr8
    from watergan.survey_files import image_files

    folder = images_folder(survey)
    names = image_files(folder)
    labels = load_object_labels(labels_path, names)
    chosen = [o for o in labels.objects if not objects or o.name in objects]
    if objects and len(chosen) < len(set(objects)):
        unknown = sorted(set(objects) - {o.name for o in labels.objects})
        raise UserInputError(f"no object named {', '.join(unknown)} in {labels_path} (it has "
                             f"{', '.join(o.name for o in labels.objects)})")
    frames = sorted({f for o in chosen for f in o.regions})
    out.mkdir(parents=True, exist_ok=True)
    written, drawn = [], []
    for frame in frames:
        image = read_bgr8(frame_file(folder, frame))
        h, w = image.shape[:2]
        regions = [(o.name, o.kind, o.regions[frame]) for o in chosen if frame in o.regions]
        picture = draw_frame(image, regions, (w / labels.width, h / labels.height))
        path = out / f"{Path(frame).stem}.png"
        atomic_write_bytes(path, cv2.imencode(".png", picture)[1].tobytes())
        written.append(path)
        drawn.append((frame, picture))
    if drawn:
        path = out / "contact_sheet.png"
        atomic_write_bytes(path, cv2.imencode(".png", contact_sheet(drawn, sheet_width_px))[1].tobytes())
        written.append(path)
    for notice in ("README.md", "LICENSE"):
        if (survey / notice).is_file():
            shutil.copy(survey / notice, out / (notice if notice == "LICENSE" else "NOTICE.md"))
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--survey", required=True, help="the survey folder (its images/, or the frames themselves)")
    parser.add_argument("--labels", required=True, help="the labels file (JSON)")
    parser.add_argument("--out", required=True, help="folder for the drawings")
    parser.add_argument("--object", action="append", default=None, help="draw only this object (repeatable)")
    parser.add_argument("--sheet-width", type=int, default=320, help="width of each frame in the contact sheet, px")
    args = parser.parse_args()
    from watergan.errors import UserInputError

    try:
        written = draw_objects(Path(args.survey), Path(args.labels), Path(args.out), args.object, args.sheet_width)
    except UserInputError as exc:
        sys.exit(f"error: {exc}")
    print(f"{len(written)} files in {args.out}")


if __name__ == "__main__":
    main()
