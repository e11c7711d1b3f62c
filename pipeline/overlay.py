"""An overlay burned into every frame (a timestamp, a vehicle's name, a depth readout): what a scene mask should leave
out, found where it stays still, sits in the frame's border and looks like text.

A burned-in overlay has three signs at once, and the finder asks for all three:

- it stays still: over ``OVERLAY_FRAMES`` frames spread over the survey (grey, at most ``WORK_PX`` wide), a pixel of
  the overlay keeps its value while the scene moves under it, so its standard deviation over the frames is below
  ``STILL_SHARE`` of the frame's median one; and, where SfM matched the frames, the overlay holds matches that stay
  within ``STILL_PX`` while their pair's median match moves ``MOVING_PX`` or more;
- it is text-like: those still pixels lie on sharp edges of the frames' median image (its gradient magnitude at
  least ``SHARP_TIMES`` its median over the frame; a low-contrast region that merely looks alike from frame to frame,
  a far wall's tiles, has none), as strokes: joined into one line by a dilation of ``LINE_GAP`` of the frame's width
  (a character's spacing), some row of the line crosses at least ``MIN_STROKES`` separate strokes (a long edge of the
  scene is one), the line at most ``MAX_LINE_SHARE`` of the frame's height tall and ``MAX_LINE_WIDTH`` of its width
  wide;
- it sits in the frame's border: the line's box lies within ``BORDER_SHARE`` of the frame's height from its top or
  bottom, or of its width from its left or right.

Along a line the characters that change (a clock's seconds) are not still; the median image still draws them sharp,
so the line's box is widened along its rows over the median's sharp pixels within one line height of it. The box
(x0, y0, x1, y1, x1 and y1 excluded, as ``mask_rects_px`` takes it) is padded by ``PAD_PX`` and scaled to the
frames' pixels. A frame without such a line gives nothing: the finder proposes no mask rather than a part of the
scene.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: A pair whose median match moves this far (pixels) moved the camera.
MOVING_PX = 20.0
#: A match displaced by less than this (pixels) in such a pair stayed still.
STILL_PX = 1.0
#: Still matches an overlay's box must hold (where SfM matched the frames).
MIN_MATCHES = 5
#: Frames the finder reads, spread over the survey, and the width it reads them at (pixels).
OVERLAY_FRAMES, WORK_PX = 12, 1280
#: A pixel stays still when its standard deviation over the frames is below this share of the frame's median one.
STILL_SHARE = 0.35
#: A text edge: the median image's gradient magnitude at least this many times its median over the frame.
SHARP_TIMES = 4.0
#: Separate still pieces a line of text holds; their joining dilation (share of the frame's width, and of its height
#: across the line); the tallest and the widest line (shares of the frame's height and width).
MIN_STROKES, LINE_GAP, LINE_ACROSS, MAX_LINE_SHARE, MAX_LINE_WIDTH = 4, 0.02, 0.01, 0.12, 0.6
#: The border the overlay sits in: this share of the frame's height from the top or bottom, or of its width from the
#: left or right.
BORDER_SHARE = 0.2
#: Padding of the proposed box (pixels of the frames).
PAD_PX = 4


def overlay_boxes(frames: list[np.ndarray]) -> list[list[int]]:
    """The boxes [x0, y0, x1, y1] of the lines of an overlay in ``frames`` ((H,W) grey arrays of one survey, in any
    order; see the module docstring), in their pixels, the line with the most strokes first; empty when no line of
    text stays still in their border."""
    import cv2

    if len(frames) < 3:
        return []
    height, width = frames[0].shape[:2]
    scale = min(1.0, WORK_PX / width)
    stack = np.stack([cv2.resize(f, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else f
                      for f in frames]).astype(np.float32)
    h, w = stack.shape[1:]
    spread, median = stack.std(0), np.median(stack, 0)
    gradient = np.hypot(cv2.Sobel(median, cv2.CV_32F, 1, 0), cv2.Sobel(median, cv2.CV_32F, 0, 1))
    sharp = gradient > SHARP_TIMES * max(float(np.median(gradient)), 1e-6)
    border = np.zeros((h, w), bool)
    by, bx = max(1, round(BORDER_SHARE * h)), max(1, round(BORDER_SHARE * w))
    border[:by], border[-by:], border[:, :bx], border[:, -bx:] = True, True, True, True
    strokes = ((spread < STILL_SHARE * max(float(np.median(spread)), 1e-6)) & sharp & border).astype(np.uint8)
    kernel = np.ones((max(3, round(LINE_ACROSS * h)) | 1, max(3, round(LINE_GAP * w)) | 1), np.uint8)
    m, lines, boxes, _ = cv2.connectedComponentsWithStats(cv2.dilate(strokes, kernel), connectivity=8)
    found = []
    for j in range(1, m):
        x, y, bw, bh, _ = boxes[j]
        x1, y1 = x + bw, y + bh
        in_border = y1 <= by or y >= h - by or x1 <= bx or x >= w - bx
        if bh > MAX_LINE_SHARE * h or bw > MAX_LINE_WIDTH * w or not in_border:
            continue
        row = (strokes[y:y1, x:x1] > 0) & (lines[y:y1, x:x1] == j)
        held = int((row[:, :1].sum(1) + (row[:, 1:] & ~row[:, :-1]).sum(1)).max())  # strokes a row crosses
        if held < MIN_STROKES:
            continue
        x0, y0, x1, y1 = _along_the_line(sharp, x, y, x1, y1)
        if x1 - x0 <= MAX_LINE_WIDTH * w:
            found.append((held, [max(0, int(np.floor(x0 / scale)) - PAD_PX),
                                         max(0, int(np.floor(y0 / scale)) - PAD_PX),
                                         min(width, int(np.ceil(x1 / scale)) + PAD_PX),
                                         min(height, int(np.ceil(y1 / scale)) + PAD_PX)]))
    return [box for _, box in sorted(found, key=lambda f: -f[0])]


def _along_the_line(sharp: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> tuple[int, int, int, int]:
    """The line's box grown over the median image's sharp pieces that touch it (the whole height of its characters)
    within one line height of it, then along its rows over sharp columns less than a line height apart (the
    characters that change)."""
    import cv2

    gap = max(1, y1 - y0)
    top, bottom = max(0, y0 - gap), min(sharp.shape[0], y1 + gap)
    n, pieces, boxes, _ = cv2.connectedComponentsWithStats(sharp[top:bottom].astype(np.uint8), connectivity=8)
    touching = set(np.unique(pieces[y0 - top:y1 - top, x0:x1])) - {0}
    for k in touching:
        x, y, bw, bh, _ = boxes[k]
        if bh <= 3 * gap and bw <= 3 * (x1 - x0):  # a piece of the text, not a long edge of the scene
            x0, y0, x1, y1 = min(x0, x), min(y0, top + y), max(x1, x + bw), max(y1, top + y + bh)
    columns = sharp[y0:y1].any(axis=0)
    while x1 < len(columns) and columns[x1:x1 + gap].any():
        x1 += int(np.argmax(columns[x1:x1 + gap])) + 1
    while x0 > 0 and columns[max(0, x0 - gap):x0].any():
        x0 = max(0, x0 - gap) + int(np.flatnonzero(columns[max(0, x0 - gap):x0])[0])
    return x0, y0, x1, y1


def still_matches(database: Path) -> tuple[np.ndarray, int]:
    """(the (N,2) positions of the database's matches that stay still in pairs where the camera moved, the number of
    such pairs)."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        keypoints = {image.image_id: db.read_keypoints(image.image_id)[:, :2] for image in db.read_all_images()}
        pair_ids, matches = db.read_all_matches()
    finally:
        db.close()
    still, moving = [np.zeros((0, 2))], 0
    for pair_id, match in zip(pair_ids, matches, strict=True):
        if len(match) < 2 * MIN_MATCHES:
            continue
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        shift = np.linalg.norm(keypoints[a][match[:, 0]] - keypoints[b][match[:, 1]], axis=1)
        if np.median(shift) < MOVING_PX:
            continue
        moving += 1
        still.append(keypoints[a][match[shift < STILL_PX, 0]])
    return np.concatenate(still), moving


def survey_frames(images_dir: Path, names: list[str]) -> list[np.ndarray]:
    """``OVERLAY_FRAMES`` of the frames ``names`` in ``images_dir``, spread over them, grey as stored."""
    import cv2

    names = sorted(names)
    picks = sorted({names[i] for i in np.linspace(0, len(names) - 1, min(OVERLAY_FRAMES, len(names))).round()
                    .astype(int)})
    frames = [cv2.imread(str(images_dir / name), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
              for name in picks]
    return [f for f in frames if f is not None]


def still_features(database: Path, width: int, height: int, images_dir: Path | None = None) -> dict | None:
    """The overlay SfM's matches and the frames show (see the module docstring): ``box_px`` [x0, y0, x1, y1] of its
    main line (x1, y1 excluded, as ``mask_rects_px`` takes it), ``boxes_px`` (every line of it), ``matches`` (still
    matches inside them) and ``pairs`` (pairs where the camera moved); None when nothing stays still in the frames'
    border with text-like structure, or without the frames (``images_dir``) to look at."""
    import pycolmap

    points, moving = still_matches(database)
    if not moving or images_dir is None:
        return None
    db = pycolmap.Database.open(str(database))
    try:
        names = [image.name for image in db.read_all_images()]
    finally:
        db.close()
    frames = [f for f in survey_frames(Path(images_dir), names) if f.shape[:2] == (height, width)]
    kept, matches = [], 0
    for x0, y0, x1, y1 in overlay_boxes(frames):
        inside = int(((points[:, 0] >= x0) & (points[:, 0] < x1) & (points[:, 1] >= y0) & (points[:, 1] < y1)).sum())
        if inside >= MIN_MATCHES:
            kept.append([x0, y0, x1, y1])
            matches += inside
    if not kept:
        return None
    return {"box_px": kept[0], "boxes_px": kept, "matches": matches, "pairs": moving}


def overlay_warning(found: dict) -> str:
    """What to do about an overlay that stays still (:func:`still_features`)."""
    boxes = found.get("boxes_px") or [found["box_px"]]
    where = "; ".join(f"x {x0}-{x1}, y {y0}-{y1}" for x0, y0, x1, y1 in boxes)
    return (f"sfm: {found['matches']} features stay still between frames while the scene moves ({found['pairs']} "
            f"pairs), on text in the frame's border at {where} px: a burned-in overlay (a timestamp)? Leave it out "
            f"with \"mask_rects_px\": {boxes} in camera.json (or a mask.png); the report draws it over a frame")
