"""Real footage: a subset of the pool crawler's survey (``../shared/data/subvo-pool``) as a user of that camera gives
it, only the image size known, the burned-in timestamp masked, and the crawler's track: SfM calibrates the camera, the
track scales the model, the forward-moving frames get their depth from the sparse points, the water is fitted and
the physics correction writes every pixel. Frames: SUBVO dataset (A. Neyestani et al., IEEE I2MTC 2025), CC BY 4.0;
see that folder's README."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_real import DATA, prepare_survey, tile_test  # noqa: E402

from pipeline.workspace import Workspace  # noqa: E402

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not (DATA / "images").is_dir(), reason=f"the real footage is not at {DATA}")]

#: The subset: 20 frames from the end of the turn into the second straight leg, at 640 px. Shorter or smaller windows
#: elsewhere register too few frames to calibrate, or give a lens the plausibility check refuses (benchmarks/RESULTS.md,
#: "Real footage"); the whole survey at full size calibrates.
FIRST, COUNT, WIDTH = 56, 20, 640


def test_the_pool_subset_runs_from_the_image_size_alone(tmp_path):
    from eval.observations import DenseMeasureConfig
    from eval.tracks import Tracks
    from eval.water import ALTERNATIVE_PRESETS
    from pipeline.correct import CorrectStage
    from pipeline.dense import DenseConfig
    from pipeline.range import RangeConfig
    from pipeline.scale import camera_heights
    from pipeline.sfm import SfmConfig
    from pipeline.survey import SurveyConfig
    from pipeline.water import WaterStage
    from watergan.io import read_image, read_png, read_scene_mask
    from watergan.survey_files import image_files
    from watergan.water_record import read_water

    survey = prepare_survey(tmp_path, WIDTH, FIRST + COUNT)
    for name in sorted(p.name for p in (survey / "images").iterdir())[:FIRST]:
        (survey / "images" / name).unlink()
    ws = Workspace(tmp_path / "ws")
    calibrated = ws.run("survey", SurveyConfig(survey_dir=str(survey), progress=False))
    camera = json.loads((ws.folder("survey") / "camera.json").read_text())
    focal_full_size = 1236.0 * WIDTH / 1280  # the whole survey's calibration at 1280 px (benchmarks/results/real.json)
    assert calibrated.self_calibration["registered"] == COUNT
    assert calibrated.rgbd_dir == "" and not list(ws.folder("survey").glob("*rgbd*"))  # WaterGAN's set: its own stage's
    assert camera["fx"] == pytest.approx(focal_full_size, rel=0.1)
    assert -0.45 < calibrated.undistorted["k1"] < -0.2  # a wide lens's barrel distortion
    mask = read_scene_mask(ws.path(calibrated.scene_mask))
    assert not mask[:5, :100].any() and mask[200:].all()  # the timestamp is out, the floor in

    sfm = ws.run("sfm", SfmConfig(progress=False))
    assert sfm.n_registered == COUNT and sfm.mean_reprojection_error_px < 1.0
    assert sfm.scale_method == "track" and sfm.scale_detail["residual_m"] < 0.1
    tracks = Tracks.load(ws.path(sfm.tracks))
    centres = tracks.world_from_cam[tracks.registered, :3, 3]
    height_m = float(np.median(camera_heights(tracks.xyz, centres)))
    assert 0.1 < height_m < 0.6  # the crawler's camera, "a few tens of cm" over the floor

    dense = ws.run("dense", DenseConfig(progress=False))
    assert sum(p == "sparse" for p in dense.pairs.values()) >= COUNT // 2  # forward motion: the sparse points' depth
    assert dense.mean_coverage > 0.3

    # a bounded table and no alternatives (the bootstrap's intervals alone) keep the test short: this subset asks
    # that every stage runs from the image size alone; the pool's water, its alternatives and intervals are
    # bench_real's, on the whole survey (benchmarks/RESULTS/cameras.md)
    ws.run("range", RangeConfig(progress=False))
    water = ws.run("water", WaterStage(progress=False, measure=DenseMeasureConfig(max_points=4000),
                                       correction_grid=None, alternatives=ALTERNATIVE_PRESETS["none"]))
    eta = read_water(ws.path(water.water_json)).params["attenuation.eta_per_m"]
    value, low, high = (np.asarray(getattr(eta, k)) for k in ("value", "low", "high"))
    assert np.all(np.isfinite(value) & (value > 0)) and np.all((low <= value) & (value <= high))

    corrected = ws.run("correct", CorrectStage(progress=False))
    names = image_files(ws.folder("survey") / "images")
    physics = tile_test(ws.path(corrected.physics_images), names, mask)
    range_from = read_png(ws.path(corrected.physics) / "range_from" / f"{Path(names[0]).stem}.png")
    # every scene pixel got a range
    assert np.isin(range_from[mask], [0, 1, 2, 4]).all() and (range_from[~mask] == 3).all()
    # a pixel darker than the veil keeps a hundredth of its signal: black only where that rounds to 0 (dark pixels)
    assert physics["black_pixels"] < 1e-4 * mask.sum() * len(names)
    raw = read_image(ws.folder("survey") / "images" / names[0])
    out = read_image(Path(ws.path(corrected.physics_images)) / f"{Path(names[0]).stem}.png")
    assert np.abs(out[~mask] - raw[~mask]).max() < 2 / 255  # the timestamp passed through
