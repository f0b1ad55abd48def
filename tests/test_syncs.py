"""On a GPU, nothing in a training step or a render chunk makes the host wait for the device.

Each step runs on the simulated GPU (tests/simdevice.py), where every copy between host and device dispatches like
any operator, and `SyncCounter` counts what would make a real GPU's host wait (`.item()`, `nonzero`, boolean masks,
blocking copies, ...). After the warm-up (a budget is sized by one wait on its first use) an expert's training step,
a mixture's, and a chunk of rendering wait not once; the training loop reads the steps' outcomes and logs on its
logging steps only, which are not counted.
"""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from helpers import TOY_BOX, family_expert, routed_mixture, toward_box_rays
from simdevice import GPU, SyncCounter, simulated_gpu

from boostnerf_cli.moe.mixture import Mixture
from boostnerf_cli.recipe import MoERecipe, TrainRecipe
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.renderer import RenderSettings, render_rays
from boostnerf_cli.tasks import FieldTask, MixtureTask
from boostnerf_cli.train import RayData, Schedule, train

WARMUP, STEPS = 3, 4


def _settings(step: float = 0.1) -> RenderSettings:
    return RenderSettings(step=step, near=0.1, far=6.0, bbox=TOY_BOX.to(GPU), color_threshold=1e-4)


def _occupancy() -> OccupancyGrid:
    occupied = torch.zeros(8, 8, 8, dtype=torch.bool)
    occupied[2:6, 2:6, 2:6] = True
    return OccupancyGrid(occupied, TOY_BOX).to(GPU)


def _mixture(kind: str) -> Mixture:
    return routed_mixture(kind, GPU)


def _steps_counted(task, rays: RayData) -> SyncCounter:
    """Train `task` for WARMUP + STEPS + 1 steps on the simulated GPU; count the waits of the STEPS steps after the
    warm-up (the last step is a logging step, and not counted)."""
    counter = SyncCounter()
    before = task.before_step

    def before_step(step: int) -> bool:
        counter.active = WARMUP <= step < WARMUP + STEPS
        return before(step)

    task.before_step = before_step
    counter.active = False
    with counter:
        train(task, rays.to(GPU), Schedule(WARMUP + STEPS + 1, batch_rays=64, log_every=1000,
                                           checkpoint_every=1000), seed=0, title="t")
    return counter


@pytest.mark.parametrize("family", ["dvgo", "tensorf", "ngp"])
def test_an_experts_training_step_and_render_chunk_never_wait(family):
    with simulated_gpu():
        model = family_expert(family).to(GPU)
        task = FieldTask(model, _settings(), TrainRecipe(occupancy_every=0), skip=_occupancy(), base_mask=None)
        assert task.packer.static  # what a GPU gets
        counter = _steps_counted(task, toward_box_rays())
        assert counter.total == 0, dict(counter.syncs)

        rays, settings, occupancy = toward_box_rays(256).to(GPU), _settings(), _occupancy()
        with torch.no_grad():
            for _ in range(WARMUP):
                render_rays(model, rays.origins, rays.dirs, settings, occupancy, packer=task.packer)
            with SyncCounter() as chunk:
                render_rays(model, rays.origins, rays.dirs, settings, occupancy, packer=task.packer)
        assert chunk.total == 0, dict(chunk.syncs)


@pytest.mark.parametrize("kind", ["top1", "top2", "ens"])
def test_a_mixtures_training_step_and_render_chunk_never_wait(kind):
    with simulated_gpu():
        mix = _mixture(kind)
        task = MixtureTask(mix, _settings(), TrainRecipe(), MoERecipe(lam=0.01))
        counter = _steps_counted(task, toward_box_rays())
        assert counter.total == 0, dict(counter.syncs)

        rays, settings = toward_box_rays(256).to(GPU), _settings()
        with torch.no_grad():
            mix.eval()
            for _ in range(WARMUP):
                render_rays(mix, rays.origins, rays.dirs, settings, mix.skip, packer=task.packer)
            with SyncCounter() as chunk:
                render_rays(mix, rays.origins, rays.dirs, settings, mix.skip, packer=task.packer)
        assert chunk.total == 0, dict(chunk.syncs)


def test_the_counter_sees_the_waits_of_the_dynamic_packing():
    """The same expert step with the exact (dynamic) packing waits on every filter: the counter is not blind."""
    from boostnerf_cli.render.packing import DYNAMIC

    with simulated_gpu():
        task = FieldTask(family_expert("dvgo").to(GPU), _settings(), TrainRecipe(occupancy_every=0), skip=_occupancy(),
                         base_mask=None, packer=DYNAMIC)
        counter = _steps_counted(task, toward_box_rays())
    assert counter.syncs["aten.nonzero.default"] >= 2 * STEPS, dict(counter.syncs)


@pytest.mark.parametrize("kind", ["dvgo", "top2"])
def test_static_budgets_train_what_the_exact_packing_trains(kind):
    """On the CPU, a task with static budgets (small ones, so that pads fill them) trains the same parameters as one
    with the exact lists: pads add nothing and take no gradient."""
    from boostnerf_cli.render.packing import DYNAMIC, Budgets

    rays, settings = toward_box_rays(), RenderSettings(step=0.1, near=0.1, far=6.0, bbox=TOY_BOX)
    results = []
    for packer in (DYNAMIC, Budgets(quantum=64)):
        torch.manual_seed(0)
        if kind == "dvgo":
            model = family_expert("dvgo")
            occupied = torch.zeros(8, 8, 8, dtype=torch.bool)
            occupied[2:6, 2:6, 2:6] = True
            task = FieldTask(model, settings, TrainRecipe(occupancy_every=0), skip=OccupancyGrid(occupied, TOY_BOX),
                             base_mask=None, packer=packer)
        else:
            mix = routed_mixture("top2", torch.device("cpu"))
            model, task = mix, MixtureTask(mix, settings, TrainRecipe(), MoERecipe(lam=0.01), packer=packer)
        train(task, rays, Schedule(6, batch_rays=64, log_every=3, checkpoint_every=1000), seed=0, title="t")
        results.append({k: v.detach().clone() for k, v in model.state_dict().items()})
    exact, static = results
    assert exact.keys() == static.keys()
    for k in exact:
        assert torch.allclose(exact[k], static[k], atol=1e-6, rtol=0), k


def test_a_step_that_overflows_its_budget_is_skipped_counted_and_the_budget_grows(caplog):
    """Budgets sized exactly (no margin) on the first step overflow on a later batch that keeps more samples: that
    step's update is skipped (the parameters stay as they were), counted in the result and said, and the budget
    grows past the largest count seen, so the run goes on."""
    from boostnerf_cli.render.packing import Budgets

    packer = Budgets(margin=1.0, quantum=1)
    model = family_expert("dvgo")
    occupied = torch.zeros(8, 8, 8, dtype=torch.bool)
    occupied[2:6, 2:6, 2:6] = True
    task = FieldTask(model, RenderSettings(step=0.1, near=0.1, far=6.0, bbox=TOY_BOX), TrainRecipe(occupancy_every=0),
                     skip=OccupancyGrid(occupied, TOY_BOX), base_mask=None, packer=packer)
    sizes = []
    real_settle = packer.settle

    def settle():
        sizes.append(dict(packer.sizes()))
        return real_settle()

    packer.settle = settle
    rays = toward_box_rays(512)
    away = torch.arange(512) % 2 == 1
    rays = RayData(rays.origins, torch.where(away[:, None], -rays.dirs, rays.dirs), rays.rgb)  # half miss the box
    result = train(task, rays, Schedule(12, batch_rays=32, log_every=100, checkpoint_every=1000), seed=0, title="t")
    assert result.skipped_steps > 0
    assert "more samples than the sample budget held, step skipped" in caplog.text  # the warning record, said or not
    grown = packer.sizes()
    assert any(grown[name] > sizes[0][name] for name in sizes[0]), (sizes[0], grown)


class _Views(SimpleNamespace):
    """Four posed cameras: what render_split reads of a dataset split."""

    def __init__(self, poses, intrinsics, height, width):
        super().__init__(poses=poses, intrinsics=intrinsics, height=height, width=width)

    def __len__(self) -> int:
        return self.poses.shape[0]


def test_rendering_a_split_sizes_its_budgets_once():
    """Every image of a split reuses the budgets the images before it sized: only the first waits to size them (and
    a budget sized on one image's first chunk is more likely to overflow on a later chunk, re-rendering the image)."""
    from boostnerf_cli.models import LoadedModel, render_split

    with simulated_gpu():
        model = family_expert("dvgo").to(GPU)
        loaded = LoadedModel("dvgo-8", "expert", model, _occupancy(), 0.1, TOY_BOX.to(GPU), 0)
        scene = SimpleNamespace(render_settings=lambda step, bbox, thr: _settings(step))
        pose = torch.eye(4)
        pose[2, 3] = 3.0  # on the +z axis, looking at the box
        intrinsics = torch.tensor([12.0, 12.0, 8.0, 8.0])  # fx, fy, cx, cy
        split = _Views(pose.repeat(4, 1, 1), intrinsics.repeat(4, 1), 16, 16)
        waits = []
        images = render_split(loaded, scene, split, GPU)
        while True:
            with SyncCounter() as counter:
                if next(images, None) is None:
                    break
            waits.append(counter.total)
    # a later image waits 8 times, to move its pose to the device, its three pictures and two sample counts back,
    # and to read the peaks of its two budgets (density, colour) when they are settled; sizing them again would add 2
    assert len(waits) == 4 and waits[0] > 8 and waits[1:] == [8, 8, 8], waits
