"""Fault injection: interrupted and concurrent runs, failing writes, damaged and stale inputs.

Each test backs one or more rows of the table in docs/reliability.md.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import REMOVE, assert_clean_failure, cli_in_process, make_recipe, run_cli

from boostnerf_cli import workspace as wsmod
from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.lineage import Survey
from boostnerf_cli.models import load_expert, save_expert
from boostnerf_cli.recipe import load_recipe
from boostnerf_cli.stages import build_moe, pretrain
from boostnerf_cli.workspace import Workspace, is_temporary


def _tmp_files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if is_temporary(p)]


@pytest.fixture()
def moe_copy(trained_ws, tmp_path):
    """A private copy of the tiny workspace with a built (untrained) mixture."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    build_moe.build(Survey(Workspace(ws)), None, load_recipe(None).moe.__class__(gate_res=8), "cpu")
    return ws


# --- one writer at a time -----------------------------------------------------------------------
def test_second_writer_is_refused_through_the_cli_and_the_lock_is_released(trained_ws, tmp_path):
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    with Workspace(ws).lock():
        proc = run_cli("eval", "--workspace", str(ws), "--views", "1", "--no-costs", "--report", "--device", "cpu")
        assert_clean_failure(proc, "in use by another boostnerf process", str(os.getpid()))
        proc = run_cli("eval", "--workspace", str(ws), "--views", "1", "--no-costs", "--device", "cpu")  # a reader
        assert_clean_failure(proc, "is being written by another boostnerf process", str(os.getpid()))
    assert not (ws / ".lock").exists()
    proc = run_cli("finetune", "--workspace", str(ws), "--topk", "1", "--device", "cpu")  # fails: no build-moe
    assert_clean_failure(proc, "build-moe")
    assert not (ws / ".lock").exists()  # released on an error exit too


HOLD_LOCK = "import sys, time; from boostnerf_cli.workspace import Workspace; cm = Workspace(sys.argv[1]).lock(); " \
            "cm.__enter__(); print('locked', flush=True); time.sleep(120)"


HOLD_READ = HOLD_LOCK.replace(".lock()", ".reading()")


def test_readers_share_a_workspace_and_a_read_only_one_can_be_evaluated(trained_ws, tmp_path, monkeypatch, capsys):
    """`eval` without --report only reads: it took the exclusive writer lock, so two evals of one workspace (two
    models on two GPUs) refused each other, and a read-only workspace (an archive, a read-only mount) could not be
    evaluated at all ("cannot take the writer lock ... fix the workspace folder's permissions")."""
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws, ignore=shutil.ignore_patterns("reports", "renders"))
    (ws / ".lock").write_text("deadhost 99999")  # left by a killed writer: not the one to name while eval reads
    holder = subprocess.Popen([sys.executable, "-c", HOLD_READ, str(ws)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        run_cli("eval", "--workspace", str(ws), "--views", "1", "--no-costs", "--device", "cpu", check=True)
        proc = run_cli("eval", "--workspace", str(ws), "--views", "1", "--no-costs", "--report", "--device", "cpu")
        assert_clean_failure(proc, "in use by another boostnerf process (reading it: eval)")
        assert not (ws / "reports").exists()
    finally:
        holder.kill()
        holder.wait()
    run_cli("eval", "--workspace", str(ws), "--views", "1", "--no-costs", "--report", "--device", "cpu", check=True)
    assert not (ws / ".lock").exists()
    real_open = os.open

    def read_only(path, flags, *args):  # what a read-only mount answers to a file it would have to create
        if str(path).endswith(".lock") and flags & os.O_CREAT:
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_open(path, flags, *args)

    monkeypatch.setattr(wsmod.os, "open", read_only)
    code, err = cli_in_process(monkeypatch, capsys, "eval", "--workspace", str(ws), "--views", "1", "--no-costs",
                               "--device", "cpu")
    assert code == 0 and "dvgo-16: PSNR" in err, err
    with Workspace(ws).reading():  # no lock file can be made, and no writer can be at work: read as it is
        assert not (ws / ".lock").exists()
    with pytest.raises(BoostNerfError, match="cannot take the writer lock"), Workspace(ws).lock():
        pass
    monkeypatch.undo()

    def no_locks(fd, op):  # a file system without flock (some network mounts): one line, not a traceback
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(wsmod.fcntl, "flock", no_locks)
    with (pytest.raises(BoostNerfError, match="cannot take the reader lock .*No locks available"),
          Workspace(ws).reading()):
        pass
    assert not (ws / ".lock").exists() or (ws / ".lock").read_text() == ""


def test_lock_of_a_killed_process_is_stale_and_taken_over(tmp_path):
    ws = tmp_path / "ws"
    holder = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(ws)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(BoostNerfError, match=f"in use by another boostnerf process .*{holder.pid}"), \
                Workspace(ws).lock():
            pass
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert str(holder.pid) in (ws / ".lock").read_text()  # the dead writer's lock file is still there
    (ws / "experts").mkdir()
    (ws / "experts" / ".dvgo-12.safetensors.abc12_x9.tmp").write_bytes(b"half")  # and a file it was writing
    (ws / "renders").mkdir()
    (ws / "renders" / ".orbit.mp4.abc12_x9.tmp.mp4").write_bytes(b"half")  # a video (ffmpeg needs the suffix)
    (ws / ".scene.tmp" / "train").mkdir(parents=True)  # a scene being generated
    with Workspace(ws).lock():
        assert (ws / ".lock").read_text().endswith(f" {os.getpid()}")
    assert not _tmp_files(ws) and not (ws / ".lock").exists() and not (ws / ".scene.tmp").exists()


def test_taking_the_lock_removes_only_what_a_killed_writer_left(tmp_path):
    """The clean-up at the lock removes boostnerf's own temporaries and nothing else: it searched the whole folder
    for `.*.tmp*`, so `pretrain -w .` or `-w ~/project` deleted a user's `.venv.tmp` folder, `.draft.tmp.txt` and
    `notes/.x.abc.tmp`, even when the command then failed (not a scene), and a command on a parent workspace deleted
    the file a nested workspace's live writer was writing."""
    ws = tmp_path / "project"
    user = [ws / ".draft.tmp.txt", ws / ".notes.tmp", ws / ".venv.tmp" / "keep", ws / "notes" / ".x.abc12_x9.tmp",
            ws / ".my.notes.tmp", ws / ".env.backup.tmp", ws / ".notes.txt.abcd1234.tmp",  # in the root: not ours
            ws / "variants" / "child" / "experts" / ".dvgo-8.safetensors.k3j2abcd.tmp",  # a live nested writer's
            ws / "experts" / ".hidden" / ".a.json.abc12_x9.tmp", ws / "experts" / ".my.notes.tmp"]
    ours = [ws / "experts" / ".dvgo-12.safetensors.k3j2abcd.tmp", ws / ".manifest.json.abc12_x9.tmp",
            ws / "renders" / "top2" / "test" / ".r_0.png.abc12_x9.tmp", ws / "reports" / ".eval.json.x_1_2345.tmp"]
    for p in user + ours:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("keep")
    (ws / "variants" / "child" / ".lock").write_text("host 1")  # that workspace's writer holds its own lock
    (ws / ".scene.tmp" / "train").mkdir(parents=True)  # the embedded scene, generation stopped half way
    with Workspace(ws).lock():
        pass
    assert [p for p in user if not p.exists()] == []
    assert [p for p in ours if p.exists()] == [] and not (ws / ".scene.tmp").exists()
    proc = run_cli("pretrain", "-w", str(ws), "--data", str(tmp_path / "nothing"), "--device", "cpu")  # refused
    assert_clean_failure(proc, "does not exist")
    assert [p for p in user if not p.exists()] == []


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_interrupt_stops_cleanly_and_the_rerun_resumes(tmp_path, tiny_scene, sig):
    recipe = make_recipe(tmp_path / "r.yaml", data={"image_size": 24}, pretrain={
        "res": [10],
        "geometry": {"res": 8, "iters": 8, "batch_rays": 64},
        "train": {"batch_rays": 64, "log_every": 1, "checkpoint_every": 5, "occupancy_every": REMOVE},
        "dvgo": {"hidden": 8},
    }, moe=REMOVE)
    ws = tmp_path / "ws"
    args = ["pretrain", "--data", str(tiny_scene), "--recipe", str(recipe), "--workspace", str(ws), "--device", "cpu"]
    proc = subprocess.Popen([sys.executable, "-m", "boostnerf_cli", *args], stderr=subprocess.PIPE, text=True,
                            stdout=subprocess.DEVNULL)
    for line in proc.stderr:
        if line.startswith("[dvgo-10] step 12/"):
            proc.send_signal(sig)
            break
    err = proc.stderr.read()
    # it ends by the signal it got (a shell's status 130 / 143), so a script running it stops too (an
    # exit 130 let a shell loop go on to its next command after a Ctrl-C)
    assert proc.wait(timeout=120) == -sig
    assert err.strip().splitlines()[-1] == (
        "interrupted: finished files are kept; rerun the same command to go on (a model in training resumes from its "
        "last checkpoint, if it had written one)")
    assert "Traceback" not in err
    assert not (ws / ".lock").exists() and not _tmp_files(ws)
    step = torch.load(ws / "checkpoints" / "dvgo-10.pt", weights_only=True)["step"]
    assert step >= 10  # nothing lost beyond the steps since this checkpoint
    rerun = run_cli(*args, check=True)
    assert f"resuming from {ws / 'checkpoints' / 'dvgo-10.pt'} at step {step}/30" in rerun.stderr
    assert json.loads((ws / "experts" / "dvgo-10.json").read_text())["iterations"] == 30


# --- failing writes ----------------------------------------------------------------------------
def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_disk_full_while_writing_an_artifact_keeps_the_previous_one(moe_copy, monkeypatch):
    ws = Workspace(moe_copy)
    before = ws.model_path("init").read_bytes()
    report_before = (ws.moe_dir / "init.json").read_text()
    real_save = wsmod.save_file

    def half_then_full(tensors, path, metadata=None):
        real_save(tensors, path, metadata=metadata)
        with open(path, "r+b") as f:
            f.truncate(os.path.getsize(path) // 2)  # the disk filled up half way
        _enospc()

    monkeypatch.setattr(wsmod, "save_file", half_then_full)
    rec = load_recipe(None).moe.__class__(gate_res=6)
    with pytest.raises(BoostNerfError, match=r"could not write .*init\.safetensors \(No space left on device\)"):
        build_moe.build(Survey(ws), None, rec, "cpu")
    assert ws.model_path("init").read_bytes() == before
    assert (ws.moe_dir / "init.json").read_text() == report_before
    assert not _tmp_files(moe_copy)


@pytest.mark.parametrize("where", ["_fsync", "replace"])
def test_failing_json_write_keeps_the_previous_report_and_manifest(moe_copy, monkeypatch, where):
    ws = Workspace(moe_copy)
    manifest = ws.manifest_path.read_text()
    if where == "replace":
        monkeypatch.setattr(wsmod.os, "replace", _enospc)
    else:
        monkeypatch.setattr(wsmod, where, _enospc)
    with pytest.raises(BoostNerfError, match="No space left on device"):
        ws.update_manifest(moe={"x": 1})
    assert ws.manifest_path.read_text() == manifest
    assert not _tmp_files(moe_copy)


def test_unwritable_workspace_is_one_clear_line(tmp_path, monkeypatch):
    def denied(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(wsmod.tempfile, "mkstemp", denied)
    with pytest.raises(BoostNerfError, match=r"could not write .*r\.json \(Permission denied\)"):
        wsmod.write_json(tmp_path / "r.json", {"a": 1})


@pytest.mark.parametrize("who", ["make-scene", "pretrain", "bench"])
def test_generating_a_scene_is_atomic(tmp_path, monkeypatch, who):
    """A scene is written to `.NAME.tmp` beside its folder and renamed when complete: a run stopped half way leaves
    no half scene that a rerun would take for a finished one (bench's default scene lost its test views that way:
    the rerun held out 3 train views instead), and the next run generates it whole."""
    from boostnerf_cli.scenes import make_scene, procedural
    from boostnerf_cli.stages import bench

    real = procedural._write_blender

    def dies_half_way(out, views, *args):
        real(out, {"train": views["train"]}, *args)  # train written, then stopped before the test split
        raise KeyboardInterrupt

    rec = load_recipe(None)
    rec.data.image_size = 16
    ws = Workspace(tmp_path / "ws")
    scene = {"make-scene": tmp_path / "scene", "pretrain": ws.root / "scene", "bench": ws.root / "scene"}[who]
    run = {"make-scene": lambda: make_scene(scene, size=16, n_train=3, n_test=1),
           "pretrain": lambda: pretrain.run(Survey(ws), None, rec, "cpu", False),
           "bench": lambda: bench.run(ws.root, None, rec, "quick", None, "cpu", 1)}[who]
    monkeypatch.setattr(procedural, "_write_blender", dies_half_way)
    with pytest.raises(KeyboardInterrupt):
        run()
    assert not scene.exists()  # no half scene a rerun would take for a finished one
    monkeypatch.setattr(procedural, "_write_blender", real)

    class Stop(Exception):
        pass

    for stage in (pretrain, bench):  # the scene is made, then the run stops: no training needed here
        if hasattr(stage, "ensure_geometry"):
            monkeypatch.setattr(stage, "ensure_geometry", lambda *a, **k: (_ for _ in ()).throw(Stop()))
    monkeypatch.setattr(bench, "bench_config", lambda *a, **k: (_ for _ in ()).throw(Stop()))
    with pytest.raises(Stop) if who != "make-scene" else __import__("contextlib").nullcontext():
        run()
    assert (scene / "transforms_test.json").exists() and not (scene.parent / ".scene.tmp").exists()


# --- damaged inputs ----------------------------------------------------------------------------
def test_damaged_training_checkpoint_and_manifest_are_one_clear_line(trained_ws, tiny_scene, tiny_recipe, tmp_path):
    ws = tmp_path / "ws"
    (ws / "checkpoints").mkdir(parents=True)
    (ws / "checkpoints" / "geometry.pt").write_bytes(b"\x00garbage")
    proc = run_cli("pretrain", "--data", str(tiny_scene), "--recipe", str(tiny_recipe), "--workspace", str(ws),
                   "--device", "cpu")
    assert_clean_failure(proc, "geometry.pt is damaged", "delete it")
    ws2 = tmp_path / "ws2"
    shutil.copytree(trained_ws, ws2)
    (ws2 / "manifest.json").write_text('{"data": ')
    proc = run_cli("build-moe", "--workspace", str(ws2), "--device", "cpu")
    assert_clean_failure(proc, "manifest", "not valid JSON")


# --- stale or mismatched inputs ----------------------------------------------------------------
def test_experts_retrained_or_removed_after_build_moe_are_detected(moe_copy):
    path = moe_copy / "experts" / "dvgo-12.safetensors"
    model, occ, meta = load_expert(path)
    with torch.no_grad():
        model.density_table.add_(0.01)  # as if `pretrain --force` had retrained it
    save_expert(path, model, occ, {k: meta[k] for k in ("name", "step", "scene")})
    proc = run_cli("finetune", "--workspace", str(moe_copy), "--topk", "1", "--device", "cpu")
    assert_clean_failure(proc, "expert dvgo-12 was retrained after build-moe", "build-moe")
    path.unlink()
    (moe_copy / "experts" / "dvgo-12.json").unlink()
    proc = run_cli("finetune", "--workspace", str(moe_copy), "--topk", "1", "--device", "cpu")
    assert_clean_failure(proc, "expert dvgo-12 was removed after build-moe")


def test_a_model_finetuned_from_an_older_init_is_not_silently_kept(moe_copy, caplog):
    from boostnerf_cli.stages import finetune

    ws = Workspace(moe_copy)
    rec = load_recipe(None).moe.__class__(gate_res=8, iters=2)
    rec.train.batch_rays = 64
    finetune.run(Survey(ws), "top1", 1, rec, "cpu", False)
    assert json.loads(ws.manifest_path.read_text())["moe"]["init"]["inputs"].keys() == {"dvgo-12", "dvgo-16"}
    caplog.set_level(logging.INFO, logger="boostnerf_cli")
    finetune.run(Survey(ws), "top1", 1, rec, "cpu", False)
    assert "already finetuned" in caplog.messages[-1]
    build_moe.build(Survey(ws), None, load_recipe(None).moe.__class__(gate_res=6), "cpu")  # a new init
    with pytest.raises(BoostNerfError, match="top1 is stale: moe/init was rebuilt after top1 was finetuned from it; "
                                             "make it again with `boostnerf finetune -w .* --topk 1 --force`"):
        finetune.run(Survey(ws), "top1", 1, rec, "cpu", False)
    finetune.run(Survey(ws), "top1", 1, rec, "cpu", True)  # --force redoes it from the new init


def test_a_different_or_changed_scene_is_refused(trained_ws, tiny_scene, tiny_recipe, tmp_path):
    """Another scene given to pretrain is refused (an identical copy elsewhere is the same scene, moved:
    test_cli.py::test_a_moved_scene_or_workspace_is_followed_not_retrained), and so is, by the later stages, the
    workspace's scene edited after pretrain."""
    import imageio.v3 as iio

    other = tmp_path / "other"
    shutil.copytree(tiny_scene, other)
    ws = tmp_path / "ws"
    shutil.copytree(trained_ws, ws)
    manifest = json.loads((ws / "manifest.json").read_text())
    manifest["data"]["path"] = str(other)
    (ws / "manifest.json").write_text(json.dumps(manifest))
    Survey(Workspace(ws)).scene()  # an identical copy passes
    img = iio.imread(other / "train" / "r_0.png")
    img[5, 5] = [255, 0, 0, 255]  # one pixel now opaque red
    iio.imwrite(other / "train" / "r_0.png", img)
    proc = run_cli("eval", "--workspace", str(ws), "--views", "1", "--no-costs", "--device", "cpu")
    assert_clean_failure(proc, "changed since pretrain")
    proc = run_cli("pretrain", "--data", str(other), "--recipe", str(tiny_recipe), "--workspace", str(ws),
                   "--device", "cpu")
    assert_clean_failure(proc, "changed since this workspace was trained on it", "--force")
    shutil.copytree(other, tmp_path / "elsewhere")  # the edited scene at another path: not the one trained on
    proc = run_cli("pretrain", "--data", str(tmp_path / "elsewhere"), "--recipe", str(tiny_recipe), "--workspace",
                   str(ws), "--device", "cpu")
    assert_clean_failure(proc, "is not the one this workspace was trained on", "--force")


def test_disk_full_while_checkpointing_is_one_line_and_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    """torch.save reports a full disk as an opaque RuntimeError; it must become the OSError's message."""
    ckpt = tmp_path / "run.pt"
    wsmod.save_torch(ckpt, {"step": 5, "w": torch.ones(10)})
    real_open = open

    class FullDisk:
        def __init__(self, f):
            self.f, self.written = f, 0

        def write(self, data):
            self.written += len(data)
            if self.written > 300:
                raise OSError(errno.ENOSPC, "No space left on device")
            return self.f.write(data)

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return self.f.__exit__(*exc)

    monkeypatch.setattr(wsmod, "open", lambda *a, **k: FullDisk(real_open(*a, **k)), raising=False)
    with pytest.raises(BoostNerfError, match=r"could not write .*run\.pt \(No space left on device\)"):
        wsmod.save_torch(ckpt, {"step": 10, "w": torch.zeros(10_000)})
    monkeypatch.undo()
    assert torch.load(ckpt, weights_only=True)["step"] == 5
    assert not _tmp_files(tmp_path)


def test_an_interrupt_inside_a_checkpoint_write_is_the_one_line_interrupt(monkeypatch, capsys):
    """Ctrl-C or SIGTERM while torch.save writes a checkpoint (a minute for a paper-size expert's 3.4 GB): the
    interrupt unwinds through the zip writer, whose cleanup raises its own RuntimeError ("unexpected pos"). The CLI
    printed that traceback and exited 1; it now sees the interrupt behind it."""
    from boostnerf_cli import cli

    def stage() -> None:
        try:
            raise cli.Interrupted()
        finally:
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 32118144 vs 32118096")

    monkeypatch.setattr(cli, "app", lambda **kwargs: stage())
    monkeypatch.setattr(cli, "_die_by", lambda signum: sys.exit(128 + signum))  # not this test process
    monkeypatch.setattr("sys.argv", ["boostnerf", "pretrain"])
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
    assert exit_info.value.code == 130
    assert capsys.readouterr().err.strip().startswith("interrupted: finished files are kept")
