"""The site depth net: a factor on the flat seafloor's depth, learned from the survey's own range, and taken by
monocular correction only where its record says it beat the flat seafloor."""

import json

import cv2
import numpy as np
import pytest
import torch

from watergan.errors import UserInputError
from watergan.formation.inverse import flat_floor_range
from watergan.nets.site_depth import SiteDepthNet
from watergan.restore_folder import correct_folder
from watergan.train_site_depth import (
    SiteDepthConfig,
    SiteFrame,
    load_site_depth,
    save_site_depth,
    split,
    train_site_depth,
)


def _frames(n=8, h=48, w=64, seed=0):
    """Frames over a floor 2 m below whose mounds are brighter the nearer they are: the image tells the depth."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    frames = []
    for k in range(n):
        cy, cx = rng.uniform(12, h - 12), rng.uniform(12, w - 12)
        factor = np.exp(-0.4 * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / 80.0))  # z / z_floor, 0.67 .. 1
        image = np.repeat((0.2 + 1.5 * (1 - factor))[..., None], 3, -1).astype(np.float32)
        floor = np.full((h, w), 2.0)
        frames.append(SiteFrame(f"{k:02d}.png", image, floor, floor * factor))
    return frames


def test_an_untrained_net_is_near_the_flat_seafloor_and_training_learns_what_the_image_tells():
    frames = _frames()
    start = SiteDepthNet(scale=4).depth(frames[0].image, frames[0].floor_z)
    np.testing.assert_allclose(start, frames[0].floor_z, rtol=0.01)
    assert split([f.name for f in frames], 4) == ([f.name for k, f in enumerate(frames) if k % 4 != 2],
                                                   ["02.png", "06.png"])
    torch.manual_seed(0)
    net, record = train_site_depth(frames, SiteDepthConfig(steps=60, batch=4, lr=3e-3, scale=4), progress=False)
    assert record["held_out"] == ["02.png", "06.png"] and len(record["train"]) == 6
    for f in frames:
        if f.name in record["held_out"]:  # frames it never saw: closer to the mound's depth than the floor is
            err_net = np.sqrt(np.mean((net.depth(f.image, f.floor_z) - f.ref_z) ** 2))
            err_floor = np.sqrt(np.mean((f.floor_z - f.ref_z) ** 2))
            assert err_net < 0.6 * err_floor, (err_net, err_floor)
    with pytest.raises(UserInputError, match="at least two frames with range"):
        train_site_depth([SiteFrame(f.name, f.image, f.floor_z, None) for f in frames], progress=False)


def test_monocular_correction_takes_the_site_net_only_where_its_record_says_it_beat_the_floor(tmp_path):
    """A net whose factor is 2 everywhere: with ``use`` its monocular correction is the RGB-D correction at twice the
    flat seafloor's range, and the result names it; without ``use`` the flat seafloor's, and the result says why."""
    from test_correct import save_model, write_images

    from watergan.data import PinholeIntrinsics
    from watergan.io import write_depth_png

    model = save_model(tmp_path / "model", range_input=True)
    images = write_images(tmp_path / "survey" / "images")
    camera = PinholeIntrinsics(30.0, 30.0, 19.5, 15.5, 40, 32)
    (tmp_path / "survey" / "camera.json").write_text(json.dumps(camera.to_json()))
    (tmp_path / "survey" / "survey.json").write_text(json.dumps({"frames": ["a.png", "b.png"],
                                                                  "nav_altitude_m": [1.5, 3.0]}))
    net = SiteDepthNet(widths=(4, 4), scale=4)
    with torch.no_grad():
        net.out.bias.fill_(np.log(2.0))
    save_site_depth(model, net, {"use": True, "why": "it beat the flat seafloor"})
    site = correct_folder(model, images, tmp_path / "site", progress=False, mode="monocular")
    assert (site.range_source, site.range_why) == ("site depth net", "it beat the flat seafloor")
    doubled = tmp_path / "doubled"
    for name, altitude_m in (("a.png", 1.5), ("b.png", 3.0)):
        write_depth_png(doubled / name, 2 * flat_floor_range(altitude_m, camera.K, 32, 40))
    correct_folder(model, images, tmp_path / "rgbd", progress=False, range_dir=doubled)
    for name in ("a.png", "b.png"):
        m, r = (cv2.imread(str(tmp_path / d / "images" / name)).astype(int) for d in ("site", "rgbd"))
        assert np.abs(m - r).max() <= 1

    save_site_depth(model, net, {"use": False, "why": "a plane does better"})
    assert load_site_depth(model)[0] is None
    floor = correct_folder(model, images, tmp_path / "floor", progress=False, mode="monocular")
    assert (floor.range_source, floor.range_why) == ("flat seafloor", "a plane does better")
    assert json.loads((tmp_path / "floor" / "summary.json").read_text())["range_source"] == "flat seafloor"
    a_site, a_floor = (cv2.imread(str(tmp_path / d / "images" / "a.png")).astype(int) for d in ("site", "floor"))
    assert np.abs(a_site - a_floor).max() > 2
