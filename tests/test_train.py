"""The training loop: resume from a checkpoint equals an uninterrupted run; the NaN guard."""

import logging
import sys

import pytest
import torch

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.fields.dvgo import DVGOConfig, DVGOExpert
from boostnerf_cli.lineage import BaselineSpec
from boostnerf_cli.recipe import TrainRecipe
from boostnerf_cli.render.occupancy import OccupancyGrid
from boostnerf_cli.render.renderer import RenderSettings
from boostnerf_cli.scenes import load_scene
from boostnerf_cli.stages.pretrain import growth_schedule
from boostnerf_cli.tasks import FieldTask
from boostnerf_cli.train import RayData, Schedule, TrainCheckpoint, train


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


def test_the_grid_reaches_its_final_size_however_few_the_steps():
    """`pretrain --iters 1` saved dvgo-8 with 7 x 7 x 5 vertices, half its voxels: the one growth step fell on step 1,
    which a run of steps 0 .. iters - 1 never reaches. Every growth step now lies inside the run."""
    for iters in range(1, 40):
        steps = growth_schedule(iters, [0.1, 0.2, 0.3])
        assert all(0 < s < iters for s in steps), (iters, steps)
        assert len(steps) == len(set(steps))
    assert growth_schedule(1, [0.1, 0.2, 0.3]) == () and growth_schedule(100, [0.1, 0.2, 0.3]) == (10, 20, 30)


def test_resume_after_a_crash_matches_an_uninterrupted_run(tiny_scene, tmp_path):
    scene = load_scene(tiny_scene)
    rays = RayData.from_split(scene.splits["train"], scene.bbox, scene.near, scene.far)
    sched = Schedule(iters=24, batch_rays=128, log_every=4, checkpoint_every=5)

    ref = _task(scene, 24)
    train(ref, rays, sched, seed=3, title="ref")

    ckpt = tmp_path / "run.pt"
    crashing = _task(scene, 24)
    real_loss = crashing.loss

    def loss(o, d, c, a, step):
        if step == 13:
            raise Interrupt()
        return real_loss(o, d, c, a, step)

    crashing.loss = loss
    with pytest.raises(Interrupt):
        train(crashing, rays, sched, seed=3, title="crash", checkpoint=TrainCheckpoint(ckpt))
    assert ckpt.exists()  # the step-10 checkpoint survived the crash

    resumed = _task(scene, 24)
    result = train(resumed, rays, sched, seed=3, title="resume", checkpoint=TrainCheckpoint(ckpt))
    assert result.iterations == 24
    sd, sd2 = ref.model.state_dict(), resumed.model.state_dict()
    assert sd.keys() == sd2.keys()
    for k in sd:
        assert torch.allclose(sd[k], sd2[k], atol=1e-6), k
    assert [h["step"] for h in result.history] == [4, 8, 12, 16, 20, 24]


def test_repeated_non_finite_steps_stop_the_run(tiny_scene):
    scene = load_scene(tiny_scene)
    rays = RayData.from_split(scene.splits["train"], scene.bbox, scene.near, scene.far)
    task = _task(scene, 50)
    real_loss = task.loss
    task.loss = lambda o, d, c, a, step: (real_loss(o, d, c, a, step)[0] * float("nan"), {})
    with pytest.raises(BoostNerfError, match="training diverged"):
        train(task, rays, Schedule(iters=50, batch_rays=64, max_bad_steps=5), seed=0, title="nan")


def test_isolated_non_finite_steps_are_skipped_and_counted(tiny_scene):
    scene = load_scene(tiny_scene)
    rays = RayData.from_split(scene.splits["train"], scene.bbox, scene.near, scene.far)
    task = _task(scene, 12)
    real_loss = task.loss

    def loss(o, d, c, a, step):
        value, logs = real_loss(o, d, c, a, step)
        return (value * float("inf"), logs) if step in (3, 7) else (value, logs)

    task.loss = loss
    result = train(task, rays, Schedule(iters=12, batch_rays=64), seed=0, title="inf")
    assert result.skipped_steps == 2
    assert all(torch.isfinite(p).all() for p in task.model.parameters())


def test_each_model_says_when_it_is_ready_and_its_report_keeps_the_seconds(tmp_path, tiny_scene, tiny_recipe,
                                                                           monkeypatch, caplog):
    """pretrain says `NAME: ready in X s (parts)` for the geometry and each expert, and each expert's report keeps
    `startup_seconds`: from the end of the model before it (its held-out scoring included) to its first step, so
    the work of the model before is not counted as this one's start-up."""
    import json
    import logging
    import re
    import time

    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.recipe import load_recipe
    from boostnerf_cli.stages import pretrain as stage
    from boostnerf_cli.startup import CLOCK
    from boostnerf_cli.workspace import Workspace

    rec = load_recipe(tiny_recipe)
    rec.pretrain.res, rec.pretrain.iters, rec.pretrain.geometry.iters = [8, 12], 4, 4
    real, scored = stage._test_psnr, []

    def slow_scoring(*args, **kwargs):
        if not scored:  # the first expert's own work after training: the next expert must not count it
            time.sleep(3.0)
        scored.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(stage, "_test_psnr", slow_scoring)
    ws = Workspace(tmp_path / "ws")
    CLOCK.begin()  # as the CLI does for each command (an earlier test in this process has used the clock)
    with caplog.at_level(logging.INFO, logger="boostnerf_cli"):
        stage.run(Survey(ws), tiny_scene, rec, "cpu", False)
    said = {m.group(1): float(m.group(2)) for m in
            (re.match(r"([\w-]+): ready in ([\d.]+) s \((?:scene|rays|models|digests) ", r.getMessage())
             for r in caplog.records) if m}
    assert set(said) >= {"geometry", "dvgo-8", "dvgo-12"}, caplog.text
    for name in ("dvgo-8", "dvgo-12"):
        report = json.loads(ws.expert_report_path(name).read_text())
        assert report["startup_seconds"] == pytest.approx(said[name], abs=0.06)
    assert said["dvgo-12"] < 3.0, said  # dvgo-8's three-second scoring is not dvgo-12's start-up


def test_skipped_steps_are_counted_warned_and_in_the_stage_report(tmp_path, tiny_scene, tiny_recipe, monkeypatch,
                                                                   capsys):
    import json

    from boostnerf_cli.cli import say_messages
    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.recipe import load_recipe
    from boostnerf_cli.stages import pretrain as stage
    from boostnerf_cli.workspace import Workspace

    say_messages()  # the stage's messages on stderr, as the CLI says them, whatever ran before
    rec = load_recipe(tiny_recipe)
    rec.pretrain.res, rec.pretrain.iters, rec.pretrain.geometry.iters = [12], 12, 10
    real = FieldTask.loss

    def loss(self, o, d, c, a, step):
        value, logs = real(self, o, d, c, a, step)
        return (value * float("nan"), logs) if step in (3, 8) else (value, logs)

    monkeypatch.setattr(FieldTask, "loss", loss)
    ws = Workspace(tmp_path / "ws")
    stage.run(Survey(ws), tiny_scene, rec, "cpu", False)
    report = json.loads(ws.expert_report_path("dvgo-12").read_text())
    assert report["skipped_steps"] == 2 and report["iterations"] == 12
    err = capsys.readouterr().err
    assert "[dvgo-12] step 4: non-finite loss, step skipped (1 so far)" in err
    assert "[dvgo-12] step 9: non-finite loss, step skipped (2 so far)" in err


def test_non_finite_gradient_is_skipped_like_a_non_finite_loss(tiny_scene):
    scene = load_scene(tiny_scene)
    rays = RayData.from_split(scene.splits["train"], scene.bbox, scene.near, scene.far)
    task = _task(scene, 10)
    real_loss = task.loss

    def loss(o, d, c, a, step):
        value, logs = real_loss(o, d, c, a, step)
        if step == 4:  # finite loss whose gradient is infinite: d/dx sqrt(x) at 0
            value = value + torch.sqrt(task.model.density_table[0, 0] * 0.0)
        return value, logs

    task.loss = loss
    before = [p.detach().clone() for p in task.model.parameters()]
    result = train(task, rays, Schedule(iters=10, batch_rays=64), seed=0, title="grad")
    assert result.skipped_steps == 1
    assert all(torch.isfinite(p).all() for p in task.model.parameters())
    assert any(not torch.equal(a, b) for a, b in zip(before, task.model.parameters()))


def test_a_state_with_non_finite_values_is_never_checkpointed(tiny_scene, tmp_path):
    scene = load_scene(tiny_scene)
    rays = RayData.from_split(scene.splits["train"], scene.bbox, scene.near, scene.far)
    task = _task(scene, 20)
    real_loss = task.loss

    def loss(o, d, c, a, step):
        if step == 7:  # an optimiser step that overflowed, in a cell no ray of the batch reaches
            with torch.no_grad():
                task.model.feature_table[0, 0] = float("inf")
        return real_loss(o, d, c, a, step)

    task.loss = loss
    ckpt = tmp_path / "run.pt"
    with pytest.raises(BoostNerfError, match="training diverged.*non-finite.*run.pt is kept"):
        train(task, rays, Schedule(iters=20, batch_rays=64, checkpoint_every=5), seed=0, title="inf",
              checkpoint=TrainCheckpoint(ckpt))
    state = torch.load(ckpt, weights_only=True)
    assert state["step"] == 5  # the last good one, untouched
    assert all(torch.isfinite(v).all() for v in state["task"]["model"].values() if v.is_floating_point())


def test_a_checkpoint_whose_numbers_changed_is_refused_as_damaged(tiny_scene, tmp_path):
    """A training checkpoint whose tensors changed after writing (here the optimiser's moments: a NaN, then a finite
    value) is one line that says it is damaged and to delete it, not a run that diverges at once and blames the
    learning rates; the same file untouched resumes."""
    scene = load_scene(tiny_scene)
    rays = RayData.from_split(scene.splits["train"], scene.bbox, scene.near, scene.far)
    ckpt = tmp_path / "run.pt"
    train(_task(scene, 4), rays, Schedule(iters=4, batch_rays=64, checkpoint_every=2), seed=0, title="a",
          checkpoint=TrainCheckpoint(ckpt))
    good = ckpt.read_bytes()
    for value in (float("nan"), 0.5):
        state = torch.load(ckpt, weights_only=True)
        moment = next(s["exp_avg"] for s in state["optim"]["state"].values() if s["exp_avg"].numel() > 1)
        moment.view(-1)[0] = value
        torch.save(state, ckpt)
        with pytest.raises(BoostNerfError, match=r"training checkpoint .*run.pt is damaged.*delete it to restart"):
            TrainCheckpoint(ckpt).load()
        ckpt.write_bytes(good)
    assert TrainCheckpoint(ckpt).load()["step"] == 4


def test_a_checkpoint_made_with_other_settings_is_refused(tiny_scene, tmp_path):
    scene = load_scene(tiny_scene)
    rays = RayData.from_split(scene.splits["train"], scene.bbox, scene.near, scene.far)
    ckpt = tmp_path / "run.pt"
    six, twelve = (BaselineSpec({"dvgo-12": "0" * 32}, iters, 0, {}).signature() for iters in (6, 12))
    train(_task(scene, 6), rays, Schedule(iters=6, batch_rays=64, checkpoint_every=3), seed=0, title="a",
          checkpoint=TrainCheckpoint(ckpt, six))
    assert torch.load(ckpt, weights_only=True)["step"] == 6  # also checkpointed after the last step
    with pytest.raises(BoostNerfError, match=r"run.pt was written with other settings \(moe.iters: 6, now 12\)"):
        train(_task(scene, 12), rays, Schedule(iters=12, batch_rays=64), seed=0, title="b",
              checkpoint=TrainCheckpoint(ckpt, twelve))


def test_a_changed_source_is_named_as_a_remade_model_not_by_its_digests():
    """A finetuning checkpoint (or a finished model) whose source (moe/init, or the baseline's largest expert) was
    remade since differs in its signature's inputs, digests: the message says the model it is made from was made
    again, with the digests shortened (in full they tell a user nothing about what to do); a setting is named by its
    recipe key."""
    from boostnerf_cli.lineage import describe_change

    was, now = "078c" * 16, "a1b2" * 16
    text = describe_change(BaselineSpec({"dvgo-16": was}, 6, 0, {}).signature(),
                           BaselineSpec({"dvgo-16": now}, 6, 0, {}).signature())
    assert was not in text and now not in text
    assert text == "the model it is made from was made again since (digest 078c078c..., now a1b2a1b2...)"
    assert describe_change(BaselineSpec({"dvgo-16": None}, 6, 0, {}).signature(),
                           BaselineSpec({"dvgo-16": now}, 6, 0, {}).signature()) == \
        "the model it is made from was made again since"
    assert describe_change(BaselineSpec({"dvgo-16": now}, 6, 0, {"batch_rays": 64}).signature(),
                           BaselineSpec({"dvgo-16": now}, 6, 0, {"batch_rays": 128}).signature()) == \
        "moe.train.batch_rays: 64, now 128"


def test_a_partial_recipe_section_keeps_that_sections_own_defaults(tmp_path):
    """moe.train with only batch_rays keeps finetuning's lower learning rates and no growth, not the
    pretraining defaults of TrainRecipe (which used to come back silently)."""
    from boostnerf_cli.recipe import MoERecipe, load_recipe

    path = tmp_path / "r.yaml"
    path.write_text("moe: {iters: 7, train: {batch_rays: 512}}\npretrain: {train: {lr_grid: 0.2}}\n")
    rec = load_recipe(path)
    finetune_defaults = MoERecipe().train
    assert rec.moe.train.batch_rays == 512 and rec.moe.iters == 7
    assert (rec.moe.train.lr_grid, rec.moe.train.lr_mlp, rec.moe.train.growth, rec.moe.train.occupancy_every) == (
        finetune_defaults.lr_grid, finetune_defaults.lr_mlp, [], 0)
    assert finetune_defaults.lr_grid != TrainRecipe().lr_grid  # the case that matters
    assert rec.pretrain.train.lr_grid == 0.2 and rec.pretrain.train.growth == TrainRecipe().growth


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf"), None])
def test_all_finite_finds_any_non_finite_gradient(bad):
    from boostnerf_cli.train import grads_finite

    def all_finite(params):
        return bool(grads_finite(params))

    params = [torch.zeros(5, requires_grad=True), torch.zeros(3, 2, requires_grad=True),
              torch.zeros(2, requires_grad=True)]
    params[0].grad = torch.tensor([1.0, -3e38, 0.0, 2.0, 3e38])  # huge but finite
    params[1].grad = torch.ones(3, 2)
    if bad is not None:
        params[1].grad[2, 1] = bad
    assert all_finite(params) is (bad is None)  # params[2] has no gradient: ignored
    assert all_finite([torch.zeros(1, requires_grad=True)])  # no gradient at all
    both = torch.zeros(4, requires_grad=True)
    both.grad = torch.tensor([float("inf"), 1.0, -float("inf"), 0.0])  # +inf and -inf in one tensor
    assert not all_finite([both])
    huge = torch.zeros(2, requires_grad=True)
    huge.grad = torch.tensor([3e38, 3e38])  # finite, but its sum overflows: refused, as documented
    assert not all_finite([huge])


def test_a_mask_over_the_geometrys_box_resumes_over_that_box(tiny_scene):
    """Until an expert's first refresh its mask is the geometry stage's grid, over the geometry's own box. A checkpoint
    stored only the cells, and the resume laid them over the expert's (tighter) box: an expert killed then trained
    to another model (weights up to 0.62 apart on a 32 px scene, 0.7 dB for an NGP expert)."""
    scene = load_scene(tiny_scene)
    task = _task(scene, 24)
    wide = scene.bbox.clone()
    wide[0] -= 0.3
    occupied = torch.zeros(5, 6, 7, dtype=torch.bool)
    occupied[1:3, 2:5, 3:6] = True
    geometry = OccupancyGrid(occupied, wide)
    task.skip = task.base_mask = geometry
    state = task.state()
    fresh = _task(scene, 24)
    fresh.base_mask = geometry
    fresh.load_state(state)
    assert torch.equal(fresh.skip.bbox, wide) and torch.equal(fresh.skip.occupied, occupied)


def test_a_checkpoint_keeps_the_random_state_of_its_own_gpu_and_resumes_with_fewer_gpus(monkeypatch):
    """A checkpoint held every visible GPU's random state (`get_rng_state_all`), which `set_rng_state_all` cannot put
    back on a machine with fewer GPUs (an invalid device ordinal, a traceback on resume). It holds the state of the
    device it trained on, which goes back to the device the run resumes on. (No GPU here: torch.cuda's two calls are
    recorded.)"""
    from boostnerf_cli.train import cuda_rng_state, restore_cuda_rng

    calls = []
    monkeypatch.setattr(torch.cuda, "get_rng_state", lambda device: torch.tensor([device.index or 0]))
    monkeypatch.setattr(torch.cuda, "set_rng_state", lambda state, device: calls.append((int(state[0]), str(device))))
    assert cuda_rng_state(torch.device("cpu")) is None
    saved = cuda_rng_state(torch.device("cuda:1"))
    restore_cuda_rng(saved, torch.device("cuda:0"))  # resumed on a one-GPU machine
    restore_cuda_rng(saved, torch.device("cpu"))
    restore_cuda_rng(None, torch.device("cuda:0"))  # a checkpoint written off CUDA
    assert calls == [(1, "cuda:0")]


def test_a_refresh_never_prunes_every_cell_the_geometry_keeps(tiny_scene):
    """A weak warm start (the prior's density below the occupancy threshold on the expert's coarse starting lattice)
    refreshed at the first growth step emptied the mask: every later step evaluated 0 samples, so no gradient could
    raise the density, and pretrain reported an expert of background only, exit 0 (res 8, 30 steps)."""
    scene = load_scene(tiny_scene)
    task = _task(scene, 24)
    occupied = torch.zeros(6, 6, 6, dtype=torch.bool)
    occupied[2:4, 2:4, 1:3] = True
    task.skip = task.base_mask = OccupancyGrid(occupied, scene.bbox.clone())
    with torch.no_grad():
        task.model.density_table.fill_(-30.0)  # alpha ~ 0 everywhere: below any threshold
    task.refresh_occupancy()
    assert task.skip.occupied.any()
    assert torch.equal(task.skip.occupied, task.base_mask.sample_cells(task.skip))
    # the next steps sample the kept cells again (the loss's sample count is what pretrain logs as samples=)
    from boostnerf_cli.stages.pretrain import train_rays

    data = train_rays(scene, scene.bbox, "cpu", task.tcfg)
    _, logs = task.loss(data.origins, data.dirs, data.rgb, None, 0)
    assert logs["samples"] > 0
    # a density that keeps some of the geometry's cells prunes as before: the mask shrinks to those
    lo, hi = scene.bbox[:, 0].tolist()
    cut = lo + 0.42 * (hi - lo)  # the geometry keeps x in [1/3, 2/3] of the box; the density the part below 0.42
    task.model.density = lambda x: torch.where(x[..., 0] < cut, 1e3, 0.0)
    task.refresh_occupancy()
    base = task.base_mask.sample_cells(task.skip)
    assert task.skip.occupied.any() and (task.skip.occupied & ~base).sum() == 0
    assert task.skip.occupied.sum() < base.sum()


def test_the_ray_table_is_every_view_s_box_hitting_rays_in_order(tiny_scene, tmp_path):
    """The training-ray table, now filled in place (its build peaked at 83 bytes per training pixel, 2.4x the table:
    300 views at 800 px would need 16 GB), holds exactly what concatenating every view's rays and keeping those that
    hit the box gave: same rays, same order, same colours and alpha; also for a forward-facing (NDC) scene."""
    from boostnerf_cli.render.rays import image_rays, intersect_box
    from boostnerf_cli.scenes import make_scene

    llff = make_scene(tmp_path / "llff", size=16, n_train=5, n_test=0, layout="llff")
    for scene in (load_scene(tiny_scene), load_scene(llff, holdout_every=0)):
        split = scene.splits["train"]
        box = scene.bbox.clone()
        box[1, 0] = box[0, 0] + 0.4 * (box[1, 0] - box[0, 0])  # a narrower box: some rays miss it
        rays = [image_rays(split.poses[i], split.intrinsics[i], split.height, split.width, scene.ndc)
                for i in range(len(split))]
        o, d = torch.cat([r[0] for r in rays]), torch.cat([r[1] for r in rays])
        hit = intersect_box(o, d, box, scene.near, scene.far)[2]
        assert 0 < int(hit.sum()) < len(hit)
        table = RayData.from_split(split, box, scene.near, scene.far, scene.ndc, keep_alpha=True)
        assert torch.equal(table.origins, o[hit]) and torch.equal(table.dirs, d[hit])
        assert torch.equal(table.rgb, split.images.reshape(-1, 3)[hit])
        if split.alpha is not None:
            assert torch.equal(table.alpha, split.alpha.reshape(-1)[hit])


def test_the_progress_bar_is_drawn_on_stderr_with_its_step_at_80_columns(monkeypatch, caplog):
    """On a terminal the bar went to stdout (a `> results.txt` caught it, the terminal showed
    nothing), and at 80 columns the logged values took the whole line: no bar, step or time were left.
    The bar is drawn where a run's messages are said (INFO, as the CLI sets it), whatever ran before."""
    import io

    from boostnerf_cli.train import Progress

    caplog.set_level(logging.INFO, logger="boostnerf_cli.train")
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    progress = Progress("top1", 2000, 0, 10)
    try:
        console = progress.bar.console
        assert console.stderr
        console.file, console.width = io.StringIO(), 80  # what an 80-column terminal shows
        progress.update(1234, {"loss": 0.1292, "psnr": 8.888, "aux": 1.234, "load0": 0.5321, "load1": 0.2895,
                               "load2": 0.1785, "samples": 16.21, "colored": 9.5})
        with console.capture() as captured:
            console.print(progress.bar.make_tasks_table(progress.bar.tasks))
        line = captured.get().rstrip("\n")
    finally:
        progress.close()
    assert line.startswith("top1 ") and "1234/2000" in line and "0:00:" in line and "loss=0.1292" in line, line


def test_adam_is_torch_fused_adam_bit_for_bit_and_skips_on_found_inf():
    """boostnerf_cli.adam.Adam runs torch's fused kernel as torch.optim.Adam(fused=True) does: the same parameters and
    states after steps of two groups with their own rates, a step skipped by found_inf changes nothing, and its state
    dict resumes to the same numbers; and building and stepping it imports no compiler."""
    import subprocess
    import sys

    from boostnerf_cli.adam import Adam

    torch.manual_seed(0)
    init = [torch.randn(50, 3), torch.randn(7)]
    ours = [torch.nn.Parameter(t.clone()) for t in init]
    theirs = [torch.nn.Parameter(t.clone()) for t in init]
    opt = Adam([{"params": ours[:1], "lr": 0.1}, {"params": ours[1:], "lr": 1e-3}], betas=(0.9, 0.99), eps=1e-15)
    ref = torch.optim.Adam([{"params": theirs[:1], "lr": 0.1}, {"params": theirs[1:], "lr": 1e-3}],
                           betas=(0.9, 0.99), eps=1e-15, fused=True)
    for step in range(6):
        grads = [torch.randn_like(t) for t in init]
        skip = step == 3
        for params, o in ((ours, opt), (theirs, ref)):
            for p, g in zip(params, grads):
                p.grad = g.clone()
            o.found_inf = torch.tensor(1.0 if skip else 0.0)
            o.step()
        for a, b in zip(ours, theirs):
            assert torch.equal(a, b)
    before = [p.detach().clone() for p in ours]
    opt.found_inf = torch.tensor(1.0)
    for p in ours:
        p.grad = torch.full_like(p, float("nan"))
    opt.step()
    assert all(torch.equal(a, b) for a, b in zip(ours, before))
    assert float(opt.state[ours[0]]["step"]) == 5.0  # six steps, one skipped (the NaN one is skipped too)
    again = Adam([{"params": [torch.nn.Parameter(t.detach().clone()) for t in ours[:1]], "lr": 0.1},
                  {"params": [torch.nn.Parameter(ours[1].detach().clone())], "lr": 1e-3}])
    again.load_state_dict(opt.state_dict())
    for p, q in zip([p for g in again.param_groups for p in g["params"]], ours):
        for key in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(again.state[p][key], opt.state[q][key])
    code = ("import sys, torch; from boostnerf_cli.adam import Adam; p = torch.nn.Parameter(torch.ones(2)); "
            "o = Adam([{'params': [p], 'lr': 0.1}]); p.grad = torch.ones(2); o.step(); "
            "sys.exit('torch._dynamo' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0, "the optimiser imported torch._dynamo"
