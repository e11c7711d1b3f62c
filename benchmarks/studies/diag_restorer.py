"""Where a trained restorer's corrections go wrong, on a simulated survey's workspace (no files written there).

    .venv/bin/python benchmarks/studies/diag_restorer.py --workspace WS [--out DIR] [--blur-px 8]

WS: a finished ``watergan run`` workspace of a simulated survey (``00_survey/truth``, ``06_restorer``,
``07_correct/restorer``, ``01_sfm``). Prints:

- per frame, the linear mean of each channel of the corrected frame over that of the in-air truth:
  its mean and standard deviation over frames, and its correlation with the frame's median true range
  (a correction that does not know the frame's absolute range shows a strong correlation);
- the raw/truth and corrected/truth ratios averaged over frames on an 8x6 grid of the image (a fixed
  pattern, such as vignetting left in place, shows here);
- colour consistency (mean variance of c/(R+G+B) across views on the SfM points, as Table II) of the raw
  frames and of four corrections with the same model, written to ``--out``: the model as is; without
  the skip layers' residual; with the affine fields blurred by ``--blur-px``; with a flat depth input
  (each frame's mean estimated depth); and, for a restorer that takes altitude, with the true altitude
  (the median of the frame's true depth) in place of the navigation's. Only for the affine head;
- where the corrected frames' inconsistency comes from: the error of each observation's normalised
  colour against the in-air truth's at the same place, its variance across a point's views (averaged
  over points, as the consistency), and what is left after removing the mean error of each frame, of
  each place in the image (16x12 cells), and of both.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from eval.colour import consistency, observation_colours
from eval.tracks import Tracks
from pipeline.stages import stage_folder
from watergan.data import read_depth, read_image, read_nav_altitudes
from watergan.imaging import gaussian_blur
from watergan.io import quantise
from watergan.nets.restorer import position_maps, restore
from watergan.train_restorer import load_restorer


def _linear_frames(folder: Path, names: list[str]) -> np.ndarray:
    return np.stack([read_image(folder / n) for n in names])


def frame_ratios(ws: Path, names: list[str]) -> None:
    corrected = _linear_frames(stage_folder(ws, "correct") / "restorer" / "images", names)
    truth = _linear_frames(stage_folder(ws, "survey") / "truth" / "inair", names)
    ranges = np.array([np.median(r[r > 0]) for r in (cv2.imread(str(stage_folder(ws, "survey") / "truth" / "range" / n),
                                                                cv2.IMREAD_UNCHANGED) for n in names)])
    lit = truth.sum(-1) > 0.05
    ratio = np.array([[c[..., k][m].mean() / t[..., k][m].mean() for k in range(3)]
                      for c, t, m in zip(corrected, truth, lit, strict=True)])
    print("per-frame corrected/truth, linear mean   R       G       B")
    print(f"  mean over frames                     {ratio.mean(0).round(3)}")
    print(f"  std over frames                      {ratio.std(0).round(3)}")
    correlation = [round(float(np.corrcoef(ranges, ratio[:, k])[0, 1]), 2) for k in range(3)]
    print(f"  correlation with the frame's range   {correlation}")

    def cells(image: np.ndarray) -> np.ndarray:
        return cv2.resize(image, (8, 6), interpolation=cv2.INTER_AREA)

    raw = _linear_frames(stage_folder(ws, "survey") / "images", names)
    raw_grid = np.mean([cells(r) / cells(t) for r, t in zip(raw, truth, strict=True)], axis=0)
    raw_grid /= raw_grid.mean(axis=(0, 1), keepdims=True)
    print("raw/truth over the image (8x6 cells, mean 1), R G B: "
          + ", ".join(f"{raw_grid[..., k].min():.2f} .. {raw_grid[..., k].max():.2f}" for k in range(3)))
    grid = np.mean([cells(c) / cells(t) for c, t in zip(corrected, truth, strict=True)], axis=0)
    grid /= grid.mean(axis=(0, 1), keepdims=True)
    for k, channel in enumerate("RGB"):
        print(f"corrected/truth over the image (8x6 cells, mean 1), {channel}: "
              f"{grid[..., k].min():.2f} .. {grid[..., k].max():.2f}")
        print(np.array2string(grid[..., k], precision=2, max_line_width=120))


@torch.no_grad()
def write_variants(ws: Path, names: list[str], out: Path, blur_px: float) -> dict[str, Path]:
    model = load_restorer(stage_folder(ws, "restorer"))
    net = model.colour_net
    if net.head != "affine":
        raise SystemExit("the variants need a restorer with the affine head")
    variants = ["model", "no skip residual", f"fields blurred {blur_px:g} px", "flat depth"]
    if model.altitude:
        variants.append("true altitude")
        nav = read_nav_altitudes(stage_folder(ws, "survey") / "survey.json", names)
    folders = {v: out / v for v in variants}
    for folder in folders.values():
        folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        image = torch.from_numpy(cv2.imread(str(stage_folder(ws, "survey") / "images" / name))[..., ::-1].copy())
        image = image.permute(2, 0, 1).float()[None] / 255
        h, w = image.shape[-2:]
        if h % model.multiple or w % model.multiple:
            raise SystemExit(f"{name}: the variants need sides that are multiples of {model.multiple}")
        altitude = torch.tensor([nav[name]]) if model.altitude else None
        depth = F.interpolate(model.depth_net(image), size=(h, w), mode="bilinear", align_corners=False)
        x = torch.cat([image, depth, position_maps(h, w)], dim=1)
        fields = net.up(net.run_core(F.avg_pool2d(x, net.factor), None, altitude))
        flat = torch.cat([image, depth.mean().expand_as(depth), position_maps(h, w)], dim=1)
        outputs = [restore(model, image, altitude)[0], net.colours(fields, x),
                   net.colours(gaussian_blur(fields, blur_px), x), net(flat, None, altitude)]
        if model.altitude:
            true_depth = read_depth(stage_folder(ws, "survey") / "truth" / "depth" / name)
            outputs.append(restore(model, image, torch.tensor([float(np.median(true_depth[true_depth > 0]))]))[0])
        for folder, rgb in zip(folders.values(), outputs, strict=True):
            encoded = quantise(rgb[0].permute(1, 2, 0).numpy(), 8)
            cv2.imwrite(str(folder / name), encoded[..., ::-1])
    return folders


def _within_point_variance(point: np.ndarray, values: np.ndarray) -> float:
    """Mean over points of the variance of ``values`` across the point's observations."""
    n = np.bincount(point)
    s1, s2 = np.bincount(point, values), np.bincount(point, values * values)
    keep = n >= 3
    return float(np.mean(s2[keep] / n[keep] - (s1[keep] / n[keep]) ** 2))


def _minus_group_mean(values: np.ndarray, group: np.ndarray) -> np.ndarray:
    return values - (np.bincount(group, values) / np.maximum(np.bincount(group), 1))[group]


def error_decomposition(ws: Path, tracks: Tracks, ours: np.ndarray) -> None:
    """``ours``: the corrected frames' normalised colour at every observation (:func:`observation_colours`)."""
    truth = observation_colours(tracks, stage_folder(ws, "survey") / "truth" / "inair")
    ok = np.isfinite(truth).all(1) & np.isfinite(ours).all(1)
    ok &= np.bincount(tracks.obs_point[ok], minlength=len(tracks.xyz))[tracks.obs_point] >= 3
    point, image, xy = tracks.obs_point[ok], tracks.obs_image[ok], tracks.obs_xy[ok]
    h, w = tracks.height, tracks.width
    cell = (np.clip(xy[:, 0] * 16 // w, 0, 15) + 16 * np.clip(xy[:, 1] * 12 // h, 0, 11)).astype(np.int64)
    print("error of c/(R+G+B) against the in-air truth, variance across views (mean over points):")
    for k, channel in enumerate("RGB"):
        error = (ours - truth)[ok, k]
        parts = {"all": error, "minus frame mean": _minus_group_mean(error, image),
                 "minus place mean": _minus_group_mean(error, cell),
                 "minus both": _minus_group_mean(_minus_group_mean(error, image), cell)}
        print(f"  {channel}: " + ", ".join(f"{label} {_within_point_variance(point, v):.2e}"
                                         for label, v in parts.items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workspace", required=True, type=Path)
    parser.add_argument("--out", type=Path, default=Path("/tmp/diag_restorer"), help="variant images go here")
    parser.add_argument("--blur-px", type=float, default=8.0)
    args = parser.parse_args()
    ws = args.workspace
    torch.set_num_threads(2)
    names = sorted(p.name for p in (stage_folder(ws, "correct") / "restorer" / "images").glob("*.png"))
    frame_ratios(ws, names)
    folders = {"raw": stage_folder(ws, "survey") / "images", **write_variants(ws, names, args.out, args.blur_px)}
    tracks = Tracks.load(stage_folder(ws, "sfm") / "tracks.npz")
    colours = {name: observation_colours(tracks, folder) for name, folder in folders.items()}  # sampled once for both
    result = consistency(tracks, folders, colours=colours)
    print(f"consistency on {result.n_points} points (mean variance of c/(R+G+B) across views; R G B)")
    for name, score in result.scores.items():
        print(f"  {name:>24}: {score.mean_variance:.3e}  {np.round(score.variance, 7).tolist()}")
    error_decomposition(ws, tracks, colours["model"])


if __name__ == "__main__":
    main()
