"""The workspace: stage folders, atomic writes, skip-if-done by configuration hash."""

from dataclasses import dataclass

import pytest

from pipeline.stages import STAGES, Stage
from pipeline.workspace import Workspace, config_hash
from watergan.errors import UserInputError
from watergan.io import atomic_write_text


@dataclass(frozen=True)
class Cfg:
    size_px: int = 8
    name: str = "a"


def _table(**fns) -> dict[str, Stage]:
    """A stage table of toy stages: a -> b (b reads a)."""
    return {"a": Stage("a", "00_a", Cfg, dict, fns["a"], (), "first"),
            "b": Stage("b", "01_b", Cfg, dict, fns.get("b", lambda w, c: {"ok": 1}), ("a",), "second")}


def test_stage_runs_once_per_configuration(tmp_path):
    calls = []

    def stage(ws_, cfg):
        calls.append(cfg)
        (ws_.stage_dir("a") / "out.txt").write_text(cfg.name)
        return {"out": "00_a/out.txt", "points": 3}

    ws = Workspace(tmp_path / "ws", _table(a=stage))
    first = ws.run("a", Cfg())
    again = ws.run("a", Cfg())
    assert len(calls) == 1 and again == first and first["points"] == 3
    ws.run("a", Cfg(name="b"))          # configuration changed: runs again
    ws.run("a", Cfg(name="b"), force=True)
    assert len(calls) == 3
    assert ws.path(first["out"]).read_text() == "b"


def test_a_rerun_upstream_reruns_the_stages_that_read_it(tmp_path):
    calls = []
    ws = Workspace(tmp_path / "ws", _table(a=lambda w, c: {"n": len(calls)}, b=lambda w, c: calls.append(c) or {}))
    ws.run("a", Cfg())
    ws.run("b", Cfg())
    ws.run("b", Cfg())
    assert len(calls) == 1 and ws.is_done("b", Cfg())
    ws.run("a", Cfg(), force=True)  # a new record upstream (its result differs): b is no longer done
    assert not ws.is_done("b", Cfg())
    ws.run("b", Cfg())
    assert len(calls) == 2


def test_failed_stage_is_not_marked_done(tmp_path):
    def broken(ws_, cfg):
        raise RuntimeError("boom")

    ws = Workspace(tmp_path, _table(a=lambda w, c: {"ok": 1}))
    ws.run("a", Cfg())
    ws = Workspace(tmp_path, _table(a=broken))
    with pytest.raises(RuntimeError):
        ws.run("a", Cfg(), force=True)
    assert not ws.is_done("a", Cfg())


def test_hash_depends_on_values_only():
    assert config_hash(Cfg()) == config_hash(Cfg(8, "a")) != config_hash(Cfg(9, "a"))


def test_atomic_write_leaves_no_temporary_files(tmp_path):
    atomic_write_text(tmp_path / "x" / "a.txt", "hello")
    assert [p.name for p in (tmp_path / "x").iterdir()] == ["a.txt"]


def test_workspace_on_a_file_is_a_clear_error(tmp_path):
    (tmp_path / "f").write_text("")
    with pytest.raises(UserInputError, match="not a folder"):
        Workspace(tmp_path / "f")


def test_every_stage_is_declared_once_and_resolves():
    """The stage table names real configuration and result dataclasses and functions, one folder each."""
    import dataclasses

    folders = [s.folder for s in STAGES.values()]
    assert len(set(folders)) == len(folders)
    for name, stage in STAGES.items():
        assert dataclasses.is_dataclass(stage.config_type) and dataclasses.is_dataclass(stage.result_type), name
        assert callable(stage.fn) and set(stage.reads) < set(STAGES), name
        assert list(STAGES).index(name) > max((list(STAGES).index(r) for r in stage.reads), default=-1), name


def test_results_hold_numpy_values_as_plain_json():
    import numpy as np

    from watergan.io import to_jsonable

    assert to_jsonable({"a": np.float32(1.5), "b": np.arange(3), "c": (np.int64(2),)}) == {"a": 1.5, "b": [0, 1, 2],
                                                                                           "c": [2]}


def test_folders_are_numbered_in_run_order_and_every_stage_has_a_workspace_command():
    from pipeline.cli import build_parser

    assert [s.folder for s in STAGES.values()] == [f"{k:02d}_{name}" for k, name in enumerate(STAGES)]
    parser = build_parser()
    for name, stage in STAGES.items():
        if name == "diagnose":  # its own command: a workspace or a bare survey folder (`watergan diagnose TARGET`)
            assert parser.parse_args(["diagnose", "W"]).func is not None
            continue
        required = ["--survey-dir", "S"] if name == "survey" else []
        args = parser.parse_args([stage.command, "--workspace", "W", *required])
        assert args.stage == name, name


def test_a_workspace_an_older_version_made_is_refused_with_what_to_do(tmp_path):
    """Folders named otherwise by an older version (04_sfm, 06_water, 01_gan) are never read under the new names."""
    import subprocess
    import sys

    old = tmp_path / "old"
    for folder in ("00_survey", "01_gan", "04_sfm", "06_water"):
        (old / folder).mkdir(parents=True)
        (old / folder / "result.json").write_text("{}")
    with pytest.raises(UserInputError, match=r"made by an older version of watergan .*01_gan, 04_sfm, 06_water.*"
                                             r"rerun into a new workspace"):
        Workspace(old)
    out = subprocess.run([sys.executable, "-m", "pipeline.cli", "water", "--workspace", str(old)],
                         capture_output=True, text=True)
    assert out.returncode == 2 and "older version" in out.stderr and "Traceback" not in out.stderr
    (old / "notes").mkdir()  # a folder of the user's without a stage record is not a stage
    assert Workspace(tmp_path / "new").root.is_dir()
