"""The training loop: resume from a checkpoint equals an uninterrupted run; the NaN guard."""

import pytest
import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.dvgo import DVGOConfig, DVGOExpert
from boostnerf_cli.recipe import TrainRecipe
from boostnerf_cli.render.renderer import RenderSettings
from boostnerf_cli.scenes import load_scene
from boostnerf_cli.stages.pretrain import FieldTask, growth_schedule
from boostnerf_cli.train import RayData, Schedule, train


class Interrupt(Exception):
    pass


def _task(scene, iters):
    torch.manual_seed(0)
    model = DVGOExpert(DVGOConfig(res=12, hidden=8, layers=1), scene.bbox)
    growth = growth_schedule(iters, [0.2])
    model.regrid(12**3 // 2)
    tcfg = TrainRecipe(batch_rays=128, occupancy_every=7, growth=[0.2])
    settings = RenderSettings(step=0.5 * model.unit, near=scene.near, far=scene.far, bbox=scene.bbox)
    return FieldTask(model, settings, tcfg, skip=None, base_mask=None, growth_steps=growth, final_voxels=12**3)


def test_resume_after_a_crash_matches_an_uninterrupted_run(tiny_scene, tmp_path):
    scene = load_scene(tiny_scene)
    rays = RayData.from_split(scene.splits["train"], scene.bbox, scene.near, scene.far)
    sched = Schedule(iters=24, batch_rays=128, log_every=4, checkpoint_every=5)

    ref = _task(scene, 24)
    train(ref, rays, sched, seed=3, title="ref")

    ckpt = tmp_path / "run.pt"
    crashing = _task(scene, 24)
    real_loss = crashing.loss

    def loss(o, d, c, step):
        if step == 13:
            raise Interrupt()
        return real_loss(o, d, c, step)

    crashing.loss = loss
    with pytest.raises(Interrupt):
        train(crashing, rays, sched, seed=3, title="crash", checkpoint=ckpt)
    assert ckpt.exists()  # the step-10 checkpoint survived the crash

    resumed = _task(scene, 24)
    result = train(resumed, rays, sched, seed=3, title="resume", checkpoint=ckpt)
    assert result.iterations == 24
    for (k, a), (_, b) in zip(ref.model.state_dict().items(), resumed.model.state_dict().items()):
        assert torch.allclose(a, b, atol=1e-6), k
    assert [h["step"] for h in result.history] == [4, 8, 12, 16, 20, 24]


def test_repeated_non_finite_steps_stop_the_run(tiny_scene):
    scene = load_scene(tiny_scene)
    rays = RayData.from_split(scene.splits["train"], scene.bbox, scene.near, scene.far)
    task = _task(scene, 50)
    real_loss = task.loss
    task.loss = lambda o, d, c, step: (real_loss(o, d, c, step)[0] * float("nan"), {})
    with pytest.raises(BoostNerfError, match="training diverged"):
        train(task, rays, Schedule(iters=50, batch_rays=64, max_bad_steps=5), seed=0, title="nan")


def test_isolated_non_finite_steps_are_skipped_and_counted(tiny_scene):
    scene = load_scene(tiny_scene)
    rays = RayData.from_split(scene.splits["train"], scene.bbox, scene.near, scene.far)
    task = _task(scene, 12)
    real_loss = task.loss

    def loss(o, d, c, step):
        value, logs = real_loss(o, d, c, step)
        return (value * float("inf"), logs) if step in (3, 7) else (value, logs)

    task.loss = loss
    result = train(task, rays, Schedule(iters=12, batch_rays=64), seed=0, title="inf")
    assert result.skipped_steps == 2
    assert all(torch.isfinite(p).all() for p in task.model.parameters())
