"""Features that never move between frames: the sign of an overlay (a burned-in timestamp, the vehicle's frame, a
port's edge) that a scene mask should leave out.

Among the SfM database's raw matches of every pair whose median feature displacement is at least ``MOVING_PX`` (the
camera moved), a match displaced by less than ``STILL_PX`` is a feature that stayed where it was while the scene
moved. Their positions are counted on a grid of ``CELL_PX`` cells; the cells holding at least ``MIN_SHARE`` of the
moving pairs' count (and at least ``MIN_COUNT``) are the overlay, and their bounding box is what a user would mask.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: A pair whose median match moves this far (pixels) moved the camera.
MOVING_PX = 20.0
#: A match displaced by less than this (pixels) in such a pair stayed still.
STILL_PX = 1.0
#: Grid cell side (pixels), and the count a cell needs: this share of the moving pairs, and at least MIN_COUNT.
CELL_PX, MIN_SHARE, MIN_COUNT = 32, 0.02, 5


def still_features(database: Path, width: int, height: int) -> dict | None:
    """The overlay the database's matches show (see the module docstring): ``box_px`` [x0, y0, x1, y1] (x1, y1
    excluded, as ``mask_rects_px`` takes it), ``matches`` (still matches inside it) and ``pairs`` (moving pairs);
    None when no cell holds enough still matches."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        keypoints = {image.image_id: db.read_keypoints(image.image_id)[:, :2] for image in db.read_all_images()}
        pair_ids, matches = db.read_all_matches()
    finally:
        db.close()
    still, moving = [], 0
    for pair_id, match in zip(pair_ids, matches, strict=True):
        if len(match) < 2 * MIN_COUNT:
            continue
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        shift = np.linalg.norm(keypoints[a][match[:, 0]] - keypoints[b][match[:, 1]], axis=1)
        if np.median(shift) < MOVING_PX:
            continue
        moving += 1
        still.append(keypoints[a][match[shift < STILL_PX, 0]])
    if not moving:
        return None
    points = np.concatenate(still)
    counts = np.zeros((height // CELL_PX + 1, width // CELL_PX + 1), int)
    np.add.at(counts, (np.clip(points[:, 1], 0, height - 1).astype(int) // CELL_PX,
                       np.clip(points[:, 0], 0, width - 1).astype(int) // CELL_PX), 1)
    rows, cols = np.nonzero(counts >= max(MIN_COUNT, MIN_SHARE * moving))
    if not len(rows):
        return None
    box = [int(cols.min() * CELL_PX), int(rows.min() * CELL_PX), int(min(width, (cols.max() + 1) * CELL_PX)),
           int(min(height, (rows.max() + 1) * CELL_PX))]
    return {"box_px": box, "matches": int(counts[rows, cols].sum()), "pairs": moving}


def overlay_warning(found: dict) -> str:
    """What to do about features that never move."""
    x0, y0, x1, y1 = found["box_px"]
    return (f"sfm: {found['matches']} features stay still between frames while the scene moves ({found['pairs']} "
            f"pairs), within x {x0}-{x1}, y {y0}-{y1} px: an overlay (a timestamp, the vehicle's frame)? Leave it out "
            f"with \"mask_rects_px\": [[{x0}, {y0}, {x1}, {y1}]] in camera.json (or a mask.png), widened to the whole "
            f"overlay")
