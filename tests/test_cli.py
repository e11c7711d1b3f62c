"""The console script: `effects`, `simulate` and their error messages."""

import json
import subprocess
import sys


def watergan(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *args], capture_output=True, text=True, cwd=cwd)


def test_effects_lists_all_twenty_with_parameters():
    out = watergan("effects")
    assert out.returncode == 0
    assert out.stdout.startswith("20 registered effects")
    for name in ("attenuation", "backscatter_conv", "vignetting_offcentre", "marine_snow", "image_field", "frame_gain",
                 "image_grid", "tone_curve", "black_level", "specular_gloss"):
        assert f"\n{name}: " in out.stdout
    assert "eta_per_m = (0.34, 0.24, 0.33) in [0, 5] 1/m" in out.stdout


def test_simulate_tiny_with_hidden_effect(tmp_path):
    out = watergan("simulate", "--preset", "tiny", "--hidden", "vignetting_offcentre", "--seed", "1",
                   "--out", str(tmp_path / "s"))
    assert out.returncode == 0, out.stderr
    assert "simulated 6 frames of 160x120" in out.stdout
    effects = json.loads((tmp_path / "s/truth/effects.json").read_text())
    assert [e["name"] for e in effects["hidden"]] == ["vignetting_offcentre"]
    assert "vignetting_offcentre" not in [e["name"] for e in effects["visible"]]
    assert len(list((tmp_path / "s/images").glob("*.png"))) == 6


def test_unknown_hidden_effect_fails_before_writing(tmp_path):
    out = watergan("simulate", "--preset", "tiny", "--hidden", "vignetting_offcenter", "--out", str(tmp_path / "s"))
    assert out.returncode == 2
    assert "unknown effect 'vignetting_offcenter'" in out.stderr and "vignetting_offcentre" in out.stderr
    assert "Traceback" not in out.stderr
    assert not (tmp_path / "s").exists()


def test_existing_output_is_not_overwritten(tmp_path):
    target = tmp_path / "mine"
    target.mkdir()
    (target / "notes.txt").write_text("my data")
    out = watergan("simulate", "--preset", "tiny", "--out", str(target))
    assert out.returncode == 2 and "--force" in out.stderr
    assert (target / "notes.txt").read_text() == "my data"
