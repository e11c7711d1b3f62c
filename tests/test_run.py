"""`watergan run` / `watergan demo`: every stage end to end on a small simulated survey, resume,
--force, the options file, and bad survey folders refused before any training starts."""

import dataclasses
import json
import shutil
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from pipeline.run import (
    RunOptions,
    load_options_file,
    run_all,
    run_options,
    stage_config,
)
from pipeline.stages import STAGES, stage_folder
from pipeline.survey import SurveyConfig, SurveyResult, check_survey
from watergan.errors import UserInputError

FAST = ["--gan-budget-min", "0.1", "--restorer-budget-min", "0.1", "--restorer-site-depth-steps", "20",
        "--restorer-stage1-min-iterations", "0", "--restorer-stage2-min-iterations", "0", "--water-fit-bootstrap", "5",
        "--diagnose-measure-n-points", "200",
        "--diagnose-candidates", "vignetting_offcentre,sensor_response", "--no-progress"]


def watergan(*args):
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *args], capture_output=True, text=True)


@pytest.mark.slow
def test_demo_end_to_end_resume_and_force(tmp_path, capsys):
    out = tmp_path / "ws"
    first = watergan("demo", "--preset", "small", "--out", str(out), *FAST)
    assert first.returncode == 0, first.stderr[-3000:]
    report = stage_folder(out, "report") / "report.html"
    assert f"report: {report}" in first.stdout
    html = report.read_text()
    assert "<img" in html and "http://" not in html.replace("http://www.w3.org", "")
    summary = json.loads((out / "run_summary.json").read_text())
    assert [s["stage"] for s in summary["stages"]] == ["survey", "sfm", "dense", "range", "water", "gan", "restorer",
                                                       "correct", "eval", "mesh", "diagnose", "report"]
    assert not any(s["skipped"] for s in summary["stages"])
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == [
        s.folder for s in STAGES.values()]  # numbered in run order, nothing loose but the run's summary
    assert sorted(p.name for p in out.iterdir() if p.is_file()) == [".lock", "run_summary.json"]  # the run's lock
    assert len(list((stage_folder(out, "correct") / "restorer" / "images").glob("*.png"))) == 10
    assert len(list((stage_folder(out, "correct") / "physics" / "images").glob("*.png"))) == 10
    correct = json.loads((stage_folder(out, "correct") / "result.json").read_text())["result"]
    assert correct["mesh_images"] in [f"{STAGES['correct'].folder}/{c}/images" for c in ("physics", "restorer")]
    assert (stage_folder(out, "mesh") / "mesh.glb").stat().st_size > 0
    tables = json.loads((stage_folder(out, "eval") / "tables.json").read_text())
    assert "ours" in json.dumps(tables) and tables["ours_mode"] == "rgb-d"  # the survey has range: RGB-D restorer
    assert "physics" in tables["methods"]
    gan = json.loads((stage_folder(out, "gan") / "result.json").read_text())["result"]["train"]
    assert gan["site_water"]["mode"] == "held"
    assert gan["site_water"]["water_json"].endswith(f"{STAGES['water'].folder}/water.json")
    assert len(list((stage_folder(out, "range") / "range").glob("*.png"))) == 10
    diagnosis = json.loads((stage_folder(out, "diagnose") / "result.json").read_text())["result"]
    assert diagnosis["ledger"] == f"{STAGES['diagnose'].folder}/model_ledger.jsonl"
    ledger = [json.loads(line) for line in (out / diagnosis["ledger"]).read_text().splitlines()]
    model = [r for r in ledger if r["kind"] == "model"][-1]
    for key in ("board_ciede2000", "consistency"):  # the ledger records what the corrected frames achieve
        assert {"raw", "physics (range)", "ours (rgb-d)"} <= set(model[key]), model.get(key)

    began = time.perf_counter()
    second = watergan("demo", "--preset", "small", "--out", str(out), *FAST)
    assert second.returncode == 0, second.stderr[-3000:]
    assert time.perf_counter() - began < 30
    assert all(s["skipped"] for s in json.loads((out / "run_summary.json").read_text())["stages"])
    assert second.stdout.count("finished earlier, skipped") == 12

    restorer_mtime = (stage_folder(out, "restorer") / "result.json").stat().st_mtime_ns
    sfm_mtime = (stage_folder(out, "sfm") / "result.json").stat().st_mtime_ns
    forced = watergan("demo", "--preset", "small", "--out", str(out), "--force", "mesh", *FAST)
    assert forced.returncode == 0, forced.stderr[-3000:]
    ran = {s["stage"] for s in json.loads((out / "run_summary.json").read_text())["stages"] if not s["skipped"]}
    assert ran == {"mesh", "report"}  # the mesh and the stage that reads it, nothing before it
    assert (stage_folder(out, "restorer") / "result.json").stat().st_mtime_ns == restorer_mtime
    assert (stage_folder(out, "sfm") / "result.json").stat().st_mtime_ns == sfm_mtime

    # a standalone stage command recognises what `watergan run` wrote: printed, not rerun (in this process: the
    # commands' own start-up is what the subprocesses above test)
    from pipeline.cli import main

    assert main(["sfm", "--workspace", str(out)]) == 0
    assert "registered 10 of 10" in capsys.readouterr().out
    assert (stage_folder(out, "sfm") / "result.json").stat().st_mtime_ns == sfm_mtime
    correct_mtime = (stage_folder(out, "correct") / "result.json").stat().st_mtime_ns
    for command in (["range"], ["gan", "--budget-min", "0.1"],
                    ["restorer", "--budget-min", "0.1", "--site-depth-steps", "20", "--stage1-min-iterations", "0",
                     "--stage2-min-iterations", "0"],
                    ["correct"]):
        assert main([*command, "--workspace", str(out), "--no-progress"]) == 0, command  # as run did them: skipped
    assert (stage_folder(out, "correct") / "result.json").stat().st_mtime_ns == correct_mtime
    capsys.readouterr()
    assert main(["report", "--workspace", str(out), "--force"]) == 0
    assert capsys.readouterr().out.strip() == str(report)

    # a moved workspace is still finished; a stage whose output is gone runs again, and the stages after it
    moved = out.rename(tmp_path / "moved")
    (stage_folder(moved, "report") / "report.html").unlink()
    assert main(["demo", "--preset", "small", "--out", str(moved), *FAST]) == 0
    captured = capsys.readouterr()
    assert captured.out.count("finished earlier, skipped") == 11, captured.out  # all but the report
    assert "report: 1 of its files are gone or cut short since it ran (e.g. 11_report/report.html)" in captured.err
    assert (stage_folder(moved, "report") / "report.html").is_file()


def _survey(root, n=4, size=(48, 64)):
    images = root / "images"
    images.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for k in range(n):
        cv2.imwrite(str(images / f"f{k}.png"), rng.integers(0, 255, (*size, 3), dtype=np.uint8))
    (root / "camera.json").write_text(json.dumps({"fx": 50, "fy": 50, "cx": 32, "cy": 24, "width": 64, "height": 48}))
    return images


def test_good_survey_is_accepted(tmp_path):
    _survey(tmp_path)
    assert check_survey(tmp_path) == {"n_images": 4, "width": 64, "height": 48, "stereo": False, "simulated": False}


@pytest.mark.parametrize("problem, message", [
    ("no_images", "no images/ folder"),
    (r"too_few", r"holds 2 image\(s\)"),
    ("mixed_sizes", "different sizes"),
    ("truncated", "truncated"),
    ("not_an_image", "not a readable"),
    ("right_unpaired", "do not pair"),
    ("no_camera", "no camera.json"),
    ("camera_not_json", r"camera file .*camera.json is not valid JSON"),
    ("camera_bad_value", r"camera file .*camera.json: fx = 'fifty' is not a positive number"),
    ("camera_other_size", r"camera file .*camera.json is for 320x240 images; the images .* are 64x48"),
    ("survey_not_json", r"survey file .*survey.json is not valid JSON"),
    ("survey_bad_altitude", r"survey file .*survey.json: nav_altitude_m is not a positive number for 1 frames "
                            r"\(e.g. f1.png: -2.0\)"),
    ("survey_short_list", r"survey file .*survey.json: 2 nav_depth_m values for 4 frames"),
    ("survey_bad_light", r"survey file .*survey.json: lights\[0\].offset_m = 'left' is not a number"),
    ("survey_missing_frame", r"survey file .*survey.json lists 1 frame\(s\) with no image in .*images \(e.g. f9.png\)"),
    ("log_missing_frame", r"navigation log .*navigation.csv has no row for 1 of the 4 frames \(e.g. f3.png\)"),
    ("log_not_a_number", r"navigation log .*navigation.csv: altitude_m holds 'high', not a number"),
    ("survey_bad_crs", r"survey file .*survey.json: crs = 'UTM 33N' is not \"EPSG:<code>\" of a projected CRS"),
    ("survey_degrees_crs", r"crs = 'EPSG:4326' \(geographic, in degrees\)"),
    ("survey_positions_no_crs", r"survey file .*survey.json gives nav_easting_m and nav_northing_m but no crs: add"),
    ("survey_crs_no_positions", r"survey file .*survey.json gives crs EPSG:32633 but no positions: add nav_easting_m"),
    ("survey_short_positions", r"survey file .*survey.json: 3 nav_northing_m values for 4 frames"),
    ("log_positions_no_crs", r"navigation log .*navigation.csv gives easting_m and northing_m but .*survey.json "
                             r"names no crs"),
])
def test_bad_survey_is_refused_before_training(tmp_path, problem, message):
    survey = tmp_path / "survey"
    images = _survey(survey)
    if problem == "no_images":
        shutil.rmtree(images)
    elif problem == "too_few":
        for p in sorted(images.iterdir())[2:]:
            p.unlink()
    elif problem == "mixed_sizes":
        cv2.imwrite(str(images / "f1.png"), np.zeros((40, 64, 3), np.uint8))
    elif problem == "truncated":
        data = (images / "f2.png").read_bytes()
        (images / "f2.png").write_bytes(data[: len(data) // 2])
    elif problem == "not_an_image":
        (images / "f3.png").write_bytes(b"not a png" + b"IEND\xaeB`\x82")  # ends like a PNG, decodes as none
    elif problem == "right_unpaired":
        (survey / "right").mkdir()
        shutil.copy(images / "f0.png", survey / "right" / "g0.png")
    elif problem == "no_camera":
        (survey / "camera.json").unlink()
    elif problem.startswith("camera_"):
        camera = json.loads((survey / "camera.json").read_text())
        text = {"camera_not_json": json.dumps(camera)[:30],
                "camera_bad_value": json.dumps({**camera, "fx": "fifty"}),
                "camera_other_size": json.dumps({**camera, "width": 320, "height": 240})}[problem]
        (survey / "camera.json").write_text(text)
    elif problem == "log_positions_no_crs":
        (survey / "survey.json").write_text(json.dumps({"nav_depth_m": [10.0] * 4}))
        rows = [f"f{k}.png,2.0,{500000 + k},5000000" for k in range(4)]
        (survey / "navigation.csv").write_text("frame,altitude_m,easting_m,northing_m\n" + "\n".join(rows) + "\n")
    elif problem.startswith("log_"):
        rows = ["f0.png,2.0", "f1.png,2.1", "f2.png,2.2"] + (["f3.png,high"] if problem == "log_not_a_number" else [])
        (survey / "navigation.csv").write_text("frame,altitude_m\n" + "\n".join(rows) + "\n")
    elif problem.startswith("survey_"):
        frames = sorted(p.name for p in images.iterdir())
        good = {"frames": frames, "nav_altitude_m": [2.0] * 4, "nav_depth_m": [10.0] * 4, "lights": []}
        placed = {"nav_easting_m": [500000.0 + k for k in range(4)], "nav_northing_m": [5e6] * 4}
        text = {"survey_not_json": json.dumps(good)[:-20],
                "survey_bad_altitude": json.dumps({**good, "nav_altitude_m": [2.0, -2.0, 2.0, 2.0]}),
                "survey_short_list": json.dumps({**good, "nav_depth_m": [10.0, 10.0]}),
                "survey_bad_light": json.dumps({**good, "lights": [{"offset_m": "left"}]}),
                "survey_missing_frame": json.dumps({**good, "frames": frames[:3] + ["f9.png"]}),
                "survey_bad_crs": json.dumps({**good, **placed, "crs": "UTM 33N"}),
                "survey_degrees_crs": json.dumps({**good, **placed, "crs": "EPSG:4326"}),
                "survey_positions_no_crs": json.dumps({**good, **placed}),
                "survey_crs_no_positions": json.dumps({**good, "crs": "EPSG:32633"}),
                "survey_short_positions": json.dumps({**good, **placed, "crs": "EPSG:32633",
                                                      "nav_northing_m": [5e6] * 3})}[problem]
        (survey / "survey.json").write_text(text)
    before = sorted(p.name for p in survey.rglob("*"))
    with pytest.raises(UserInputError, match=message):
        run_all(RunOptions(survey_dir=str(survey), workspace=str(tmp_path / "ws"), progress=False))
    assert not (stage_folder(tmp_path / "ws", "gan")).exists()  # nothing trained
    assert sorted(p.name for p in survey.rglob("*")) == before  # the user's folder is untouched


def test_cli_bad_survey_is_a_clear_error(tmp_path):
    out = watergan("run", str(tmp_path / "missing"), "--workspace", str(tmp_path / "ws"))
    assert out.returncode == 2
    assert "does not exist" in out.stderr and "Traceback" not in out.stderr


def test_a_survey_file_spoilt_after_the_survey_stage_is_refused_on_the_next_run(tmp_path):
    """The survey stage finished earlier is skipped, but its checks run again before anything trains."""
    from pipeline.workspace import Workspace

    survey = tmp_path / "survey"
    _survey(survey)
    opts = RunOptions(survey_dir=str(survey), workspace=str(tmp_path / "ws"), progress=False)
    Workspace(opts.workspace).run("survey", stage_config("survey", opts))
    (survey / "survey.json").write_text('{"frames": ["f0.png", "f1.png"], "nav_altitude_m": [2.0, ')
    with pytest.raises(UserInputError, match="survey.json is not valid JSON"):
        run_all(opts)
    assert not (stage_folder(tmp_path / "ws", "gan")).exists()


@pytest.mark.parametrize("what", ["survey", "camera", "sfm_board", "eval_board", "toml"])
def test_cli_bad_input_file_is_one_line_naming_it_and_exit_2(tmp_path, what):
    """Each bad input file stops `watergan run` at once: exit 2, one line naming the file, no traceback, no
    training, the user's files unchanged."""
    survey = tmp_path / "survey"
    _survey(survey)
    bad = {"survey": survey / "survey.json", "camera": survey / "camera.json", "sfm_board": tmp_path / "board.json",
           "eval_board": tmp_path / "board.json", "toml": tmp_path / "run.toml"}[what]
    bad.write_text('{"images": {"f0.png": [[1, 2], [3, ' if what != "toml" else "gan_budget_min = [1.5\n")
    options = {"sfm_board": ["--sfm-board-json", str(bad)], "eval_board": ["--eval-board-json", str(bad)],
               "toml": ["--config", str(bad)]}.get(what, [])
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    out = watergan("run", str(survey), "--workspace", str(tmp_path / "ws"), "--no-progress", *options)
    assert out.returncode == 2, out.stderr[-2000:]
    assert len(out.stderr.strip().splitlines()) == 1 and str(bad) in out.stderr, out.stderr
    assert "Traceback" not in out.stderr and not (stage_folder(tmp_path / "ws", "gan")).exists()
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file() and "ws" not in p.parts} == before


def test_options_file_and_unknown_keys(tmp_path):
    good = tmp_path / "run.toml"
    good.write_text('gan_budget_min = 1.5\nadd = ["vignetting_offcentre"]\n')
    assert load_options_file(good) == {"gan_budget_min": 1.5, "add": ("vignetting_offcentre",)}
    bad = tmp_path / "bad.toml"
    bad.write_text("gan_budget = 1\n")
    with pytest.raises(UserInputError, match="unknown option.*gan_budget"):
        load_options_file(bad)


def test_unknown_effect_and_stage_fail_first(tmp_path):
    """An unknown effect name fails when the option is read (file or command line), before anything runs."""
    _survey(tmp_path / "s")
    from pipeline.cli import main
    from watergan.formation import UnknownEffectError

    for key in ("add", "gan_effects", "water_effects", "diagnose_candidates", "diagnose_fit_fixed_effects"):
        with pytest.raises(UnknownEffectError, match="vignetting_x"):
            run_options({"survey_dir": str(tmp_path / "s"), "workspace": str(tmp_path / "ws"), key: "vignetting_x"})
    assert main(["run", str(tmp_path / "s"), "--workspace", str(tmp_path / "ws"), "--add", "vignetting_x"]) == 2
    assert main(["diagnose", str(tmp_path / "s"), "--effects", "attenuation,vignetting_x"]) == 2
    with pytest.raises(UserInputError, match="unknown stage"):
        run_all(RunOptions(survey_dir=str(tmp_path / "s"), workspace=str(tmp_path / "ws"), force=("gann",)))
    assert not (tmp_path / "ws").exists()


def test_survey_stage_links_without_copying(tmp_path):
    from pipeline.survey import run_survey
    from pipeline.workspace import Workspace

    for name in ("a", "b"):
        _survey(tmp_path / name)
        (tmp_path / name / "rgbd" / "rgb").mkdir(parents=True)
    ws = Workspace(tmp_path / "ws")
    run_survey(ws, SurveyConfig(str(tmp_path / "a")))
    assert (ws.folder("survey") / "images").resolve() == (tmp_path / "a" / "images").resolve()
    summary = run_survey(ws, SurveyConfig(str(tmp_path / "b")))  # the workspace moved to another survey
    assert (ws.folder("survey") / "images").resolve() == (tmp_path / "b" / "images").resolve()
    assert summary.rgbd_dir == str((tmp_path / "b" / "rgbd").resolve())
    assert sorted(p.name for p in (tmp_path / "a" / "images").iterdir()) == ["f0.png", "f1.png", "f2.png", "f3.png"]


def test_the_gan_stage_reruns_when_the_rendering_of_the_pairs_changes(tmp_path):
    """The gan stage's configuration holds the paired set's rendering too: another recolouring changes its
    hash (the stage reruns), a progress bar does not."""
    from pipeline.gan import GanStage
    from pipeline.workspace import config_hash
    from watergan.generate import GenerateConfig
    from watergan.train import GanConfig

    train = GanConfig(rgbd_dir=tmp_path / "rgbd", underwater_dir=tmp_path / "images", out_dir=tmp_path / "model")
    pairs = GenerateConfig(model_dir=tmp_path / "model", rgbd_dir=tmp_path / "rgbd", out_dir=tmp_path / "generated")
    base = config_hash(GanStage(train, pairs))
    assert config_hash(GanStage(train, dataclasses.replace(pairs, recolour_fraction=0.0))) != base
    assert config_hash(GanStage(train, dataclasses.replace(pairs, progress=False))) == base


def test_a_standalone_sfm_is_what_run_would_do(tmp_path):
    """`watergan sfm --workspace W --survey S` writes the record `watergan run S --workspace W` takes as done:
    the same configuration on the same upstream (the survey stage), so run skips sfm."""
    from eval.synth import make_config, simulate_survey
    from pipeline.workspace import Workspace

    survey, ws = tmp_path / "survey", tmp_path / "ws"
    simulate_survey(survey, make_config("small"), force=True)
    out = watergan("sfm", "--workspace", str(ws), "--survey", str(survey))
    assert out.returncode == 0 and "registered" in out.stdout, out.stderr[-3000:]
    sfm_record = (stage_folder(ws, "sfm") / "result.json").read_text()

    workspace = Workspace(ws)
    opts = run_options({"survey_dir": str(survey), "workspace": str(ws), "progress": False})
    workspace.run("survey", stage_config("survey", opts))  # as run_all does
    assert workspace.is_done("sfm", stage_config("sfm", opts))
    assert (stage_folder(ws, "sfm") / "result.json").read_text() == sfm_record
    other = run_options({"survey_dir": str(survey), "workspace": str(ws), "sfm_matching": "exhaustive"})
    assert not workspace.is_done("sfm", stage_config("sfm", other))


def test_run_sets_any_stage_option_from_the_command_line_or_a_file(tmp_path):
    from pipeline.cli import build_parser
    from pipeline.cli_run import _options
    from pipeline.workspace import Workspace

    toml = tmp_path / "run.toml"
    toml.write_text('restorer_head = "direct"\nadd = ["vignetting_offcentre"]\ngan_budget_min = 1.5\n')
    args = build_parser().parse_args(["run", "S", "--workspace", str(tmp_path / "ws"), "--config", str(toml),
                                      "--restorer-widths", "paper", "--no-restorer-skip", "--gan-budget-min", "2",
                                      "--diagnose-effects", "attenuation,backscatter", "--add", "gain"])
    opts = _options(args, "S", str(tmp_path / "ws"))
    assert opts.add == ("gain",)  # the command line wins over the file
    assert opts.stages["restorer"] == {("train", "head"): "direct", ("train", "widths"): "paper",
                                       ("train", "skip"): False}
    assert opts.stages["gan"] == {("budget_min",): 2.0}
    # the stages take what the common options set from their configuration, the rest from the workspace
    from pipeline.gan import gan_configs, restorer_config

    ws = Workspace(tmp_path / "ws")
    ws.save("survey", SurveyConfig("S"), SurveyResult(n_images=3, width=8, height=6, stereo=False, simulated=False,
                                                      rgbd_dir=str(tmp_path), survey_dir="S", navigation=True))
    diagnose = stage_config("diagnose", opts)
    assert diagnose.effects == ("attenuation", "backscatter") and diagnose.add == ("gain",)
    assert stage_config("water", opts).add == ("gain",) and stage_config("gan", opts).add == ("gain",)
    with pytest.raises(UserInputError, match="WaterGAN needs the water stage"):
        gan_configs(ws, stage_config("gan", opts))  # WaterGAN starts from the site water
    learned = _options(build_parser().parse_args(["run", "S", "--workspace", "W", "--gan-budget-min", "2", "--add",
                                                  "gain", "--gan-site-water-mode", "learned"]), "S", "W")
    gan, pairs = gan_configs(ws, stage_config("gan", learned))
    assert gan.budget_min == 2.0 and gan.effects[-1] == "gain" and gan.site_water is None
    assert gan.rgbd_dir == pairs.rgbd_dir == tmp_path and gan.out_dir == pairs.model_dir == ws.folder("gan") / "model"
    ws.save("survey", SurveyConfig("S"), SurveyResult(n_images=3, width=8, height=6, stereo=False, simulated=False,
                                                      rgbd_dir="", survey_dir="S"))  # none given: the stage's own
    gan, pairs = gan_configs(ws, stage_config("gan", learned))
    assert gan.rgbd_dir == pairs.rgbd_dir == ws.folder("gan") / "generic_rgbd"
    by_count = _options(build_parser().parse_args(["run", "S", "--workspace", "W", "--gan-iterations", "5",
                                                   "--gan-site-water-mode", "learned"]), "S", "W")
    assert gan_configs(ws, stage_config("gan", by_count))[0].budget_min is None  # the count alone stops it
    with pytest.raises(UserInputError, match="the restorer needs the gan stage"):
        restorer_config(ws, stage_config("restorer", opts))
    with pytest.raises(SystemExit):
        build_parser().parse_args(["run", "S", "--workspace", "W", "--restorer-head", "magic"])
    with pytest.raises(UserInputError, match="unknown option.*restorer_hed"):
        run_options({"survey_dir": "S", "workspace": "W", "restorer_hed": "direct"})


def test_options_from_a_file_are_checked_as_the_command_line_checks_them(tmp_path):
    opts = run_options({"survey_dir": "S", "workspace": "W", "sfm_matching": "exhaustive", "gan_budget_min": 4,
                        "restorer_depth_hw": "56x56", "dense_fuse": False, "add": "gain,vignetting"})
    assert opts.stages["sfm"][("matching",)] == "exhaustive" and opts.add == ("gain", "vignetting")
    assert opts.stages["gan"][("budget_min",)] == 4.0 and isinstance(opts.stages["gan"][("budget_min",)], float)
    assert opts.stages["restorer"][("train", "depth_hw")] == (56, 56)
    for key, value, expected in (("sfm_matching", "bogus", "one of auto"), ("dense_fuse", "no", "true or false"),
                                 ("restorer_depth_hw", "big", "HEIGHTxWIDTH"), ("seed", 1.5, "an integer")):
        bad = tmp_path / f"{key}.toml"
        bad.write_text(f"{key} = {value!r}\n".replace("'", '"'))
        with pytest.raises(UserInputError, match=f"{bad}.*{key}.*{expected}"):
            load_options_file(bad)


def test_the_restorer_finds_its_pairs_altitude_and_range_mode_in_the_workspace(tmp_path):
    """What `watergan run` used to pass the restorer, the stage reads itself: the gan stage's pairs, the survey's
    navigation (altitude) and the range stage's maps (RGB-D mode); options given win."""
    from pipeline.gan import GanStage, GanStageResult, RestorerStage, restorer_config
    from pipeline.workspace import Workspace

    ws = Workspace(tmp_path / "ws")
    survey = SurveyResult(n_images=3, width=8, height=6, stereo=False, simulated=False, rgbd_dir=str(tmp_path),
                          survey_dir="S", navigation=False)
    ws.save("survey", SurveyConfig("S"), survey)
    gan = STAGES["gan"].folder
    ws.save("gan", GanStage(), GanStageResult(train={}, model=f"{gan}/model", generated=f"{gan}/generated",
                                              generated_count=2, generate_seconds=0.0))
    cfg = restorer_config(ws, RestorerStage())
    assert cfg.data_dir == ws.folder("gan") / "generated" and cfg.out_dir == ws.folder("restorer")
    assert not cfg.altitude and not cfg.range_input  # no navigation, no range stage
    ws.save("survey", SurveyConfig("S"), dataclasses.replace(survey, navigation=True))
    assert restorer_config(ws, RestorerStage()).altitude
    assert not restorer_config(ws, RestorerStage(altitude=False)).altitude
    assert restorer_config(ws, RestorerStage(range_input=True)).range_input


def test_a_navigation_log_gives_the_survey_its_navigation(tmp_path):
    """navigation.csv by time: interpolated at survey.json's frame times; roll and pitch give "down" in the camera
    frame. The survey stage writes the merged survey file into the workspace and leaves the user's as it was."""
    from pipeline.navigation import down_in_camera
    from pipeline.workspace import Workspace

    survey = tmp_path / "survey"
    _survey(survey)
    frames = [f"f{k}.png" for k in range(4)]
    (survey / "survey.json").write_text(json.dumps({"frames": frames, "frame_time_s": [0.5, 1.5, 2.5, 3.0]}))
    (survey / "navigation.csv").write_text("time_s,depth_m,altitude_m,roll_deg,pitch_deg,heading_deg\n"
                                           "0,10,2.0,0,0,90\n1,10.5,2.2,10,0,90\n2,11,2.4,0,-10,90\n"
                                           "3,11.5,2.6,0,0,90\n")
    before = (survey / "survey.json").read_text()
    opts = RunOptions(survey_dir=str(survey), workspace=str(tmp_path / "ws"), progress=False)
    result = Workspace(opts.workspace).run("survey", stage_config("survey", opts))
    written = json.loads((stage_folder(tmp_path / "ws", "survey") / "survey.json").read_text())
    assert result.navigation and (survey / "survey.json").read_text() == before
    np.testing.assert_allclose(written["nav_altitude_m"], [2.1, 2.3, 2.5, 2.6])
    np.testing.assert_allclose(written["nav_depth_m"], [10.25, 10.75, 11.25, 11.5])
    np.testing.assert_allclose(written["nav_down_cam"][0], down_in_camera(np.array([5.0]), np.array([0.0]))[0],
                               atol=1e-6)
    np.testing.assert_allclose(down_in_camera(np.array([0.0, 90.0, 0.0]), np.array([0.0, 0.0, 90.0])),
                               [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-12)  # starboard down: +x; bow up: +y


def test_a_navigation_log_gives_the_frames_positions(tmp_path):
    """easting_m and northing_m of navigation.csv (interpolated by time like the other columns) become survey.json's
    nav_easting_m and nav_northing_m, in the crs that survey.json names."""
    from pipeline.navigation import navigation_from_log

    frames = [f"f{k}.png" for k in range(3)]
    (tmp_path / "survey.json").write_text(json.dumps({"frames": frames, "frame_time_s": [0.5, 1.0, 2.0],
                                                      "crs": "EPSG:32633"}))
    log = tmp_path / "navigation.csv"
    log.write_text("time_s,easting_m,northing_m\n0,500000.0,5000000.0\n2,500002.0,5000001.0\n")
    nav = navigation_from_log(log, frames, [0.5, 1.0, 2.0])
    np.testing.assert_allclose(nav["nav_easting_m"], [500000.5, 500001.0, 500002.0])
    np.testing.assert_allclose(nav["nav_northing_m"], [5000000.25, 5000000.5, 5000001.0])
    log.write_text("time_s,easting_m\n0,500000.0\n2,500002.0\n")
    with pytest.raises(UserInputError, match="has easting_m alone: give easting_m and northing_m"):
        navigation_from_log(log, frames, [0.5, 1.0, 2.0])
