"""Train-PSNR trend warning, recipe values for resolutions a recipe does not list, family-specific
checkpoint signatures (a changed TensoRF or NGP setting is noticed on resume)."""

from __future__ import annotations

import json
import logging

import pytest
import torch
from conftest import REMOVE, make_recipe, run_cli

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.recipe import PretrainRecipe
from boostnerf_cli.stages.pretrain import expert_options
from boostnerf_cli.train import PsnrTrend, RayData, Schedule, train


def _trend(means: list[float]) -> list[str]:
    trend, warnings = PsnrTrend(), []
    for step, m in enumerate(means, 1):
        for v in (m - 0.1, m + 0.1):  # two steps per interval, mean m
            trend.add(v)
        trend.close_interval()
        w = trend.falling_warning(step * 100)
        if w:
            warnings.append(w)
    return warnings


def test_a_falling_train_psnr_warns_once_naming_the_likely_cause():
    warnings = _trend([20.0, 22.6, 22.4, 21.5, 20.9, 20.1, 19.0])
    assert len(warnings) == 1
    assert "22.60 -> 20.90" in warnings[0] and "--no-skip" in warnings[0] and "lr_grid" in warnings[0]


@pytest.mark.parametrize("means", [
    [20.0, 21.0, 22.0, 23.0, 24.0],  # learning
    [22.0, 21.9, 22.1, 21.8, 22.0, 21.9],  # noise around a plateau
    [22.0, 21.95, 21.9, 21.85, 21.8],  # falling, but by under 0.5 dB in all
])
def test_no_warning_while_learning_or_on_a_plateau(means):
    assert _trend(means) == []


class _FallingTask:
    """A task whose logged PSNR falls by 1 dB every 10 steps (its loss still has a gradient)."""

    def __init__(self):
        self.w = torch.nn.Parameter(torch.zeros(1))

    def param_groups(self):
        return [{"params": [self.w], "lr": 1e-3}]

    def loss(self, origins, dirs, rgb, alpha, step):
        return (self.w ** 2).sum() + 0 * origins.sum(), {"psnr": 30.0 - step // 10}

    def before_step(self, step):
        return False

    def state(self):
        return {"w": self.w.detach().clone()}

    def load_state(self, state):
        self.w.data.copy_(state["w"])


def test_the_training_loop_warns_when_the_train_psnr_keeps_falling(capsys):
    rays = RayData(torch.zeros(16, 3), torch.ones(16, 3), torch.zeros(16, 3))
    result = train(_FallingTask(), rays, Schedule(60, batch_rays=4, log_every=10), seed=0, title="t")
    err = capsys.readouterr().err
    assert err.count("fell for 3 logging intervals") == 1
    assert [h["psnr_mean"] for h in result.history][:3] == [30.0, 29.0, 28.0]


def test_a_resolution_the_recipe_does_not_list_takes_the_nearest_listed_value(caplog):
    rec = PretrainRecipe(model="dvgo", res=[48, 64, 100], dvgo={"hidden": {64: 64, 72: 96, 80: 128}, "layers": 2})
    caplog.set_level(logging.INFO, logger="boostnerf_cli")
    assert expert_options(rec, 72, say=True) == {"hidden": 96, "layers": 2, "res": 72} and caplog.messages == []
    assert expert_options(rec, 48, say=True)["hidden"] == 64
    assert expert_options(rec, 100, say=True)["hidden"] == 128
    assert expert_options(rec, 76, say=True)["hidden"] == 128  # a tie: the larger
    said = caplog.messages
    assert len(said) == 3 and "no value for res 48: using 64" in said[0] and "(64)" in said[0]
    assert expert_options(rec, 48)["hidden"] == 64 and len(caplog.messages) == 3  # said only when asked to
    with pytest.raises(BoostNerfError, match="empty mapping"):
        expert_options(PretrainRecipe(dvgo={"hidden": {}}), 64)


def test_res_flag_over_a_per_resolution_recipe_runs_and_says_what_it_chose(tmp_path, tiny_scene):
    recipe = make_recipe(tmp_path / "r.yaml", pretrain={
        "iters": 6,
        "geometry": {"res": 10, "iters": 10, "batch_rays": 128, "alpha_init": REMOVE},
        "train": {"batch_rays": 128, "log_every": 3, "checkpoint_every": 3, "occupancy_every": REMOVE},
        "dvgo": {"hidden": {12: 8, 16: 16}},
    }, moe=REMOVE)
    proc = run_cli("pretrain", "-w", str(tmp_path / "ws"), "--data", str(tiny_scene), "--recipe", str(recipe),
                   "--res", "10,20", "--device", "cpu")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "pretrain.dvgo.hidden lists no value for res 10: using 8" in proc.stderr
    assert "no value for res 20: using 16" in proc.stderr
    assert json.loads((tmp_path / "ws" / "experts" / "dvgo-20.json").read_text())["iterations"] == 6


FAMILY_SECTIONS = {
    "tensorf": {"hidden": 8, "layers": 1, "density_rank": 2, "app_rank": 2, "app_dim": 4, "fit_steps": 5},
    "ngp": {"hidden": 8, "log2_table": 8, "base_res": 4, "max_res": 16, "grid_res": 8},
}
FAMILY_RES = {"tensorf": 8, "ngp": 3}


def _family_recipe(path, family: str, **section_changes):
    """A small one-expert recipe of `family` with its FAMILY_SECTIONS entry (changed by `section_changes`)."""
    return make_recipe(path, pretrain={
        "model": family,
        "res": [FAMILY_RES[family]],
        "iters": 40,
        "geometry": {"res": 8, "iters": 5, "batch_rays": 64, "alpha_init": REMOVE},
        "train": {"batch_rays": 64, "log_every": 5, "checkpoint_every": 5, "occupancy_every": REMOVE},
        "dvgo": REMOVE,
        family: {**FAMILY_SECTIONS[family], **section_changes},
    }, moe=REMOVE)


@pytest.mark.parametrize("family", ["tensorf", "ngp"])
def test_a_changed_family_setting_is_noticed_on_resume(tmp_path, tiny_scene, family):
    """The checkpoint signature records the family's own section (it recorded `dvgo` whatever the family)."""
    recipe = _family_recipe(tmp_path / "a.yaml", family)
    ws = tmp_path / "ws"
    proc = run_cli("pretrain", "-w", str(ws), "--data", str(tiny_scene), "--recipe", str(recipe), "--device", "cpu",
                   "--iters", "40")
    assert proc.returncode == 0, proc.stderr[-1500:]
    # a checkpoint of an unfinished run, then the same run with one family setting changed
    name = f"{family}-{FAMILY_RES[family]}"
    ckpt = ws / "checkpoints" / f"{name}.pt"
    (ws / "experts" / f"{name}.safetensors").unlink()
    (ws / "experts" / f"{name}.json").unlink()
    killed = run_cli("pretrain", "-w", str(ws), "--data", str(tiny_scene), "--recipe", str(recipe), "--device",
                     "cpu", "--iters", "40", env_extra={"BOOSTNERF_TEST_KILL": "checkpoint:2"})
    assert killed.returncode != 0 and ckpt.exists()
    changed = _family_recipe(tmp_path / "b.yaml", family, hidden=12)
    proc = run_cli("pretrain", "-w", str(ws), "--data", str(tiny_scene), "--recipe", str(changed), "--device", "cpu",
                   "--iters", "40")
    assert proc.returncode == 2 and "other settings" in proc.stderr and f"pretrain.{family}.hidden:" in proc.stderr, \
        proc.stderr
