"""Real footage, scored without truth: the pool crawler's survey (``../shared/data/subvo-pool``) run end to end as a
user of that camera would run it, with only the image size known.

    .venv/bin/python benchmarks/bench_real.py [--out DIR] [--width 1280] [--frames 80] [--json PATH]
                                              [--measure-only] [extra `watergan run` options...]

``--measure-only`` skips the run and measures the finished workspace ``OUT/ws`` again (minutes, not the run's
twenty).

The survey folder it writes (``OUT/survey``): ``images/`` (links to the frames, or copies resized to ``--width``),
``camera.json`` holding only the image size and the burned-in timestamp's rectangle (``mask_rects_px``), and
``navigation.csv`` converted from the data's ``track.csv`` (its ``x_m``, ``z_m`` in the floor plane written as
``x_m``, ``y_m``), as a user would. Then ``watergan run OUT/survey --workspace OUT/ws``.

What it measures, with the keys of ``benchmarks/results/real.json``:

- SfM: ``registered`` of ``frames``, ``reprojection_px``; the self-calibration (model, focal length, lens) and
  ``focal_halves_pct`` (each half of the survey bundle-adjusted alone: :func:`pipeline.calibrate.self_calibrate`);
- scale: the track's similarity (scale, spread, residual) and ``scale_heldout_pct`` (the first half of the
  positions against the second: :func:`pipeline.scale.track_halves`); ``scale_height_halves_pct``: the same check
  read from the model's camera heights over the floor (:func:`model_height_halves`), which the track does not enter;
- the water with its intervals (``water``);
- per method (raw, physics, restorer, gray world, Sea-thru): Table II's ``consistency`` (R, G, B: variance of
  normalised colour across each 3D point's views), and the tile test: the floor is one tile colour near and far,
  so the mean over its pixels of the chromaticity c = RGB / (R + G + B) in its far band (rows 50-62 % of the frame)
  and in its near band (rows 88-100 %), linear RGB, middle 70 % of the width, every frame pooled and the pixels the
  scene mask says are not the scene left out, should agree: ``tile_chromaticity_distance`` = |c_far - c_near|
  (Euclidean; ``tile_chromaticity_distance_of_mean``: the same for each band's mean colour, which the far band's
  blur, mixing tile and grout in a pixel, does not bias) and ``tile_luminance_ratio`` = the bands' mean Y_far /
  Y_near (Y = 0.2126 R + 0.7152 G + 0.0722 B).
  ``black_pixels`` counts the
  corrected frames' pixels at 0 in every channel outside the mask;
  Table II again at patch sizes of 5, 15 and 31 px (``consistency_by_patch_px``: patch side -> R, G, B), these
  methods measured together on the same observations, so its 5 px values can differ a little from ``consistency``
  (the eval stage pools every one of its methods); at 5 px the measure follows the tile/grout texture;
- per labelled object (``benchmarks/data/subvo_objects.json``, drawn by ``benchmarks/draw_objects.py``; regions mapped
  into the workspace's undistorted frames) and method, under ``methods.<method>.objects.<name>``: the mean linear
  colour per frame, its range per frame (the water stage's range maps) and median range, the chromaticity spread
  across its frames ``object_chromaticity_spread`` (sum over channels of max - min of c = RGB / (R + G + B)) and
  the slope of c against ln range (:mod:`eval.objects`); ``methods.<method>.objects_median_spread``, the median
  over objects; ``objects``: the labels, their counts and each method's median spread over raw's; the figure
  ``real_objects.png`` beside the JSON (each object's chromaticity against range, raw beside each correction);
- ``dark_object_veil``: per dark object (kind "dark") and raw frame, its mean linear radiance and range beside the
  water's additive term at that range, C(r) = k B_inf (1 - exp(-beta r)) at the image centre, with the interval
  of the box of k's, B_inf's and beta's intervals and whether the radiance lies inside (:func:`eval.objects.
  dark_object_veil`); ``record_veil``: water.json's veil at the views' median range with its joint interval;
- ``depth_relief_ratio``: the site depth net's RMSE against the dense range on relief pixels of held-out frames over
  the flat seafloor's (``depth_relief``: both RMSEs, over all pixels too, and the best plane's); from the restorer
  stage's comparison, or, where the survey has no altimeter (the pool), the net trained here with the model's floor
  at each camera's height as its flat seafloor (:func:`depth_relief`);
- seconds per stage and the run's peak memory (``ru_maxrss`` of the children).

The data's notice (its README: source, licence, attribution) is copied beside everything written from it.
"""

from __future__ import annotations

import argparse
import csv
import json
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data" / "subvo-pool"
#: The burned-in timestamp at full size (1280x720), pixels [x0, y0, x1, y1].
TIMESTAMP_PX = (0, 0, 430, 45)
#: The tile test's bands: rows as fractions of the frame's height, and the middle fraction of its width.
FAR_ROWS, NEAR_ROWS, MIDDLE = (0.50, 0.62), (0.88, 1.00), 0.70
#: The labelled objects of the footage (full-size pixels of the original frames).
OBJECT_LABELS = ROOT / "benchmarks" / "data" / "subvo_objects.json"
#: Table II's patch sizes, pixels of the workspace's frames.
PATCHES_PX = (5, 15, 31)
#: The methods the per-object and per-patch measures take, in this order.
OBJECT_METHODS = ("raw", "physics", "restorer", "gray_world", "seathru")


def prepare_survey(out: Path, width: int, n_frames: int) -> Path:
    """The survey folder a user of this camera would write (see the module docstring); frames resized to ``width``
    (and their mask and track alike) when it is not the data's 1280, the first ``n_frames`` of them."""
    import cv2

    survey = out / "survey"
    names = sorted(p.name for p in (DATA / "images").iterdir())[:n_frames]
    (survey / "images").mkdir(parents=True, exist_ok=True)
    factor = width / 1280
    for name in names:
        target = survey / "images" / name
        if target.exists() or target.is_symlink():
            continue
        if width == 1280:
            target.symlink_to(DATA / "images" / name)
        else:
            image = cv2.imread(str(DATA / "images" / name), cv2.IMREAD_COLOR)
            height = int(round(720 * factor))
            cv2.imwrite(str(target), cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA),
                        [cv2.IMWRITE_JPEG_QUALITY, 95])
    camera = {"width": width, "height": int(round(720 * factor)),
              "mask_rects_px": [[int(round(v * factor)) for v in TIMESTAMP_PX]]}
    (survey / "camera.json").write_text(json.dumps(camera))
    with (DATA / "track.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if r["frame"] in set(names)]
    with (survey / "navigation.csv").open("w") as f:
        f.write("frame,x_m,y_m\n")
        f.writelines(f"{r['frame']},{r['x_m']},{r['z_m']}\n" for r in rows)
    shutil.copy(DATA / "README.md", survey / "NOTICE.md")
    shutil.copy(DATA / "LICENSE", survey / "LICENSE")
    return survey


def tile_test(folder: Path, names: list[str], mask: np.ndarray | None) -> dict:
    """The tile test of the module docstring on the frames of ``folder`` (found by name or stem): the mean over the
    band's pixels (every frame pooled) of each pixel's chromaticity, and the bands' mean luminance."""
    from watergan.io import frame_file, read_image

    sums = {"far": np.zeros(3), "near": np.zeros(3)}
    rgb = {"far": np.zeros(3), "near": np.zeros(3)}
    luminance = {"far": 0.0, "near": 0.0}
    counts = {"far": 0, "near": 0}
    black = 0
    for name in names:
        image = read_image(frame_file(folder, name))
        h, w = image.shape[:2]
        scene = mask if mask is not None else np.ones((h, w), bool)
        black += int(((image <= 0).all(axis=2) & scene).sum())
        columns = slice(int(w * (1 - MIDDLE) / 2), int(w * (1 + MIDDLE) / 2))
        for band, (top, bottom) in (("far", FAR_ROWS), ("near", NEAR_ROWS)):
            rows = slice(int(h * top), int(h * bottom))
            pixels = image[rows, columns][scene[rows, columns]]
            sums[band] += (pixels / np.maximum(pixels.sum(1, keepdims=True), 1e-6)).sum(0)
            rgb[band] += pixels.sum(0)
            luminance[band] += float((pixels @ [0.2126, 0.7152, 0.0722]).sum())
            counts[band] += len(pixels)
    chroma = {b: sums[b] / max(counts[b], 1) for b in sums}
    mean_y = {b: luminance[b] / max(counts[b], 1) for b in sums}
    of_mean = {b: rgb[b] / rgb[b].sum() for b in rgb}
    return {"tile_chromaticity_distance": round(float(np.linalg.norm(chroma["far"] - chroma["near"])), 5),
            "tile_chromaticity_distance_of_mean": round(float(np.linalg.norm(of_mean["far"] - of_mean["near"])), 5),
            "tile_luminance_ratio": round(mean_y["far"] / mean_y["near"], 4),
            "tile_far_chromaticity": np.round(chroma["far"], 5).tolist(),
            "tile_near_chromaticity": np.round(chroma["near"], 5).tolist(), "black_pixels": black}


def method_folders(ws) -> dict[str, Path]:
    """Each method's corrected frames in the workspace (the raw frames the workspace's undistorted ones)."""
    folders = {"raw": ws.stage_dir("survey") / "images"}
    correct = ws.result("correct")
    if correct is not None:
        if correct.physics_images:
            folders["physics"] = ws.path(correct.physics_images)
        if correct.images:
            folders["restorer"] = ws.path(correct.images)
    evaluate = ws.result("eval")
    if evaluate is not None:
        for method in ("gray_world", "seathru"):
            folders[method] = ws.path(evaluate.baselines_dir) / method
    return {m: f for m, f in folders.items() if f.is_dir()}


def label_warp(ws):
    """The labels' masks into the workspace's undistorted frames (:func:`eval.objects.undistortion_warp` of the
    survey stage's camera.json); None without a lens."""
    from eval.objects import undistortion_warp

    return undistortion_warp(json.loads((ws.folder("survey") / "camera.json").read_text()))


def range_maps(ws, names: list[str]):
    """Each frame's range (metres, NaN: none) from the range stage's maps; None without the range stage."""
    from eval.objects import range_frames

    ranges = ws.result("range")
    return None if ranges is None else range_frames(ws.path(ranges.range_dir), names)


def object_constancy(ws, folders: dict[str, Path], names: list[str], labels_path: Path = OBJECT_LABELS) -> dict:
    """Per method of ``folders``, :func:`eval.objects.measure_objects` of the labelled objects in its frames, with the
    water stage's ranges: ``{method: {"objects": {...}, "objects_median_spread": S}}``."""
    from eval.objects import LazyFrames, load_object_labels, measure_objects, object_pixels
    from watergan.io import frame_file, read_image

    data_frames = sorted(p.name for p in (DATA / "images").iterdir()) if (DATA / "images").is_dir() else None
    labels = load_object_labels(labels_path, data_frames)  # a survey of fewer frames measures the labels it holds
    ranges = range_maps(ws, names)
    warp = label_warp(ws)
    pixels: dict[tuple, dict] = {}
    out = {}
    for method, folder in folders.items():
        images = LazyFrames(names, lambda name, folder=folder: read_image(frame_file(folder, name)))
        first = next((f for f in labels.frames() if f in images), None)
        if first is None:
            continue
        shape = images[first].shape[:2]
        if shape not in pixels:
            pixels[shape] = object_pixels(labels, shape, names, warp)
        out[method] = measure_objects(images, labels, pixels[shape], ranges)
    return out


def consistency_by_patch(ws, folders: dict[str, Path], patches=PATCHES_PX) -> dict[str, dict[str, list]]:
    """Table II (:func:`eval.colour.consistency`, at least 3 views) of ``folders`` at each patch size, the views the
    physics correction gave no measured range left out of all as the eval stage does: method -> patch -> R, G, B."""
    from eval.colour import consistency, observation_colours
    from eval.tracks import Tracks
    from pipeline.evaluate import measured_views

    tracks = Tracks.load(ws.path(ws.result("sfm").tracks))
    correct = ws.result("correct")
    unmeasured = None
    if "physics" in folders and correct is not None and correct.physics_mask and ws.path(correct.physics_mask).is_dir():
        unmeasured = ~measured_views(tracks, ws.path(correct.physics_mask))
    out: dict[str, dict[str, list]] = {m: {} for m in folders}
    for patch in patches:
        colours = {m: observation_colours(tracks, f, patch) for m, f in folders.items()}
        if unmeasured is not None:
            for values in colours.values():
                values[unmeasured] = np.nan
        result = consistency(tracks, folders, patch, 3, colours=colours)
        for method, score in result.scores.items():
            out[method][str(patch)] = [round(v, 8) for v in score.variance]
    return out


def objects_summary(per_method: dict, labels_path: Path = OBJECT_LABELS) -> dict:
    """The labels' counts and each method's ``objects_median_spread`` over raw's, and over raw's per object."""
    from eval.objects import load_object_labels

    labels = load_object_labels(labels_path)
    raw = per_method.get("raw", {})
    summary = {"labels": str(labels_path.relative_to(ROOT)), "n_objects": len(labels.objects),
               "n_object_frames": labels.n_object_frames(),
               "objects_median_spread": {m: e["objects_median_spread"] for m, e in per_method.items()}}
    if raw.get("objects_median_spread"):
        summary["median_spread_over_raw"] = {m: round(e["objects_median_spread"] / raw["objects_median_spread"], 4)
                                             for m, e in per_method.items() if e["objects_median_spread"] is not None}
        summary["spread_over_raw_per_object"] = {
            m: {name: round(o["object_chromaticity_spread"] / raw["objects"][name]["object_chromaticity_spread"], 4)
                for name, o in e["objects"].items()
                if o["object_chromaticity_spread"] is not None and raw["objects"].get(name, {}).get(
                    "object_chromaticity_spread")}
            for m, e in per_method.items()}
    return summary


def _interval(p) -> dict:
    """{"value", "low", "high"} of a :class:`watergan.water_record.ParamInterval`; a parameter the water held (not
    fitted) has its value as both ends."""
    held = not p.fitted
    return {"value": p.value, "low": p.value if held and p.low is None else p.low,
            "high": p.value if held and p.high is None else p.high}


def dark_veil(ws, raw_objects: dict) -> dict | None:
    """``dark_object_veil``: the dark objects' raw radiance per frame beside the water's additive term at their
    ranges (:func:`eval.objects.dark_object_veil`, from water.json's B_inf, beta and gain k), and beside it the
    record's own veil at the views' median range with its joint interval (``record_veil``, without k); None without
    the water's backscatter."""
    from eval.objects import dark_object_veil
    from watergan.water_record import read_water

    water = ws.result("water")
    if water is None or not raw_objects:
        return None
    record = read_water(ws.path(water.water_json))
    params = record.params
    if "backscatter.b_inf" not in params or "backscatter.beta_per_m" not in params:
        return None
    gain = _interval(params["gain.k"]) if "gain.k" in params else None
    out = dark_object_veil(raw_objects, _interval(params["backscatter.b_inf"]),
                           _interval(params["backscatter.beta_per_m"]), gain)
    out.update(gain_k=gain, record_veil=record.veil)
    return out


def floor_navigation(points: np.ndarray, world_from_cam: np.ndarray, names: list[str]
                     ) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """Each camera's altitude over the model's floor plane (:func:`pipeline.scale.floor_plane` of the sparse
    ``points``; model units, metres in a scaled model) and the floor's down direction in its camera frame,
    g = R^T (-n) (``world_from_cam`` (N,4,4): x_world = R x_cam + t; n the floor's normal towards the cameras), by
    the stems of ``names``: the navigation a survey without an altimeter leaves to the model."""
    from pipeline.scale import floor_plane

    centres = world_from_cam[:, :3, 3]
    n, d = floor_plane(points, centres)
    altitude = centres @ n - d
    down = np.einsum("kji,j->ki", world_from_cam[:, :3, :3], -n)
    stems = [Path(name).stem for name in names]
    return ({s: float(a) for s, a in zip(stems, altitude, strict=True)},
            {s: g for s, g in zip(stems, down, strict=True)})


def relief_summary(metrics: dict) -> dict:
    """The site depth net against the dense range from a held-out comparison's ``metrics.json``
    (:func:`eval.depth.compare_depth_folders`): ``depth_relief_ratio`` = the net's RMSE on relief pixels over the
    plane's (``plane``: the one the comparison divides by), the same over all pixels, each RMSE, the best plane's
    (a lower bound for any plane) and how many frames and what share of pixels are relief."""
    sources = metrics.get("sources", {})
    plane = metrics.get("ratio_to", "")

    def rmse(name: str, part: str):
        entry = (sources.get(name) or {}).get(part)
        return None if not entry else entry["rmse_m"]

    def ratio(a, b):
        return None if a is None or not b else round(a / b, 4)

    net_relief, plane_relief = rmse("depth net", "relief"), rmse(plane, "relief")
    net_all, plane_all = rmse("depth net", "all"), rmse(plane, "all")
    return {"depth_relief_ratio": ratio(net_relief, plane_relief), "all_rmse_ratio": ratio(net_all, plane_all),
            "plane": plane, "net_relief_rmse_m": net_relief, "plane_relief_rmse_m": plane_relief,
            "net_all_rmse_m": net_all, "plane_all_rmse_m": plane_all,
            "best_plane_relief_rmse_m": rmse("best plane", "relief"),
            "relief_fraction": metrics.get("relief_fraction"), "held_out_frames": len(metrics.get("per_image", {}))}


def depth_relief(ws, out: Path) -> dict:
    """``depth_relief``: the site depth net on held-out frames against the dense range, beside the plane
    (:func:`relief_summary`). From the restorer stage's own comparison where it made one; else (a survey without an
    altimeter, as the pool's) the net trained here as the stage trains it (:func:`pipeline.site_depth.fit_site_depth`,
    the stage's default steps, into ``out/site_depth``), its flat seafloor the model's floor at each camera's height
    and attitude (:func:`floor_navigation`)."""
    from eval.depth import Navigation
    from eval.tracks import Tracks
    from pipeline.gan import RestorerStage
    from pipeline.site_depth import fit_site_depth
    from watergan.train_site_depth import SiteDepthConfig

    restorer = ws.result("restorer")
    site = getattr(restorer, "site_depth", {}) if restorer is not None else {}
    if site.get("metrics"):
        metrics, source = ws.folder("restorer") / site["metrics"], "the restorer stage's held-out comparison"
        record = site
    else:
        survey = ws.stage_dir("survey")
        nav = Navigation.from_survey(survey / "survey.json")
        if nav is None or not (survey / "survey.json").is_file() or ws.result("dense") is None:
            return {"depth_relief_ratio": None, "stage_why": site.get("why"),
                    "why": "no camera.json, survey.json or dense depth in the workspace"}
        tracks = Tracks.load(ws.path(ws.result("sfm").tracks))
        names = [str(n) for n, r in zip(tracks.image_names, tracks.registered, strict=True) if r]
        altitude, down = floor_navigation(tracks.xyz, tracks.world_from_cam[tracks.registered], names)
        folder = out / "site_depth"
        record = fit_site_depth(ws, SiteDepthConfig(steps=RestorerStage().site_depth_steps), folder, False,
                                Navigation(nav.camera, altitude, down))
        if not record.get("metrics"):
            return {"depth_relief_ratio": None, "stage_why": site.get("why"), "why": record.get("why")}
        metrics = folder / record["metrics"]
        source = f"trained by bench_real into {folder}, the flat seafloor the model's floor at each camera's height"
    return {**relief_summary(json.loads(metrics.read_text())), "source": source, "why": record.get("why"),
            "stage_why": site.get("why")}


def model_height_halves(ws) -> dict:
    """The crawler's camera rides at a constant height over the floor: :func:`pipeline.scale.height_halves` of the
    model's camera heights over its floor plane, the model's own scale drift between the halves, read without the
    track."""
    from eval.tracks import Tracks
    from pipeline.scale import camera_heights, height_halves

    tracks = Tracks.load(ws.path(ws.result("sfm").tracks))
    return height_halves(camera_heights(tracks.xyz, tracks.world_from_cam[tracks.registered, :3, 3]))


def collect(ws, run_summary: dict, out: Path) -> dict:
    """Everything real.json holds (see the module docstring) from a finished workspace; ``out``: the working folder
    (the site depth net trained here goes into it)."""
    from watergan.io import read_scene_mask
    from watergan.survey_files import image_files
    from watergan.water_record import read_water

    survey, sfm = ws.result("survey"), ws.result("sfm")
    calibration = survey.self_calibration
    figures = {
        "registered": sfm.n_registered, "frames": sfm.n_images,
        "reprojection_px": round(sfm.mean_reprojection_error_px, 4),
        "self_calibration": calibration,
        "focal_halves_pct": calibration.get("halves", {}).get("focal_diff_pct"),
        "lens": survey.undistorted,
        "scale": {"method": sfm.scale_method, "factor": sfm.scale_factor, "spread": sfm.scale_spread,
                  **sfm.scale_detail},
        "scale_heldout_pct": sfm.scale_detail.get("halves", {}).get("heldout_pct"),
        "scale_height_halves_pct": model_height_halves(ws)["heldout_pct"],
        "sfm_lens_k1": sfm.lens_k1,
    }
    water = ws.result("water")
    if water is not None:
        data = read_water(ws.path(water.water_json))
        figures["water"] = {k: {f: getattr(v, f) for f in ("value", "low", "high", "on_bound", "units")}
                            for k, v in data.params.items() if k.split(".")[0] in ("attenuation", "backscatter")}
        figures["water"]["veil"] = data.veil
    mask = read_scene_mask(ws.path(survey.scene_mask)) if survey.scene_mask else None
    names = image_files(ws.stage_dir("survey") / "images")
    evaluate = ws.result("eval")
    consistency = evaluate.consistency_variance if evaluate is not None else {}
    methods = {}
    folders = method_folders(ws)
    for method, folder in folders.items():
        entry = tile_test(folder, names, mask)
        key = {"physics": "physics", "restorer": "ours"}.get(method, method)
        if key in consistency:
            entry["consistency"] = [float(v) for v in consistency[key]]
        methods[method] = entry
    measured = {m: folders[m] for m in OBJECT_METHODS if m in folders}
    for method, by_patch in consistency_by_patch(ws, measured).items():
        methods[method]["consistency_by_patch_px"] = by_patch
    per_object = object_constancy(ws, measured, names)
    for method, entry in per_object.items():
        methods[method].update(entry)
    figures["methods"] = methods
    figures["objects"] = objects_summary(per_object)
    figures["dark_object_veil"] = dark_veil(ws, per_object.get("raw", {}).get("objects", {}))
    figures["depth_relief"] = depth_relief(ws, out)
    figures["depth_relief_ratio"] = figures["depth_relief"]["depth_relief_ratio"]
    figures["seconds"] = {t["stage"]: t["seconds"] for t in run_summary.get("stages", [])}
    figures["seconds"]["total"] = run_summary.get("seconds")
    return figures


def targets(figures: dict) -> dict:
    """The issue's targets, as booleans (None where the run did not reach the figure)."""
    raw = figures["methods"].get("raw", {})
    def within(value, limit):
        return None if value is None else value <= limit

    out = {"registered_all": figures["registered"] == figures["frames"],
           "reprojection_under_1px": figures["reprojection_px"] < 1.0,
           "focal_halves_within_3pct": within(figures["focal_halves_pct"], 3),
           "scale_heldout_within_5pct": within(figures["scale_heldout_pct"], 5)}
    for method in ("physics", "restorer"):
        entry = figures["methods"].get(method)
        if entry is None or not raw:
            continue
        out[f"{method}_chromaticity_half_of_raw"] = \
            entry["tile_chromaticity_distance"] <= 0.5 * raw["tile_chromaticity_distance"]
        out[f"{method}_luminance_0p8_1p25"] = 0.8 <= entry["tile_luminance_ratio"] <= 1.25
        if "consistency" in entry and "consistency" in raw:
            out[f"{method}_consistency_below_raw"] = all(a < b for a, b in zip(entry["consistency"],
                                                                                 raw["consistency"], strict=True))
        out[f"{method}_no_black"] = entry["black_pixels"] == 0
        spread, raw_spread = entry.get("objects_median_spread"), raw.get("objects_median_spread")
        if spread is not None and raw_spread:
            out[f"{method}_objects_spread_half_of_raw"] = spread <= 0.5 * raw_spread
            per_object = figures.get("objects", {}).get("spread_over_raw_per_object", {}).get(method, {})
            out[f"{method}_objects_below_raw_every_object"] = bool(per_object) and all(v < 1 for v in
                                                                                       per_object.values())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="/tmp/bench_real", help="working folder (survey and workspace)")
    parser.add_argument("--width", type=int, default=1280, help="frame width (1280: the data's own size)")
    parser.add_argument("--frames", type=int, default=80, help="the first N frames")
    parser.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "real.json"))
    parser.add_argument("--measure-only", action="store_true",
                        help="skip the run: measure the finished workspace OUT/ws again")
    args, extra = parser.parse_known_args()
    from eval.objects import chromaticity_figure
    from pipeline.workspace import Workspace

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    out = Path(args.out)
    survey = prepare_survey(out, args.width, args.frames)
    ws_dir = out / "ws"
    command = [sys.executable, "-m", "pipeline.cli", "run", str(survey), "--workspace", str(ws_dir), *extra]
    if not args.measure_only:
        print("$ " + " ".join(command[2:]), flush=True)
        subprocess.run(command, check=True, cwd=ROOT)
    peak_gib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 2**20
    ws = Workspace(ws_dir)
    shutil.copy(survey / "NOTICE.md", ws_dir / "NOTICE.md")
    figures = collect(ws, json.loads((ws_dir / "run_summary.json").read_text()), out)
    figures["peak_memory_gib"] = None if args.measure_only else round(peak_gib, 2)
    figures["targets"] = targets(figures)
    figures["command"] = "benchmarks/bench_real.py " + " ".join(sys.argv[1:])
    figures["commit"] = commit
    figures["notice"] = ("Frames: SUBVO dataset (A. Neyestani et al., IEEE I2MTC 2025), CC BY 4.0, "
                         "github.com/A8neyestani/SUBVO; see ../shared/data/subvo-pool/README.md")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(figures, indent=1) + "\n")
    figure = Path(args.json).parent / f"{Path(args.json).stem}_objects.png"
    chromaticity_figure({m: e["objects"] for m, e in figures["methods"].items() if "objects" in e}, figure,
                        note="Frames: SUBVO dataset (A. Neyestani et al., IEEE I2MTC 2025), CC BY 4.0, "
                             "github.com/A8neyestani/SUBVO; labels: benchmarks/data/subvo_objects.json")
    print(json.dumps({k: figures[k] for k in ("registered", "frames", "reprojection_px", "focal_halves_pct",
                                              "scale_heldout_pct", "targets")}, indent=1))
    for method, entry in figures["methods"].items():
        print(f"{method:10} tile distance {entry['tile_chromaticity_distance']:.4f}  far/near "
              f"{entry['tile_luminance_ratio']:.3f}  consistency {entry.get('consistency')}  "
              f"black {entry['black_pixels']}  objects' median spread {entry.get('objects_median_spread')}")
    veil = figures["dark_object_veil"] or {}
    print(f"dark objects inside the additive term's interval: {veil.get('inside_fraction')} of channel-frames; "
          f"site depth net over the plane on relief pixels: {figures['depth_relief_ratio']} "
          f"({figures['depth_relief'].get('why')})")


if __name__ == "__main__":
    main()
