"""scripts/gpucheck.py, the logic of scripts/gpu-check.sh and scripts/paper-check.sh: paper-check's plan, the
utilisation samples and each stage's share of them, the `ready in` lines, the budget's cut, the records a later call
resumes from. The scripts themselves run on the CPU with DEVICE=cpu SCALE=tiny (minutes: not a test)."""

import importlib.util
import json
import logging
import subprocess
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("gpucheck", ROOT / "scripts" / "gpucheck.py")
gc = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(gc)


def _recipe(scale: str, tmp_path: Path) -> dict:
    out = tmp_path / "recipe.yaml"
    gc.main(["recipe", "paper-check", scale, str(ROOT / "recipes" / "blender-dvgo-paper-official.yaml"), str(out)])
    import yaml

    return yaml.safe_load(out.read_text())


def _lego_like(tmp_path: Path, train: int = 100, test: int = 0) -> Path:
    scene = tmp_path / "lego"
    scene.mkdir(parents=True)
    (scene / "transforms_train.json").write_text(json.dumps({"frames": [{}] * train}))
    if test:
        (scene / "transforms_test.json").write_text(json.dumps({"frames": [{}] * test}))
    return scene


def test_held_out_views_as_eval_renders_them(tmp_path):
    assert gc.held_out_views(_lego_like(tmp_path), 8) == 13  # views 0, 8, ..., 96
    assert gc.held_out_views(_lego_like(tmp_path / "b", 100, 200), 8) == 200  # the test split, when there is one


def test_plan_at_the_targets_gives_the_official_steps_inside_the_budget(tmp_path):
    """At the GPU speed targets (docs/gpu.md) the paper chain fits the official 20,000 joint steps in 540 s; the plan's
    numbers are the formula's."""
    rec = _recipe("full", tmp_path)
    s = gc.settings("paper-check", "full", env={})
    plan = gc.plan_chain(rec, 13, s)
    assert rec["data"]["image_size"] == 800 and rec["pretrain"]["res"] == [160, 200, 256]
    assert plan["iters"] == 20000 and plan["fits"]
    assert plan["expected_s"] <= s["BUDGET_S"] == 540
    # a DVGO-256 step of 8192 rays at 5 M rays/s x 256/160; a mixture's 2.5x that
    assert plan["seconds_per_step"]["baseline"] == pytest.approx(8192 / 5e6 * 1.6, rel=1e-3)
    assert plan["seconds_per_step"]["top2"] == pytest.approx(2.5 * plan["seconds_per_step"]["baseline"], rel=1e-3)
    # geometry 5000 steps at 100^3, each expert 1000
    assert plan["pretrain_s"] == pytest.approx(8192 / 5e6 * (5000 * 100 + 1000 * (160 + 200 + 256)) / 160, abs=0.1)


def test_plan_rounds_down_and_says_when_the_least_does_not_fit(tmp_path):
    rec = _recipe("full", tmp_path)
    s = gc.settings("paper-check", "full", env={"SPEED": "0.5"})
    plan = gc.plan_chain(rec, 13, s)
    per_step = sum(plan["seconds_per_step"].values())
    s_budget = float(s["BUDGET_S"])
    window = s_budget - plan["fixed_s"] - plan["pretrain_s"] - plan["tail_s"]
    assert plan["iters"] % 100 == 0 and 1000 <= plan["iters"] < 20000
    assert plan["iters"] * per_step <= window + 1e-6 < (plan["iters"] + 100) * per_step
    assert plan["expected_s"] <= s_budget and plan["fits"]
    slow = gc.plan_chain(rec, 13, gc.settings("paper-check", "full", env={"SPEED": "0.16"}))
    assert slow["iters"] == 1000 and not slow["fits"] and slow["expected_s"] > s_budget
    assert "does not fit" in gc.describe_plan(slow) and "does not fit" not in gc.describe_plan(plan)


def test_settings_take_the_environment_and_survive_bash():
    values = gc.settings("paper-check", "full", env={"BUDGET_S": "300", "ORACLE_MAP_RES": "8, 16 $(x)"})
    assert values["BUDGET_S"] == "300" and values["SPEED"] == 1
    script = gc.shell_assignments(values) + 'printf "%s|%s|%s" "$BUDGET_S" "$ORACLE_MAP_RES" "$F_MIN"'
    out = subprocess.run(["bash", "-c", script], capture_output=True, text=True, check=True).stdout
    assert out == "300|8, 16 $(x)|1000"


NVIDIA_SMI = """\
timestamp, index, utilization.gpu [%], memory.used [MiB]
2026/11/26 12:00:00.000, 0, 10, 1000
2026/11/26 12:00:00.500, 0, 30, 1200
2026/11/26 12:00:00.500, 1, 99, 9999
2026/11/26 12:00:01.000, 0, [N/A], 1300
2026/11/26 12:00:01.500, 0, 90, 2000
2026/11/26 12:00:02.000, 0, 50
"""


def test_nvidia_smi_samples_and_a_stage_window():
    samples = gc.parse_samples(NVIDIA_SMI)
    t0 = time.mktime(time.strptime("2026/11/26 12:00:00", "%Y/%m/%d %H:%M:%S"))
    assert [(round(t - t0, 3), u, m) for t, u, m in samples] == [(0.0, 10, 1000), (0.5, 30, 1200), (1.5, 90, 2000)]
    assert gc.parse_samples(NVIDIA_SMI, index=1)[0][1:] == (99, 9999)
    stats = gc.window_stats(samples, t0 + 0.4, t0 + 1.6)
    assert stats == {"mean": 60, "max": 90, "mem_max": 2000, "samples": 2}
    assert gc.window_stats(samples, t0 + 1.4, t0 + 1.45)["mean"] == 90  # shorter than a period: the nearest sample
    assert gc.window_stats(samples, t0 + 60, t0 + 61) is None
    assert gc.window_stats([], t0, t0 + 1) is None


def test_ready_lines_of_a_stage_log(caplog):
    """The lines boostnerf_cli.startup writes, read back with their parts; compile seconds summed."""
    from boostnerf_cli.startup import Clock

    clock = Clock()
    with clock.part("scene"):
        pass
    with caplog.at_level(logging.INFO, logger="boostnerf_cli"):
        clock.ready("dvgo-160")
    text = caplog.text + "\n[dvgo-160] step 1\ntop2: ready in 12.5 s\ngpucheck: torch.compile took 3.5 s in this " \
        "process\ngpucheck: torch.compile took 1.0 s in this process\n"
    ready = gc.ready_lines(text)
    assert [r["what"] for r in ready] == ["dvgo-160", "top2"] and ready[1]["seconds"] == 12.5
    assert ready[0]["parts"].startswith("scene ") and ready[1]["parts"] == ""
    assert gc.compile_seconds(text) == 4.5 and gc.compile_seconds("nothing") is None
    line = gc.stage_line("(b) finetune top2", "OK", 20.0, text)
    assert "ready: dvgo-160 " in line and "top2 12.5 s" in line and "compile 4.5 s" in line
    failed = gc.stage_line("(a) finetune", "FAIL", 3.0, "Error: V_D keeps no cell\n" + text.splitlines()[-1] + "\n")
    assert failed.endswith("(Error: V_D keeps no cell)"), failed  # the error, not the wrapper's compile line


def test_each_stage_gets_the_utilisation_of_its_window(tmp_path):
    t0 = time.mktime(time.strptime("2026/11/26 12:00:00", "%Y/%m/%d %H:%M:%S"))
    (tmp_path / "logs").mkdir()
    (tmp_path / "util.csv").write_text(NVIDIA_SMI)
    for name, a, b in (("first", 0.0, 0.6), ("second", 1.2, 1.8)):
        log = tmp_path / "logs" / f"{name}.log"
        log.write_text(f"{name}: ready in 0.3 s (scene 0.1 s)\n")
        gc.record_stage(tmp_path, name, "OK", t0 + a, t0 + b, log)
    stages = gc.read_stages(tmp_path)
    assert [s["log"] for s in stages] == [str(tmp_path / "logs" / "first.log"), str(tmp_path / "logs" / "second.log")]
    text = gc.summary(stages, gc.read_samples(tmp_path), t0, "GPU")
    rows = {line.split("|")[2].strip(): [c.strip() for c in line.split("|")[1:-1]] for line in text.splitlines()
            if line.startswith("| OK")}
    assert rows["first"][7] == "20 / 30" and rows["second"][7] == "90 / 90"
    assert rows["first"][5] == "first 0.3 s (scene 0.1 s)" and rows["first"][4] == "0"


def test_a_later_call_reads_the_stage_that_trained_the_model(tmp_path):
    """A model resumed by a second call: its utilisation is that of the call whose log says it started training."""
    calls = []
    for i, util in enumerate((20, 80)):
        d = tmp_path / f"call-{i}"
        (d / "logs").mkdir(parents=True)
        log = d / "logs" / "ft.log"
        log.write_text("top1: ready in 2.0 s\n" if i == 1 else "interrupted\n")
        t = 1000.0 + 100 * i
        gc.record_stage(d, "(3) finetune top1", "OK" if i else "CUT", t, t + 10, log)
        calls.append((gc.read_stages(d), [(t + 5, float(util), 1.0)]))
    assert gc.training_stage("top1", "(3) finetune top1", calls)["mean"] == 80
    assert gc.training_stage("top2", "(3) finetune top1", calls) is None


def test_steady_rate_leaves_out_the_first_interval():
    history = [{"step": 250, "seconds": 30.0}, {"step": 500, "seconds": 32.5}, {"step": 750, "seconds": 35.5}]
    rate, extra = gc.steady(history, 1000, 40.0)
    assert rate == pytest.approx(0.01) and extra == pytest.approx(30.0)
    assert gc.steady(history[:1], 1000, 40.0) == (None, None)


def test_a_stage_past_the_budget_is_cut_and_a_spent_budget_starts_none(tmp_path):
    """gpucheck-lib.sh's `check`: OK, FAIL, CUT at the deadline (the command stopped), and 'not started' after it."""
    script = f"""
HERE={ROOT}; OUT={tmp_path}; DEV=cpu; BUDGET_S=2; NAME=t
. "$HERE/scripts/gpucheck-lib.sh"
mkdir -p "$OUT/logs" "$OUT/.pids"; : >"$OUT/stages.tsv"
DEADLINE=$(( EPOCHSECONDS + 8 ))  # `check` starts nothing with under 5 s left
check ok true; check bad false; check slow sleep 60
check late true
echo "rcs $?"
"""
    t = time.monotonic()
    out = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=120).stdout
    assert time.monotonic() - t < 60
    status = [line.split("\t")[:2] for line in (tmp_path / "stages.tsv").read_text().splitlines()]
    assert status == [["ok", "OK"], ["bad", "FAIL"], ["slow", "CUT"], ["late", "CUT"]]
    assert "not started: the budget of 2 s was spent" in (tmp_path / "logs" / "late.log").read_text()
    assert "rcs 124" in out
