"""The site depth net in a workspace: trained on the survey's own frames with dense depth, kept for monocular
correction only where it beats the flat seafloor on frames it never saw.

:func:`fit_site_depth` (run by the restorer stage after the restorer): every survey frame with the navigation's
altitude (and attitude) becomes a :class:`watergan.train_site_depth.SiteFrame` (its linear image, its flat
seafloor's depth, the dense stage's depth as the reference); the net trains on all but every 4th frame; the held-out
frames' metric depth is compared with the dense depth beside the flat seafloor's as it is
(:func:`eval.depth.compare_depth_folders`, ``metric``); ``use`` is true when the net's RMSE is below the flat
seafloor's both on relief pixels and over all pixels. The net, its record and the held-out maps and metrics go
into the restorer's folder (the record's ``metrics``: relative to it), so ``correct --mode monocular`` finds them
beside the restorer.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from eval.depth import DepthCompareConfig, Navigation, compare_depth_folders
from watergan.data import read_image
from watergan.errors import UserInputError
from watergan.formation.inverse import flat_floor_depth
from watergan.io import atomic_write_bytes, frame_file, read_depth
from watergan.train_site_depth import SiteDepthConfig, SiteFrame, save_site_depth, train_site_depth

HELD_OUT = "site_depth_heldout"
"""Folder (in the restorer's) of the held-out frames' depth (``pred/<stem>.npy``, metres) and their comparison."""


def site_frames(survey: Path, dense_dir: Path, navigation) -> list[SiteFrame]:
    """The survey's frames (``survey.json``'s order) that have the navigation's altitude, with their flat seafloor's
    depth and, where the dense stage wrote one, their reference depth."""
    frames = []
    for name in json.loads((survey / "survey.json").read_text())["frames"]:
        stem = Path(name).stem
        if stem not in navigation.altitude_m:
            continue
        image = read_image(frame_file(survey / "images", name), "linear").astype(np.float32)
        h, w = image.shape[:2]
        floor = flat_floor_depth(navigation.altitude_m[stem], navigation.K_for(h, w), h, w,
                                 navigation.down_cam.get(stem)).astype(np.float32)
        ref = dense_dir / f"{stem}.png"  # single precision: a survey's frames are held together
        frames.append(SiteFrame(name, image, floor, read_depth(ref).astype(np.float32) if ref.is_file() else None))
    return frames


def fit_site_depth(ws, config: SiteDepthConfig, model_dir: Path, progress: bool = True,
                   navigation: Navigation | None = None) -> dict:
    """Train, compare on the held-out frames and save into ``model_dir`` (see the module docstring); returns the
    record, or {"use": False, "why": ...} without training when the survey lacks what the net needs. ``navigation``:
    the altitudes (and attitudes) of the flat seafloor; None: the survey's navigation."""
    dense = ws.result("dense")
    survey = ws.stage_dir("survey")
    navigation = navigation if navigation is not None else Navigation.from_survey(survey / "survey.json")
    if dense is None or navigation is None or not navigation.altitude_m:
        return {"use": False, "why": "no dense depth, camera.json or navigation altitude: nothing to learn from"}
    dense_dir = ws.path(dense.depth_dir)
    frames = site_frames(survey, dense_dir, navigation)
    try:
        net, record = train_site_depth(frames, config, progress)
    except UserInputError as exc:
        return {"use": False, "why": str(exc)}
    held = Path(model_dir) / HELD_OUT
    for f in frames:
        if f.name in record["held_out"]:
            buffer = io.BytesIO()
            np.save(buffer, net.depth(f.image, f.floor_z).astype(np.float32))
            atomic_write_bytes(held / "pred" / f"{Path(f.name).stem}.npy", buffer.getvalue())
    try:
        compared = compare_depth_folders(held / "pred", dense_dir, held,
                                         DepthCompareConfig(pred_dir=str(held / "pred"), metric=True), navigation)
    except UserInputError as exc:  # no held-out frame with enough dense depth
        return {"use": False, "why": f"the held-out frames cannot be compared: {exc}"}
    relief, overall = compared.relief_rmse_ratio, compared.all_rmse_ratio
    use = bool(np.isfinite(relief) and relief < 1.0 and overall < 1.0)
    record.update(use=use, relief_rmse_ratio=relief, all_rmse_ratio=overall, held_out_frames=len(compared.per_image),
                  metrics=f"{HELD_OUT}/metrics.json",
                  why=(f"on {len(compared.per_image)} held-out frames its RMSE is {relief:.2f}x the flat seafloor's on "
                       f"relief pixels and {overall:.2f}x over all pixels: "
                       + ("monocular correction takes it" if use else "monocular correction keeps the flat seafloor")))
    save_site_depth(model_dir, net, record)
    return record


def site_depth_metrics(ws) -> Path | None:
    """The restorer stage's site depth net's held-out comparison (``metrics.json``), None when it trained none."""
    restorer = ws.result("restorer")
    metrics = getattr(restorer, "site_depth", {}).get("metrics") if restorer is not None else None
    return ws.folder("restorer") / metrics if metrics else None
