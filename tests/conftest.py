"""Shared fixtures and helpers: the tiny recipe (`make_recipe` writes it and its variants), tiny generated
scenes, a tiny trained workspace (made once per test run and worker), and running the real CLI."""

from __future__ import annotations

import collections
import copy
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

# pytest-xdist runs test files in parallel workers (pyproject addopts): each worker, and every CLI subprocess
# it starts, gets its share of the cores, so the workers do not oversubscribe them.
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
_THREADS = max(1, min(2, (os.cpu_count() or 1) // _WORKERS))
os.environ["OMP_NUM_THREADS"] = str(_THREADS)
torch.set_num_threads(_THREADS)

# The tiny recipe every CLI test starts from; `make_recipe` writes it, or a variant of it.
TINY_RECIPE = {
    "data": {"image_size": 32, "holdout_every": 8},
    "pretrain": {
        "model": "dvgo",
        "res": [12, 16],
        "iters": 30,
        "geometry": {"res": 12, "iters": 100, "batch_rays": 256, "alpha_init": 0.01},
        "train": {"batch_rays": 256, "log_every": 10, "checkpoint_every": 10, "occupancy_every": 10},
        "dvgo": {"hidden": 16, "layers": 1},
    },
    "moe": {
        "gate_res": 8,
        "bake_res": 16,  # the 8^3 gate baked on 16^3, not 128^3: each mixture loads ~0.6 s sooner (suite -1 min)
        "iters": 20,
        "train": {"batch_rays": 256, "log_every": 10, "checkpoint_every": 10},
    },
}


class _Remove:
    def __repr__(self) -> str:
        return "REMOVE"


REMOVE = _Remove()  # as a value in `make_recipe` changes: leave that key out (the tool's default applies)


def merge(base: dict, changes: dict) -> dict:
    """A deep copy of `base` with `changes` merged in: a mapping merges into the mapping it replaces, any
    other value replaces the old one, and `REMOVE` deletes the key."""
    out = copy.deepcopy(base)
    for key, value in changes.items():
        if value is REMOVE:
            out.pop(key, None)
        elif isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def make_recipe(path: Path, **changes: dict) -> Path:
    """Write `TINY_RECIPE` with `changes` (top-level sections: data=..., pretrain=..., moe=...) merged in
    (see `merge`) to the YAML file `path`, and return `path`. The file's stem is the recipe's name."""
    path.write_text(yaml.safe_dump(merge(TINY_RECIPE, changes), sort_keys=False))
    return path


# Whole-run quality references: PSNR (dB) of the tiny workspace's models on the tiny scene's test split, measured
# when these checks were written (with 1 thread; earlier references were the same with 2). A run must reach its
# reference within PSNR_MARGIN. The margin is small because these 30-step models are weak: dvgo-16 (17.51 dB)
# falls to 16.81 dB with its colour MLP zeroed and to 15.34 dB against shuffled test images, and both must fail the
# check (test_cli.py::test_the_psnr_references_fail_broken_models). Retrain and remeasure when the recipe or the
# training changes on purpose (last: e4fa017, the box widened by half a pixel's footprint around each surface
# point instead of a coarse cell, +1.4 to +1.6 dB: it was 15.28 / 16.13 with 15.61 zeroed and 14.88 shuffled).
PSNR_MARGIN = 0.25
TINY_PSNR = {"dvgo-12": 16.93, "dvgo-16": 17.51}  # pretrain reports, and eval over the 3 test views
TINY_MOE_PSNR_2_VIEWS = {"dvgo-12": 17.48, "dvgo-16": 18.01, "baseline": 18.44, "top1": 18.19, "top2": 18.39,
                         "ens": 18.37}  # eval --views 2 after build-moe and the four finetunes


# Test files that are split into one work unit per test: their tests share no fixture, and each takes minutes.
SPLIT_FILES = {"test_demo_scene.py"}


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own hook reads the xdist_group marks
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The work units of `--dist loadgroup --no-loadscope-reorder` (pyproject addopts): a test file is one unit, which
    one worker runs whole (its module fixtures are made once), but a `SPLIT_FILES` test is a unit of its own, so two
    workers can share that file. Those units run first, then the units with more `slow` tests: a long one handed
    out last would end the run alone."""
    def unit(item: pytest.Item) -> str:
        return item.nodeid if item.path.name in SPLIT_FILES else item.nodeid.split("::")[0]

    slow = collections.Counter(unit(item) for item in items if item.get_closest_marker("slow"))
    for item in items:
        item.add_marker(pytest.mark.xdist_group(unit(item)))
    # a stable sort: the order inside each unit is kept
    items.sort(key=lambda item: (item.path.name not in SPLIT_FILES or not slow[unit(item)], -slow[unit(item)]))


_SERVER: dict = {}  # this worker's CLI fork server (tests/cli_server.py): its process and socket, started once
_BASE_ENV = dict(os.environ)  # the worker's environment before any test changes it: the server's


def _cli_server() -> str:
    """The socket of this worker's CLI fork server, started on first use and stopped when the worker exits."""
    if not _SERVER:
        import atexit
        import tempfile

        sock = Path(tempfile.mkdtemp(prefix="boostnerf-cli-")) / "cli.sock"
        env = {**_BASE_ENV, "PYTHONWARNINGS": "ignore"}
        server = subprocess.Popen([sys.executable, str(Path(__file__).parent / "cli_server.py"), str(sock)], env=env,
                                  stdout=subprocess.PIPE, text=True)
        if server.stdout.readline().strip() != "ready":
            raise RuntimeError("the CLI fork server (tests/cli_server.py) did not start")
        atexit.register(server.kill)
        _SERVER.update(process=server, socket=str(sock))
    return _SERVER["socket"]


def run_cli(*args: str, cwd: Path | None = None, check: bool = False,
            env_extra: dict[str, str] | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run the real CLI (`boostnerf ARGS`) in a process of its own, with `env_extra` set: a child forked from this
    worker's CLI server (tests/cli_server.py), which has imported torch already; a fresh `python -m boostnerf_cli`
    when the test changed PYTHONPATH (a stand-in module or a plugin the server's imports cannot see). `timeout`:
    seconds the command may take."""
    env = {**os.environ, "PYTHONWARNINGS": "ignore", **(env_extra or {})}
    if env.get("PYTHONPATH") != _BASE_ENV.get("PYTHONPATH"):
        proc = subprocess.run([sys.executable, "-m", "boostnerf_cli", *args], capture_output=True, text=True,
                              cwd=cwd, env=env, timeout=timeout)
    else:
        proc = _forked(list(args), cwd, env, timeout)
    if check and proc.returncode != 0:
        raise AssertionError(f"boostnerf {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return proc


def run_script(script: Path | str, *args: str, cwd: Path | None = None,
               env_extra: dict[str, str] | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """`python SCRIPT ARGS` (a script of scripts/ or research/, as a user runs it), with `env_extra` set, in a
    child forked from this worker's CLI server (tests/cli_server.py: as `__main__`, its folder first on the path),
    which has imported torch already."""
    env = {**os.environ, "PYTHONWARNINGS": "ignore", **(env_extra or {})}
    return _forked(list(args), cwd, env, timeout, str(script))


def _forked(args: list[str], cwd: Path | None, env: dict[str, str], timeout: float,
            script: str | None = None) -> subprocess.CompletedProcess:
    """`boostnerf ARGS` (with `script`: `python SCRIPT ARGS`) in a child of this worker's CLI server."""
    import tempfile

    from cli_server import request

    argv = [sys.executable, script, *args] if script else ["boostnerf", *args]
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err, open(os.devnull, "rb") as null:
        code = request(_cli_server(), args, str(cwd or Path.cwd()), env, [null.fileno(), out.fileno(), err.fileno()],
                       timeout=timeout, script=script)
        out.seek(0)
        err.seek(0)
        return subprocess.CompletedProcess(argv, code, out.read().decode(), err.read().decode())


def cli_in_process(monkeypatch, capsys, *args: str) -> tuple[int, str]:
    """Run the CLI entry point (`boostnerf_cli.cli.main`, what the `boostnerf` script calls) in this
    process -> (exit code, stderr). Same code path as a subprocess, without paying torch's import again."""
    from boostnerf_cli.cli import main

    monkeypatch.setattr("sys.argv", ["boostnerf", *args])
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        main()
    return exit_info.value.code, capsys.readouterr().err


def assert_clean_failure(proc: subprocess.CompletedProcess, *needles: str) -> None:
    """The CLI refused cleanly: exit code 2, no traceback, the last stderr line is `error: ...` and holds
    every one of `needles`."""
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) >= 1 and lines[-1].startswith("error:"), proc.stderr
    for n in needles:
        assert n in lines[-1], lines[-1]


def unavailable(what: str, install: str) -> None:
    """A part the test extra installs (pycolmap, Chromium) is missing: the test is skipped, but fails under CI
    (CI=true, which .ci/run sets), where it is installed and its absence is a broken set-up, not a pass."""
    if os.environ.get("CI") == "true":
        pytest.fail(f"{what} is missing on this CI machine: {install}")
    pytest.skip(f"{what} is not installed: {install}")


def need_pycolmap():
    """pycolmap (`boostnerf capture`'s structure from motion); the test skipped without it, or failed under CI."""
    try:
        import pycolmap
    except ImportError:
        unavailable("pycolmap", 'pip install -e ".[test]"')
    return pycolmap


def no_temp_files(folder: Path) -> bool:
    """True when no temporary file of an unfinished atomic write (`workspace.is_temporary`) is left under `folder`."""
    from boostnerf_cli.workspace import is_temporary

    return not [p for p in folder.rglob("*") if is_temporary(p)]


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    from boostnerf_cli.scenes import make_scene

    return make_scene(tmp_path_factory.mktemp("scene") / "tiny", size=32, n_train=12, n_test=3, seed=0)


@pytest.fixture(scope="session")
def tiny_recipe(tmp_path_factory) -> Path:
    return make_recipe(tmp_path_factory.mktemp("recipe") / "tiny.yaml")


@pytest.fixture(scope="session")
def trained_ws(tmp_path_factory, tiny_scene, tiny_recipe) -> Path:
    """A workspace with two tiny pretrained experts (through the real CLI)."""
    ws = tmp_path_factory.mktemp("ws") / "ws"
    run_cli("pretrain", "--data", str(tiny_scene), "--recipe", str(tiny_recipe), "--workspace", str(ws),
            "--device", "cpu", check=True)
    return ws


@pytest.fixture(scope="session")
def mixture_ws(tmp_path_factory, trained_ws) -> Path:
    """`trained_ws` with a mixture: build-moe and a 5-step top2 (through the real CLI)."""
    import shutil

    ws = tmp_path_factory.mktemp("mixture") / "ws"
    shutil.copytree(trained_ws, ws)
    run_cli("build-moe", "--workspace", str(ws), "--device", "cpu", check=True)
    run_cli("finetune", "--workspace", str(ws), "--topk", "2", "--iters", "5", "--device", "cpu", check=True)
    return ws
