"""The workspace: stage folders, atomic writes, skip-if-done by configuration hash."""

from dataclasses import dataclass

import pytest

from pipeline.workspace import Workspace, atomic_write_text, config_hash
from watergan.errors import UserInputError


@dataclass(frozen=True)
class Cfg:
    size_px: int = 8
    name: str = "a"


def test_stage_runs_once_per_configuration(tmp_path):
    ws = Workspace(tmp_path / "ws")
    calls = []

    def stage(ws_, cfg):
        calls.append(cfg)
        (ws_.stage_dir("sfm") / "out.txt").write_text(cfg.name)
        return {"out": "04_sfm/out.txt", "points": 3}

    first = ws.run("sfm", Cfg(), stage)
    again = ws.run("sfm", Cfg(), stage)
    assert len(calls) == 1 and again == first and first["result"]["points"] == 3
    ws.run("sfm", Cfg(name="b"), stage)          # configuration changed: runs again
    ws.run("sfm", Cfg(name="b"), stage, force=True)
    assert len(calls) == 3
    assert ws.path(first["result"]["out"]).read_text() == "b"


def test_failed_stage_is_not_marked_done(tmp_path):
    ws = Workspace(tmp_path)

    def broken(ws_, cfg):
        raise RuntimeError("boom")

    ws.run("dense", Cfg(), lambda w, c: {"ok": 1})
    with pytest.raises(RuntimeError):
        ws.run("dense", Cfg(), broken, force=True)
    assert not ws.is_done("dense", Cfg())


def test_hash_depends_on_values_only():
    assert config_hash(Cfg()) == config_hash(Cfg(8, "a")) != config_hash(Cfg(9, "a"))


def test_atomic_write_leaves_no_temporary_files(tmp_path):
    atomic_write_text(tmp_path / "x" / "a.txt", "hello")
    assert [p.name for p in (tmp_path / "x").iterdir()] == ["a.txt"]


def test_workspace_on_a_file_is_a_clear_error(tmp_path):
    (tmp_path / "f").write_text("")
    with pytest.raises(UserInputError, match="not a folder"):
        Workspace(tmp_path / "f")
