"""Every command the docs show runs.

Each ```bash block of docs/*.md and README.md is a runnable example (plain ``` blocks are synopses
and are not run). From those blocks this test keeps the lines a user would paste to drive boostnerf:
`boostnerf ...`, `bash recipes/...` and shell variable assignments, and runs them in order, one bash
script per document (`set -euo pipefail`), in an empty folder that has the repository's `recipes/` and
`research/`.

`boostnerf` is a shim on PATH that runs this checkout's CLI (through tests/cli_server.py, which
imports torch once and forks per command) with tiny settings, so the documented
long runs (lego, 20k iterations, 800 px) finish in seconds; the command lines themselves are
unchanged. The shim replaces the values of:
  --data and chain's DATA (the tiny generated scene, unless an earlier command made that folder; chain's - is kept),
  --recipe (a tiny recipe; the recipe named must exist: a file, or for chain also a name in recipes/; chain is given
  the tiny recipe when it names none, and keeps a name that is no recipe, which it refuses itself),
  --iters, --res, --image-size, --gate-res, --frames, --size, --train-views, --test-views,
  --device (cpu; added when missing); `export mesh` gets --threshold 0.005 (a model of a few steps is faint).
`make-scene --content textured` (photos for `boostnerf capture`) keeps its size and views: structure from motion
finds too few features in tiny photos to place their cameras.
A command that exits non-zero fails the test with the document and the command named.
"""

from __future__ import annotations

import json
import os
import re
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import make_recipe

ROOT = Path(__file__).parent.parent
DOCS = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]

# the tiny recipe's changes: the smallest chain that still exercises every stage (two experts, a gate, a few
# steps each)
DOCS_CHANGES = {
    "data": {"image_size": 16},
    "pretrain": {
        "res": [8, 12],
        "iters": 8,
        "geometry": {"res": 8, "iters": 20, "batch_rays": 128},
        "train": {"batch_rays": 128, "log_every": 4, "checkpoint_every": 4, "occupancy_every": 4},
        "dvgo": {"hidden": 8},
    },
    "moe": {"gate_res": 4, "iters": 4, "train": {"batch_rays": 128, "log_every": 2, "checkpoint_every": 2}},
}

TINY_VALUES = {"--iters": "4", "--res": "8,12", "--image-size": "16", "--gate-res": "4", "--frames": "3",
               "--size": "16", "--train-views": "6", "--test-views": "2", "--device": "cpu"}
NEEDS_DEVICE = {"pretrain", "build-moe", "finetune", "render", "eval", "count-params", "chain"}

SHIM = r'''#!{python}
"""`boostnerf` for the docs test: this checkout's CLI with tiny settings (see tests/test_docs_commands.py)."""
import os, subprocess, sys
from pathlib import Path

TINY = {tiny!r}
args = sys.argv[1:]
if args[:1] == ["make-scene"] and "textured" in args:  # photos to capture: as the docs give them
    TINY = {{k: v for k, v in TINY.items() if k not in ("--size", "--train-views", "--test-views")}}
chain = args[:1] == ["chain"]
if chain and len(args) > 1 and args[1] != "-" and not args[1].startswith("--") and not Path(args[1]).exists():
    args = ["chain", os.environ["DOCS_SCENE"], *args[2:]]  # DATA, as --data
out, i = [], 0
while i < len(args):
    a = args[i]
    key, eq, val = a.partition("=")
    if key.startswith("--") and key in TINY | {{"--data": 0, "--recipe": 0}}:
        if not eq:
            i += 1
            val = args[i] if i < len(args) else ""
        named = key == "--recipe" and (Path(val).exists() or (chain and Path("recipes", val + ".yaml").exists()))
        if key == "--recipe" and not named and chain:  # no recipe: chain's own refusal is what is tested
            out += [key, val]
            i += 1
            continue
        if key == "--recipe" and not named:
            sys.exit(f"docs test: the recipe {{val!r}} named in the docs does not exist")
        if key == "--data":  # a scene an earlier command made is used; a dataset the docs name is replaced
            val = val if Path(val).exists() else os.environ["DOCS_SCENE"]
        else:
            val = os.environ["DOCS_RECIPE"] if key == "--recipe" else TINY[key]
        out += [key, val]
    else:
        out.append(a)
    i += 1
if chain and "--recipe" not in out and "--help" not in out:  # the recipe chain would pick is sized for a dataset
    out += ["--recipe", os.environ["DOCS_RECIPE"]]
if args[:2] == ["export", "mesh"] and "--threshold" not in out:  # a model of a few steps is faint: a lower level
    out += ["--threshold", "0.005"]
if args and args[0] in {needs_device!r} and "--device" not in out and "--help" not in out:
    out += ["--device", "cpu"]
with open(os.environ["DOCS_LOG"], "a") as log:
    log.write("boostnerf " + " ".join(args) + "\n    -> " + " ".join(out) + "\n")
sys.path.insert(0, {tests!r})
from cli_server import client  # noqa: E402

sys.exit(client(os.environ["DOCS_SOCKET"], out))
'''

_KEEP = re.compile(r"^\s*(boostnerf\s|bash\s+recipes/|[A-Za-z_][A-Za-z0-9_]*=\S)")


def bash_blocks(text: str) -> list[str]:
    return re.findall(r"^```bash\n(.*?)^```", text, flags=re.DOTALL | re.MULTILINE)


def runnable_lines(block: str) -> list[str]:
    """The block's boostnerf / recipe-script commands and variable assignments (continuations joined)."""
    joined = re.sub(r"\s*\\\n\s*", " ", block)
    return [line.strip() for line in joined.splitlines() if _KEEP.match(line)]


def documented_commands() -> dict[str, list[str]]:
    found = {}
    for doc in DOCS:
        lines = [line for block in bash_blocks(doc.read_text()) for line in runnable_lines(block)]
        if any(not re.match(r"[A-Za-z_][A-Za-z0-9_]*=", line) for line in lines):
            found[doc.name] = lines
    return found


def test_the_docs_show_commands_and_the_extractor_reads_them():
    found = documented_commands()
    assert {"quickstart.md", "recipes.md", "stages.md", "README.md"} <= set(found)
    sample = "```bash\nR=recipes/x.yaml; WS=ws\nboostnerf pretrain --data d \\\n    --workspace $WS  # c\n" \
             "python -m pip install x\n```\n"
    assert runnable_lines(bash_blocks(sample)[0]) == ["R=recipes/x.yaml; WS=ws",
                                                      "boostnerf pretrain --data d --workspace $WS  # c"]


@pytest.fixture(scope="module")
def docs_env(tmp_path_factory):
    from boostnerf_cli.scenes import make_scene

    base = tmp_path_factory.mktemp("docs")
    scene = make_scene(base / "scene", size=16, n_train=8, n_test=2, seed=0)
    recipe = make_recipe(base / "docs-recipe.yaml", **DOCS_CHANGES)
    bin_dir = base / "bin"
    bin_dir.mkdir()
    shim = bin_dir / "boostnerf"
    shim.write_text(SHIM.format(python=sys.executable, tiny=TINY_VALUES, needs_device=NEEDS_DEVICE,
                                tests=str(Path(__file__).parent)))
    shim.chmod(shim.stat().st_mode | stat.S_IXUSR)
    sock = base / "cli.sock"
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "DOCS_SCENE": str(scene),
           "DOCS_RECIPE": str(recipe), "DOCS_SOCKET": str(sock),
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
           "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": "1"}
    server = subprocess.Popen([sys.executable, str(Path(__file__).parent / "cli_server.py"), str(sock)], env=env,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert server.stdout.readline().strip() == "ready", "the CLI fork server did not start"
        yield base, env
    finally:
        server.terminate()
        server.wait(timeout=30)


@pytest.mark.slow
def test_every_documented_command_runs(docs_env):
    """The documents in a user's reading order (quickstart first), in one folder, so later documents can
    use the workspaces the quickstart made; every document is run even when an earlier one failed."""
    base, env = docs_env
    commands = documented_commands()
    order = sorted(commands, key=lambda d: (d != "quickstart.md", d == "README.md", d))
    cwd = base / "user"
    cwd.mkdir()
    (cwd / "recipes").symlink_to(ROOT / "recipes")
    (cwd / "research").symlink_to(ROOT / "research")  # results.md's commands name research/recipes/
    failures = []
    for doc in order:
        log = cwd / f"{doc}.log"
        script = cwd / f"{doc}.sh"
        script.write_text("set -euo pipefail\ntrap 'echo \"docs test: failed: $BASH_COMMAND\" >&2' ERR\n"
                          + "\n".join(commands[doc]) + "\n")
        proc = subprocess.run(["bash", str(script)], cwd=cwd, env={**env, "DOCS_LOG": str(log)}, capture_output=True,
                              text=True, timeout=900, check=False)
        ran = log.read_text() if log.exists() else ""
        if proc.returncode != 0:
            failures.append(f"{doc}: a documented command failed:\n{proc.stderr[-2500:]}\nran:\n{ran[-1500:]}")
        else:
            assert ran.count("boostnerf ") >= sum(1 for line in commands[doc] if line.startswith("boostnerf ")), doc
    assert not failures, "\n\n".join(failures)


def _run_chain(cwd: Path, env: dict, *args: str) -> tuple[subprocess.CompletedProcess, str]:
    log = cwd / "chain.log"
    log.unlink(missing_ok=True)
    proc = subprocess.run(["bash", "recipes/chain.sh", *args], cwd=cwd, env={**env, "DOCS_LOG": str(log)},
                          capture_output=True, text=True, timeout=900, check=False)
    return proc, log.read_text() if log.exists() else ""


STAGES = ["[1/10] pretrain", "[2/10] build-moe", "[3/10] finetune baseline", "[4/10] finetune top1",
          "[5/10] finetune top2", "[6/10] finetune ens", "[7/10] eval", "[8/10] count-params",
          "[9/10] render --compare", "[10/10] render --path"]


def stage_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if re.fullmatch(r"\[\d+/\d+\] .+", line)]


@pytest.mark.slow
def test_chain_skips_finished_models_redoes_the_reports_and_stops_at_the_first_failure(docs_env):
    """recipes/chain.sh, the thin caller of `boostnerf chain`: its arguments and environment reach the command, a
    rerun trains nothing again, a failing stage stops the chain naming it, and a typo is refused before any stage."""
    base, env = docs_env
    cwd = base / "chain"
    cwd.mkdir()
    (cwd / "recipes").symlink_to(ROOT / "recipes")
    env = {**env, "TOP1_WEIGHT": "raw"}  # Top-1 weighted by the gate's probability, as the official code does
    proc, ran = _run_chain(cwd, env, "demo-dvgo-cpu", "-", "ws", "--iters", "6", "--frames", "3")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert [line.split()[1] for line in ran.splitlines() if line.startswith("boostnerf")] == ["chain"]
    assert "--top1-weight raw" in ran and "--models baseline top1 top2 ens" in ran, ran
    assert "--set pretrain.iters=6" in ran, ran  # pretrain's --iters, as the recipe key it sets
    assert stage_lines(proc.stderr) == STAGES
    ws = cwd / "ws"
    finetuned = {m: json.loads((ws / "moe" / f"{m}.json").read_text()) for m in ("top1", "top2", "ens")}
    assert [finetuned[m]["renormalize"] for m in ("top1", "top2")] == [False, True], finetuned
    assert json.loads((ws / "experts" / "dvgo-8.json").read_text())["iterations"] == 6
    # a report of one model over one view, then a rerun: nothing is trained again (build-moe keeps moe/init, made
    # with the same settings, so every mixture is current), and the reports cover every model and view again (the chain
    # kept any report newer than the models, this one too)
    init, first = (ws / "moe" / "init.safetensors").read_bytes(), json.loads((ws / "reports" / "eval.json").read_text())
    subprocess.run(["boostnerf", "eval", "-w", str(ws), "--model", "top2", "--views", "1", "--report", "--no-costs",
                    "--device", "cpu"], cwd=cwd, env={**env, "DOCS_LOG": str(cwd / "eval.log")}, check=True,
                   capture_output=True)
    proc, ran = _run_chain(cwd, env, "demo-dvgo-cpu", "-", "ws", "--iters", "6", "--frames", "3")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stderr.count("already finetuned, skipping") == 4 and "already trained, skipping" in proc.stderr
    assert "pictures in" in proc.stderr and "kept" in proc.stderr  # the pictures are newer than the models
    assert (ws / "moe" / "init.safetensors").read_bytes() == init
    report = json.loads((ws / "reports" / "eval.json").read_text())
    assert [m["name"] for m in report["models"]] == [m["name"] for m in first["models"]]
    assert len(first["models"]) == 2 + 4 and report["views"] == first["views"] > 1
    # a stage that fails stops the chain there, naming it, and leaves no workspace
    bad = cwd / "not-a-scene"
    bad.mkdir()  # exists, so the shim keeps it; a Blender layout pretrain cannot read
    (bad / "transforms_train.json").write_text("{not json")
    proc, ran = _run_chain(cwd, env, "demo-dvgo-cpu", str(bad), "ws-bad")
    assert proc.returncode == 2 and "error: chain stopped at stage 1/10, pretrain: cannot parse" in proc.stderr
    assert stage_lines(proc.stderr) == STAGES[:1] and not (cwd / "ws-bad").exists()
    proc, _ = _run_chain(cwd, env, "no-such-recipe", "-", "ws-bad")
    assert proc.returncode == 2 and "recipe no-such-recipe not found" in proc.stderr
    assert "blender-dvgo-cpu" in proc.stderr
    # a typo in MODELS or TOP1_WEIGHT is refused before any stage (after pretrain, build-moe and the baseline)
    proc, ran = _run_chain(cwd, {**env, "MODELS": "baseline ensemble"}, "demo-dvgo-cpu", "-", "ws-typo")
    assert proc.returncode == 2 and "unknown model 'ensemble'" in proc.stderr and not stage_lines(proc.stderr)
    proc, ran = _run_chain(cwd, {**env, "TOP1_WEIGHT": "probability"}, "demo-dvgo-cpu", "-", "ws-typo")
    assert proc.returncode == 2 and "--top1-weight probability" in proc.stderr and not stage_lines(proc.stderr)
    assert not (cwd / "ws-typo").exists()
