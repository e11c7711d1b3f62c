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


def test_stage_folder_is_the_tables_folder_under_a_workspace_path(tmp_path):
    from pipeline.stages import stage_folder

    for name, stage in STAGES.items():
        assert stage_folder(tmp_path, name) == Workspace(tmp_path).folder(name) == tmp_path / stage.folder
    with pytest.raises(KeyError, match="unknown stage 'waters'"):
        stage_folder(tmp_path, "waters")


#: Where each stage's ``found`` fields come from (stage -> found field -> source), as its function fills them:
#: "STAGE.FIELD" a field of the result of a stage it reads, "STAGE/" a stage's folder (its own or one it reads),
#: "config.FIELD" a field of its own configuration.
FOUND_SOURCES = {
    "gan": {"train.rgbd_dir": "survey.rgbd_dir", "train.underwater_dir": "survey/", "train.out_dir": "gan/",
            "train.site_water": "water.water_json", "train.budget_min": "config.budget_min",
            "generate.model_dir": "gan/", "generate.rgbd_dir": "survey.rgbd_dir", "generate.out_dir": "gan/"},
    "restorer": {"train.data_dir": "gan.generated", "train.out_dir": "restorer/", "train.altitude": "survey.navigation",
                 "train.range_input": "range.range_dir"},
    "water": {"measure.normal_smooth_px": "range.normal_smooth_px"},
}


def _field_type(cls: type, dotted: str) -> type:
    """The type of the field ``dotted`` names in the dataclass ``cls`` (walked through nested dataclasses); an
    AssertionError naming the part that is not a field."""
    import dataclasses
    import typing

    for part in dotted.split("."):
        assert dataclasses.is_dataclass(cls), f"{dotted}: {cls} has no fields (at {part!r})"
        assert part in {f.name for f in dataclasses.fields(cls)}, f"{dotted}: {cls.__name__} has no field {part!r}"
        cls = typing.get_type_hints(cls)[part]
    return cls


def test_found_and_local_fields_are_fields_of_the_configuration_and_found_ones_of_an_upstream_result():
    """Every dotted path of the stage table (``found``, ``local``, ``run_defaults``) names a field of the stage's
    configuration, and every ``found`` field has its source (:data:`FOUND_SOURCES`): a field the result of a stage
    it reads has, a stage's folder, or a field of its own configuration."""
    import dataclasses

    assert set(FOUND_SOURCES) == {name for name, stage in STAGES.items() if stage.found}
    for name, stage in STAGES.items():
        for path in (*stage.found, *stage.local, *(p for p, _ in stage.run_defaults)):
            _field_type(stage.config_type, path)
        sources = FOUND_SOURCES.get(name, {})
        assert set(sources) == set(stage.found), name
        for path, source in sources.items():
            if source.startswith("config."):
                _field_type(stage.config_type, source.removeprefix("config."))
            elif source.endswith("/"):
                assert source[:-1] == name or source[:-1] in stage.reads, (name, path, source)
            else:
                upstream, _, field = source.partition(".")
                assert upstream in stage.reads, (name, path, source)
                assert field in {f.name for f in dataclasses.fields(STAGES[upstream].result_type)}, (name, path, source)


def _marked_result(stage: str):
    """The stage's result with every string field ``"STAGE.FIELD"`` (a mark to find where it went), every boolean
    False, numbers 1 and containers empty."""
    import dataclasses
    import typing

    cls = STAGES[stage].result_type
    values = {}
    for f in dataclasses.fields(cls):
        kind = typing.get_origin(typing.get_type_hints(cls)[f.name]) or typing.get_type_hints(cls)[f.name]
        values[f.name] = {str: f"{stage}.{f.name}", bool: False, int: 1, float: 1.0, list: [], dict: {}}[kind]
    return cls(**values)


def test_found_fields_are_filled_from_the_sources_named(tmp_path):
    """Each stage with ``found`` fields, resolved in a workspace whose upstream results carry marks
    (:func:`_marked_result`), fills each found field from the source :data:`FOUND_SOURCES` names: the mark of that
    result's field (a path ending in it, or a flag or number other than the field's default that the mark sets), a
    path in that stage's folder, or the value given to that configuration field."""
    import dataclasses
    import operator

    from pipeline.gan import gan_configs, restorer_config
    from pipeline.water import range_settings

    resolve = {"gan": lambda ws, cfg: dict(zip(("train", "generate"), gan_configs(ws, cfg), strict=True)),
               "restorer": lambda ws, cfg: {"train": restorer_config(ws, cfg)},
               "water": lambda ws, cfg: {"measure": range_settings(ws, cfg).measure}}
    assert set(resolve) == set(FOUND_SOURCES)
    ws = Workspace(tmp_path / "ws")
    for stage in {src.partition(".")[0] for sources in FOUND_SOURCES.values() for src in sources.values()
                  if "." in src and not src.startswith("config.")}:
        ws.save(stage, None, _marked_result(stage))
    for name, sources in FOUND_SOURCES.items():
        given = {src.removeprefix("config."): 7.5 for src in sources.values() if src.startswith("config.")}
        cfg = dataclasses.replace(STAGES[name].config_type(), **given)
        default = STAGES[name].config_type()
        resolved = resolve[name](ws, cfg)
        for path, source in sources.items():
            head, _, rest = path.partition(".")
            value = operator.attrgetter(rest)(resolved[head])
            if source.startswith("config."):
                assert value == given[source.removeprefix("config.")], (name, path)
            elif source.endswith("/"):
                assert ws.folder(source[:-1]).resolve() in (value.resolve(), *value.resolve().parents), (name, path)
            elif isinstance(value, bool):
                mark = getattr(ws.result(source.partition(".")[0]), source.partition(".")[2])
                assert value == bool(mark) != operator.attrgetter(path)(default), (name, path, value)
            elif isinstance(value, float):  # the mark of a number: 1.0, not the field's default
                mark = getattr(ws.result(source.partition(".")[0]), source.partition(".")[2])
                assert value == mark != operator.attrgetter(path)(default), (name, path, value)
            else:
                assert str(value).endswith(source), (name, path, value)


def test_a_workspace_an_older_version_made_is_refused_with_what_to_do(tmp_path):
    """Folders named otherwise by an older version (04_sfm, 06_water, 01_gan) are never read under the new names."""
    import subprocess
    import sys

    old = tmp_path / "old"
    for folder in (STAGES["survey"].folder, "01_gan", "04_sfm", "06_water"):
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


def _writes(name="out.txt", text="x" * 100):
    def stage(ws_, cfg):
        atomic_write_text(ws_.stage_dir("a") / name, text)
        return {"out": f"00_a/{name}"}
    return stage


def test_a_stage_whose_files_were_deleted_or_cut_short_runs_again_and_says_so(tmp_path, capsys):
    calls = []
    ws = Workspace(tmp_path / "ws", _table(a=lambda w, c: calls.append(1) or _writes()(w, c)))
    ws.run("a", Cfg())
    assert ws.is_done("a", Cfg()) and ws.record("a")["outputs"] == {"00_a/out.txt": 100}
    (ws.folder("a") / "out.txt").write_text("x" * 10)  # cut short
    assert not ws.is_done("a", Cfg())
    ws.run("a", Cfg())
    assert "files are gone or cut short" in capsys.readouterr().err and len(calls) == 2
    (ws.folder("a") / "out.txt").unlink()  # deleted
    assert ws.missing("a") == ["00_a/out.txt"]
    ws.run("a", Cfg())
    assert len(calls) == 3 and ws.is_done("a", Cfg()) and (ws.folder("a") / "out.txt").stat().st_size == 100


@dataclass(frozen=True)
class PathCfg:
    folder: str = ""


def test_a_moved_workspace_is_still_done(tmp_path):
    """A configuration that holds a path inside the workspace (as the pipeline's stages fill theirs in) hashes it
    relative to the workspace; the results it read hash as saved."""
    table = {"a": Stage("a", "00_a", PathCfg, dict, _writes(), (), "first"),
             "b": Stage("b", "01_b", PathCfg, dict, lambda w, c: {"ok": 1}, ("a",), "second")}
    ws = Workspace(tmp_path / "ws", table)
    for stage in ("a", "b"):
        ws.run(stage, PathCfg(str(ws.root.resolve() / "00_a")))
    (tmp_path / "ws").rename(tmp_path / "moved")
    moved = Workspace(tmp_path / "moved", table)
    assert all(moved.is_done(s, PathCfg(str(moved.root.resolve() / "00_a"))) for s in ("a", "b"))
    assert not moved.is_done("a", PathCfg(str(tmp_path / "elsewhere" / "00_a")))


def test_a_second_process_is_refused_while_the_first_writes_the_workspace(tmp_path):
    import subprocess
    import sys

    ws = Workspace(tmp_path / "ws", _table(a=_writes()))
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from pipeline.workspace import lock_workspace; "
                               f"from pathlib import Path; lock_workspace(Path({str(ws.root)!r})); print('held', "
                               "flush=True); time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(UserInputError, match=rf"in use by process {holder.pid} .*wait for it to finish"):
            ws.run("a", Cfg())
    finally:
        holder.kill()
        holder.wait()
    ws.run("a", Cfg())  # the first process has ended: its lock went with it
    assert ws.is_done("a", Cfg())


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_written_files_follow_the_umask(tmp_path, umask, mode):
    import os

    before = os.umask(umask)
    try:
        atomic_write_text(tmp_path / "a.txt", "hello")
    finally:
        os.umask(before)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == mode


def test_writes_from_many_threads_keep_the_umask(tmp_path):
    """correct's lanes write at once: each file gets the umask's mode and the process's umask is left as it was
    (reading it means setting it to 0 for a moment)."""
    import os
    import sys
    from concurrent.futures import ThreadPoolExecutor

    before, interval = os.umask(0o022), sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # threads switch as often as they can: between the umask's two calls too
    try:
        with ThreadPoolExecutor(8) as pool:
            list(pool.map(lambda k: atomic_write_text(tmp_path / f"{k}.txt", "x"), range(3000)))
        assert os.umask(0o022) == 0o022
    finally:
        os.umask(before)
        sys.setswitchinterval(interval)
    assert {f.stat().st_mode & 0o777 for f in tmp_path.iterdir()} == {0o644}


def test_a_full_disk_is_one_clear_error_and_a_rerun_completes(tmp_path, monkeypatch):
    import errno
    import os

    import watergan.io as io

    real_fdopen = io.os.fdopen

    class Full:
        def __init__(self, fd, mode):
            self.file = real_fdopen(fd, mode)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.file.close()

        def write(self, data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    ws = Workspace(tmp_path / "ws", _table(a=_writes()))
    monkeypatch.setattr(io.os, "fdopen", Full)
    with pytest.raises(io.WriteError, match=r"cannot write .*00_a/out.txt: No space left on device; free some space"):
        ws.run("a", Cfg())
    assert not ws.is_done("a", Cfg()) and list(ws.folder("a").iterdir()) == []  # nothing half-written kept
    monkeypatch.setattr(io.os, "fdopen", real_fdopen)
    ws.run("a", Cfg())
    assert ws.is_done("a", Cfg())


def test_a_full_disk_under_another_writer_is_one_line_from_the_command(monkeypatch, capsys):
    import errno
    import os

    import pipeline.cli as cli

    def full(args):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/ws/02_dense/fused_mesh.ply")

    monkeypatch.setattr(cli, "cmd_effects", full)
    assert cli.main(["effects"]) == 3  # an output cannot be written (2: the input is wrong)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot write /ws/02_dense/fused_mesh.ply: No space left on device" in err
