"""Every recipe value is range-checked when read, and every file the tool reads fails with one line.

The bad and good values below are written from the code that uses each value (not read from the
rules declared in boostnerf_cli), so a rule that drifts from what the code needs fails here.
"""

from __future__ import annotations

import json
import math
import os

import pytest
import torch
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.recipe import load_recipe, recipe_dict, recipe_from_dict
from boostnerf_cli.workspace import Workspace, read_json, read_meta, save_tensors

NAN_INF = st.sampled_from([math.nan, math.inf, -math.inf])
INT_BELOW = lambda lo: st.integers(max_value=lo - 1)  # noqa: E731
# a dense grid resolution below lo or above 1024 (1024^3 cells of one channel are 4 GiB: past it, only out of memory)
GRID_OUTSIDE = lambda lo: st.one_of(INT_BELOW(lo), st.integers(min_value=1025))  # noqa: E731
NOT_POSITIVE = st.one_of(st.floats(max_value=0.0, allow_nan=False), NAN_INF)
NEGATIVE = st.one_of(st.floats(max_value=-1e-9, allow_nan=False), NAN_INF)
OUTSIDE_OPEN_UNIT = st.one_of(st.floats(max_value=0.0, allow_nan=False), st.floats(min_value=1.0, allow_nan=False),
                              st.just(math.nan))
OUTSIDE_THRESHOLD = st.one_of(st.floats(max_value=-1e-12, allow_nan=False), st.floats(min_value=1.0, allow_nan=False),
                              st.just(math.nan))
BAD_WORD = st.text(min_size=1, max_size=12)


def _positive_weights(text: str) -> bool:
    """Whether `text` lists explicit penalty weights: finite numbers > 0 separated by commas (e.g. "1, 1.5")."""
    try:
        return all(0 < float(x) < math.inf for x in text.split(","))
    except ValueError:
        return False


# neither a named scheme nor a list of positive, finite weights ("1" is one weight: a one-expert mixture's)
BAD_PENALTY = st.one_of(
    BAD_WORD.filter(lambda w: w not in ("geometric", "linear", "quadratic", "none") and not _positive_weights(w)),
    st.sampled_from(["1, 0", "1, -2", "1, inf", "1, nan", "1,,2", "1, x", "1.5 2"]))

# key -> out-of-range values (what the code using the value cannot work with)
BAD: dict[str, st.SearchStrategy] = {
    "data.image_size": INT_BELOW(8),  # as --image-size: 1 x 1 images trained
    "data.holdout_every": st.one_of(st.integers(max_value=-1), st.just(1)),  # blender.py: 0 (off) or >= 2
    "data.format": BAD_WORD.filter(lambda w: w not in ("auto", "blender", "nsvf", "tanks", "llff", "nerfstudio")),
    "data.bbox": st.one_of(  # a box: six finite numbers, each max above its min
        st.lists(st.floats(-10, 10), max_size=12).filter(lambda b: len(b) != 6),
        st.lists(st.floats(-10, 10), min_size=3, max_size=3).flatmap(
            lambda lo: st.integers(0, 2).map(lambda axis: lo + [v - (i == axis) for i, v in enumerate(lo)])),
        st.tuples(NAN_INF, st.integers(0, 5)).map(lambda t: [t[0] if i == t[1] else (-1.0 if i < 3 else 1.0)
                                                             for i in range(6)])),
    "pretrain.model": BAD_WORD.filter(lambda w: w not in ("dvgo", "tensorf", "ngp")),
    "pretrain.iters": INT_BELOW(1),
    "pretrain.res": GRID_OUTSIDE(1).map(lambda r: [64, r]),  # one expert too large
    "pretrain.seed": st.one_of(st.integers(max_value=-1), st.integers(min_value=2**63)),  # numpy / torch seeds
    "pretrain.geometry.res": GRID_OUTSIDE(1),
    "pretrain.geometry.iters": INT_BELOW(1),
    "pretrain.geometry.batch_rays": INT_BELOW(1),
    "pretrain.geometry.lr": NOT_POSITIVE,
    "pretrain.geometry.alpha_init": OUTSIDE_OPEN_UNIT,  # log(1/(1-a) - 1)
    "pretrain.geometry.alpha_threshold": OUTSIDE_THRESHOLD,
    "pretrain.geometry.weight_entropy": NEGATIVE,
    "pretrain.train.batch_rays": INT_BELOW(1),
    "pretrain.train.lr_grid": st.one_of(NOT_POSITIVE, st.floats(min_value=10.0, exclude_min=True)),  # Adam's step
    "pretrain.train.lr_mlp": NOT_POSITIVE,
    "pretrain.train.lr_decay": st.one_of(st.floats(max_value=0.0, allow_nan=False),
                                         st.floats(min_value=1.0, exclude_min=True, allow_nan=False),
                                         st.just(math.nan)),
    "pretrain.train.step_ratio": st.one_of(NOT_POSITIVE, st.floats(0, 0.05, exclude_max=True), st.floats(min_value=4.0,
                                           exclude_min=True)),  # samples per ray: out of memory, or past the box
    "pretrain.train.color_threshold": OUTSIDE_THRESHOLD,
    "pretrain.train.occupancy_threshold": OUTSIDE_THRESHOLD,
    "pretrain.train.weight_rgbper": NEGATIVE,
    "pretrain.train.occupancy_every": INT_BELOW(0),
    "pretrain.train.log_every": INT_BELOW(1),  # step % log_every
    "pretrain.train.checkpoint_every": INT_BELOW(1),
    "pretrain.dvgo.alpha_init": OUTSIDE_OPEN_UNIT,
    "pretrain.dvgo.feat_dim": INT_BELOW(1),
    "pretrain.dvgo.hidden": INT_BELOW(0),
    "pretrain.dvgo.view_pe": st.one_of(INT_BELOW(0), st.integers(min_value=17)),  # sin(2^k pi x): inf past k = 127
    "pretrain.dvgo.layers": st.one_of(INT_BELOW(0), st.integers(min_value=17)),
    "pretrain.tensorf.alpha_init": OUTSIDE_OPEN_UNIT,
    "pretrain.tensorf.density_rank": INT_BELOW(1),
    "pretrain.tensorf.l1_weight": NEGATIVE,
    "pretrain.tensorf.fit_steps": INT_BELOW(0),
    "pretrain.ngp.alpha_init": OUTSIDE_OPEN_UNIT,
    "pretrain.ngp.log2_table": st.one_of(INT_BELOW(1), st.integers(min_value=31)),  # hashgrid.py: 1..30
    "pretrain.ngp.features": INT_BELOW(1),
    "pretrain.ngp.grid_res": GRID_OUTSIDE(1),
    "pretrain.ngp.max_res": st.integers(min_value=(1 << 24) - 2),  # hashgrid.py: level resolution + 2 < 2^24
    "moe.gate_type": BAD_WORD.filter(lambda w: w not in ("grid", "linear", "switch")),
    "moe.gate_grid": BAD_WORD.filter(lambda w: w not in ("auto", "dense", "tensorf", "hash")),
    "moe.gate_res": GRID_OUTSIDE(2),
    "moe.vd_res": GRID_OUTSIDE(1),
    "moe.density_threshold": OUTSIDE_THRESHOLD,
    "moe.step_from": BAD_WORD.filter(lambda w: w not in ("smallest", "largest")),
    "moe.topk": INT_BELOW(1),
    "moe.lam": NEGATIVE,
    "moe.penalty": BAD_PENALTY,
    "moe.bake_res": GRID_OUTSIDE(0),
    "moe.render_min_weight": st.one_of(NEGATIVE, st.floats(0.5, 1e6)),
    "moe.iters": INT_BELOW(1),
    "moe.lr_gate": NOT_POSITIVE,
    "moe.lr_gate_mlp": NOT_POSITIVE,
    "moe.train.lr_grid": NOT_POSITIVE,
    "moe.train.batch_rays": INT_BELOW(1),
}

# key -> values the code works with (including the edges: 0 = off, 1 for lr_decay, ...)
GOOD: dict[str, st.SearchStrategy] = {
    "data.holdout_every": st.one_of(st.just(0), st.integers(2, 100)),
    "data.bbox": st.tuples(st.lists(st.floats(-100, 100), min_size=3, max_size=3),
                           st.lists(st.floats(0.01, 100), min_size=3, max_size=3)).map(
        lambda t: t[0] + [lo + size for lo, size in zip(*t)]),
    "pretrain.iters": st.integers(1, 10**6),
    "pretrain.train.lr_decay": st.one_of(st.just(1.0), st.floats(1e-9, 1.0)),
    "pretrain.train.occupancy_every": st.integers(0, 10**4),
    "pretrain.train.color_threshold": st.one_of(st.just(0.0), st.floats(0.0, 0.999)),
    "pretrain.dvgo.alpha_init": st.floats(1e-12, 1 - 1e-9),
    "pretrain.dvgo.hidden": st.integers(0, 512),
    "pretrain.ngp.log2_table": st.integers(1, 30),
    "pretrain.tensorf.feat_pe": st.integers(0, 8),
    "moe.gate_res": st.integers(2, 512),
    "moe.topk": st.integers(1, 16),
    "moe.lam": st.floats(0.0, 10.0),
    "moe.bake_res": st.integers(0, 256),
    "moe.render_min_weight": st.floats(0.0, 0.4999),
    "moe.gate_type": st.sampled_from(["grid", "linear", "switch"]),
}


def _nested(key: str, value) -> dict:
    out = value
    for part in reversed(key.split(".")):
        out = {part: out}
    return out


def _write(tmp_path, data: dict):
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _assert_refused(tmp_path, cases: dict[str, str]) -> None:
    """Each recipe text of `cases` is refused in one line holding its expected words."""
    for text, expected in cases.items():
        (tmp_path / "r.yaml").write_text(text)
        with pytest.raises(BoostNerfError) as e:
            load_recipe(tmp_path / "r.yaml")
        assert expected in str(e.value) and "\n" not in str(e.value), (text, str(e.value))


def _assert_names(err: BoostNerfError, key: str) -> None:
    msg = str(err)
    assert "\n" not in msg and msg.strip() == msg
    assert key in msg and "must be" in msg, msg


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(), key=st.sampled_from(sorted(BAD)))
def test_out_of_range_values_are_one_line_naming_the_key(tmp_path, data, key):
    value = data.draw(BAD[key], label=key)
    path = _write(tmp_path, _nested(key, value))
    with pytest.raises(BoostNerfError) as e:
        load_recipe(path)
    _assert_names(e.value, key)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(),
       key=st.sampled_from(["pretrain.dvgo.alpha_init", "pretrain.dvgo.hidden", "pretrain.ngp.log2_table"]),
       res=st.integers(2, 512))
def test_per_resolution_values_are_checked_each(tmp_path, data, key, res):
    value = data.draw(BAD[key], label=key)
    good = {"pretrain.dvgo.alpha_init": 0.01, "pretrain.dvgo.hidden": 64, "pretrain.ngp.log2_table": 19}[key]
    path = _write(tmp_path, _nested(key, {res + 1: good, res: value}))
    with pytest.raises(BoostNerfError) as e:
        load_recipe(path)
    _assert_names(e.value, f"{key}[{res}]")


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(), key=st.sampled_from(sorted(GOOD)))
def test_in_range_values_load(tmp_path, data, key):
    value = data.draw(GOOD[key], label=key)
    rec = load_recipe(_write(tmp_path, _nested(key, value)))
    section = rec
    for part in key.split(".")[:-1]:
        section = getattr(section, part)
    got = section[key.split(".")[-1]] if isinstance(section, dict) else getattr(section, key.split(".")[-1])
    assert got == value
    assert recipe_from_dict(recipe_dict(rec)) == rec  # the manifest's copy passes the same checks


ANY_VALUE = st.recursive(st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=8)),
                         lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                 st.dictionaries(st.one_of(st.text(max_size=5), st.integers()), inner,
                                                                 max_size=3)), max_leaves=6)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(sorted(set(BAD) | set(GOOD) | {"pretrain.res", "pretrain.train.growth", "moe.renormalize",
                                                           "pretrain.dvgo", "moe.train", "name"})),
       value=ANY_VALUE)
@example(key="pretrain.dvgo", value={"\n": None})  # a key that is a newline: the message spanned two lines
def test_any_value_loads_or_is_one_line(tmp_path, key, value):
    """Whatever YAML holds at a key: the recipe loads, or one BoostNerfError line naming the key; never another
    exception."""
    try:
        load_recipe(_write(tmp_path, _nested(key, value)))
    except BoostNerfError as e:
        msg = str(e)
        assert "\n" not in msg and key.split(".")[0] in msg, msg


def test_known_bad_values_are_one_line_each(tmp_path):
    cases = {
        "pretrain:\n  dvgo: {alpha_init: 0}\n": "recipe key pretrain.dvgo.alpha_init = 0.0: must be in (0, 1)",
        "pretrain:\n  dvgo: {alpha_init: 1}\n": "recipe key pretrain.dvgo.alpha_init = 1.0: must be in (0, 1)",
        "pretrain:\n  model: ngp\n  ngp: {log2_table: 40}\n":
            "recipe key pretrain.ngp.log2_table = 40: must be in [1, 30]",
        "pretrain:\n  train: {batch_rays: -4}\n": "recipe key pretrain.train.batch_rays = -4: must be >= 1",
        "pretrain:\n  train: {growth: [0.1, 1.2]}\n": "recipe key pretrain.train.growth = 1.2: must be in (0, 1)",
        "moe:\n  train: {lr_decay: 1.5}\n": "recipe key moe.train.lr_decay = 1.5: must be in (0, 1]",
        "moe:\n  gate_res: 1\n": "recipe key moe.gate_res = 1: must be in [2, 1024]",
        "moe:\n  gate_res: 3000\n": "recipe key moe.gate_res = 3000: must be in [2, 1024]",
        "pretrain:\n  res: [64, 4096]\n": "recipe key pretrain.res = 4096: must be in [1, 1024]",
        "moe:\n  penalty: cubic\n": "recipe key moe.penalty = 'cubic': must be one of geometric, linear, "
                                    "quadratic, none",
        "pretrain:\n  res: []\n": "recipe key pretrain.res = []: needs at least 1 value(s)",
        "pretrain:\n  res: [64, 96, 64]\n": "recipe key pretrain.res = [64, 96, 64] lists 64 more than once: each "
                                          "expert is named by its resolution",  # build-moe's topk error, before
        "pretrain:\n  model: ngp\n  res: [8]\n  ngp: {base_res: 64, max_res: 32}\n":
            "recipe key pretrain.ngp.max_res = 32: must be >= base_res (64) (expert ngp-8)",
        "pretrain:\n  dvgo: {width: 3}\n": "unknown recipe key pretrain.dvgo.width",
        "pretrain:\n  dvgo: {hidden: {abc: 3}}\n": "the keys of a per-expert mapping must be resolutions",
        "data:\n  bbox: [-1, -1, 1, 1, 1, 1]\n": "recipe key data.bbox = [-1.0, -1.0, 1.0, 1.0, 1.0, 1.0]: must be six "
                                              "numbers, xmin, ymin, zmin, xmax, ymax, zmax, each max above its min",
        "data:\n  bbox: [-1, -1, -1, 1, 1]\n": "recipe key data.bbox = [-1.0, -1.0, -1.0, 1.0, 1.0]: must be six",
    }
    _assert_refused(tmp_path, cases)


def test_values_that_would_crash_or_train_garbage_are_refused(tmp_path, tiny_scene):
    """Values the recipe accepted that crashed mid-run with a traceback (alpha_init 1e-300, a
    per-resolution ngp mapping checked at the listed resolution only, a box no camera sees), trained a blank or noisy
    model with exit 0 (step_ratio 1e6, lr 1e30) or failed after minutes (view_pe 200, a million layers); and YAML's
    surprises: a key given twice (the last won silently, a second `pretrain:` block dropped the first) and 1e-2 read
    as text."""
    from conftest import assert_clean_failure, make_recipe, run_cli

    from boostnerf_cli.fields.dvgo import DVGOConfig, DVGOExpert

    cases = {
        "pretrain:\n  dvgo: {view_pe: 200}\n": "pretrain.dvgo.view_pe = 200: must be in [0, 16]",
        "pretrain:\n  dvgo: {layers: 1000000}\n": "pretrain.dvgo.layers = 1000000: must be in [0, 16]",
        "pretrain:\n  train: {step_ratio: 1.0e+6}\n": "pretrain.train.step_ratio = 1000000.0: must be in [0.05, 4]",
        "pretrain:\n  train: {lr_grid: 1.0e+30}\n": "pretrain.train.lr_grid = 1e+30: must be in (0, 10]",
        "moe:\n  gate_channels: 10000000\n": "moe.gate_channels = 10000000: must be in [1, 512]",
        "data:\n  bbox: [-1.0e+30, -1, -1, 1, 1, 1]\n": "data.bbox = -1e+30: must be in [-1e+06, 1e+06]",
        "pretrain:\n  model: ngp\n  res: [4]\n  ngp: {max_res: {6: 8}}\n":
            "pretrain.ngp.max_res = 8: must be >= base_res (16) (expert ngp-4)",
        "pretrain:\n  iters: 50\n  res: [12]\n  iters: 5000\n": "key 'iters' is given twice (lines 2 and 4): keep one",
        "pretrain:\n  iters: 50\nmoe:\n  iters: 9\npretrain:\n  res: [12]\n": "key 'pretrain' is given twice",
        # an unhashable key was a TypeError traceback; 1e3 where an int belongs, a number
        # where text belongs; 8 and "8" in one per-resolution mapping; a resolution 8.5
        "pretrain:\n  iters: 30\n  [1, 2]: 3\n": "is not valid YAML",
        "pretrain:\n  iters: 1e3\n": "recipe key pretrain.iters must be int, got 1000.0 (write 1000)",
        "name: 1e5\n": "recipe key name must be str, got 100000.0 (quote it to keep it text)",
        "pretrain:\n  dvgo: {hidden: {8: 16, '8': 32}}\n": "pretrain.dvgo.hidden lists resolution 8 twice: keep one",
        "pretrain:\n  dvgo: {hidden: {8.5: 16}}\n": "the keys of a per-expert mapping must be resolutions",
        "pretrain:\n  model: tensorf\n  tensorf: {app_dim: 100000000}\n": "app_dim = 100000000: must be in [1, 4096]",
    }
    _assert_refused(tmp_path, cases)
    (tmp_path / "r.yaml").write_text("pretrain:\n  train: {lr_grid: 1e-2, lr_mlp: 1.0e-3, lr_decay: 5E-1}\n")
    train = load_recipe(tmp_path / "r.yaml").pretrain.train
    assert (train.lr_grid, train.lr_mlp, train.lr_decay) == (0.01, 1e-3, 0.5)  # read as numbers (YAML 1.1: text)
    (tmp_path / "r.yaml").write_text("pretrain:\n  train: &t {batch_rays: 256, lr_grid: 0.1}\n"
                                     "moe:\n  train: {<<: *t, lr_grid: 0.03}\n")  # a merge key, overridden: no twice
    train = load_recipe(tmp_path / "r.yaml").moe.train
    assert (train.batch_rays, train.lr_grid) == (256, 0.03)
    expert = DVGOExpert(DVGOConfig(res=4, alpha_init=1e-300), torch.tensor([[-1.0] * 3, [1.0] * 3]))
    assert math.isfinite(expert.shift) and expert.shift < -600  # log(1e-300): math domain error before
    far = make_recipe(tmp_path / "far.yaml", data={"image_size": 16, "bbox": [100, 100, 100, 101, 101, 101]})
    assert_clean_failure(run_cli("pretrain", "--data", str(tiny_scene), "--recipe", str(far),
                                 "-w", str(tmp_path / "ws"), "--device", "cpu"),
                         "no training ray crosses the box", "data.bbox")


def test_loss_weights_that_overflow_float32_and_finetuning_keys_finetuning_ignores_are_refused(tmp_path):
    """`--penalty 1,1e39,2` passed the check (finite as a Python float) and every step's float32 loss was inf: the
    run stopped as "diverged", with advice to lower the learning rates. `moe.train.step_ratio` and `moe.train.growth`
    were accepted and did nothing (finetuning samples at the experts' step and grows no grid)."""
    cases = {
        "moe:\n  penalty: '1, 1e39, 2'\n": "recipe key moe.penalty = '1, 1e39, 2': must be one of geometric, linear, "
                                          "quadratic, none, or numbers in (0, 1e+06]",
        "moe:\n  lam: 1.0e+39\n": "recipe key moe.lam = 1e+39: must be in [0, 1e+06]",
        "pretrain:\n  train: {weight_entropy: 1.0e+39}\n":
            "pretrain.train.weight_entropy = 1e+39: must be in [0, 1e+06]",
        "moe:\n  train: {step_ratio: 0.25}\n": "recipe key moe.train.step_ratio = 0.25: finetuning does not use it",
        "moe:\n  train: {growth: [0.5]}\n": "recipe key moe.train.growth = [0.5]: finetuning does not use it",
    }
    _assert_refused(tmp_path, cases)
    (tmp_path / "r.yaml").write_text("moe:\n  lam: 1.0e+6\n  penalty: '1, 1e6'\n"
                                     "  train: {step_ratio: 0.5, growth: []}\n")
    assert load_recipe(tmp_path / "r.yaml").moe.lam == 1e6  # the bounds and the defaults themselves load


def test_a_bad_value_in_a_workspace_manifest_is_refused():
    data = recipe_dict(load_recipe(None))
    data["moe"]["topk"] = 0
    with pytest.raises(BoostNerfError, match=r"^workspace manifest's recipe key moe.topk = 0: must be >= 1$"):
        recipe_from_dict(data)


# --- files ---------------------------------------------------------------------------------------
def test_read_json_of_a_folder_a_non_object_and_binary_bytes(tmp_path):
    (tmp_path / "dir.json").mkdir()
    with pytest.raises(BoostNerfError, match=r"report .*dir.json is a folder"):
        read_json(tmp_path / "dir.json", "report")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(BoostNerfError, match="holds a JSON list, not an object"):
        read_json(tmp_path / "list.json", "report")
    (tmp_path / "bin.json").write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(BoostNerfError, match="is not valid JSON"):
        read_json(tmp_path / "bin.json", "report")


def test_read_json_unreadable(tmp_path, monkeypatch):
    path = tmp_path / "r.json"
    path.write_text("{}")

    def denied(self, *a, **k):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(type(path), "read_text", denied)
    with pytest.raises(BoostNerfError, match=r"cannot read report .*r.json \(Permission denied\)"):
        read_json(path, "report")


def test_lock_file_that_cannot_be_opened_is_one_line(tmp_path, monkeypatch):
    real_open = os.open

    def denied(path, *a, **k):
        if str(path).endswith(".lock"):
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, *a, **k)

    monkeypatch.setattr(os, "open", denied)
    with pytest.raises(BoostNerfError, match=r"cannot take the writer lock .*\.lock \(Permission denied\)"):
        with Workspace(tmp_path / "ws").lock():
            pass


def test_safetensors_whose_metadata_is_not_an_object(tmp_path):
    from safetensors.torch import save_file

    path = tmp_path / "x.safetensors"
    save_file({"a": torch.zeros(2)}, str(path), metadata={"boostnerf": "[1, 2]"})
    with pytest.raises(BoostNerfError, match="not a boostnerf file"):
        read_meta(path)


@pytest.mark.parametrize("version", ["1", "3", None])
def test_a_file_of_another_format_version_is_one_line(tmp_path, version):
    """A file from an earlier boostnerf (format "1") or a later one ("3"), or a safetensors file with boostnerf
    metadata but no version, is refused in one line naming both formats, before any of its tensors is interpreted."""
    from safetensors.torch import save_file

    path = tmp_path / "x.safetensors"
    meta = {"name": "dvgo-12", "family": "dvgo", **({"format_version": version} if version else {})}
    save_file({"a": torch.zeros(2)}, str(path), metadata={"boostnerf": json.dumps(meta)})
    with pytest.raises(BoostNerfError) as e:
        read_meta(path)
    msg = str(e.value)
    assert "\n" not in msg and f"file format {version!r}" in msg and "reads format '2'" in msg, msg


def _tiny_expert_file(tmp_path, **meta_changes):
    from boostnerf_cli.fields.dvgo import DVGOConfig, DVGOExpert
    from boostnerf_cli.models import save_expert
    from boostnerf_cli.render.occupancy import OccupancyGrid

    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    model = DVGOExpert(DVGOConfig(res=6, hidden=8, layers=1), box)
    path = tmp_path / "e.safetensors"
    save_expert(path, model, OccupancyGrid(torch.ones(4, 4, 4, dtype=torch.bool), box))
    from boostnerf_cli.workspace import load_tensors

    tensors, meta = load_tensors(path)
    drop = meta_changes.pop("drop", None)
    if drop:
        tensors.pop(drop)
    meta = {**meta, **meta_changes}
    meta.pop("digest"), meta.pop("format_version")
    save_tensors(path, tensors, meta)
    return path


@pytest.mark.parametrize("change", [
    {"drop": "occupancy_bbox"},  # KeyError outside any handler before
    {"config": {"res": 6, "hidden": 8, "layers": 1, "alpha_init": 0}},  # math domain error before
    {"config": {"res": 6, "hidden": 8, "layers": 1, "alpha_init": 1}},  # division by zero before
    {"unit": "wide"},  # ValueError before
    {"family": ["dvgo"]},  # unhashable: TypeError before
], ids=["no-occupancy-bbox", "alpha-0", "alpha-1", "unit-text", "family-list"])
def test_expert_file_with_the_wrong_structure_is_one_line(tmp_path, change):
    from boostnerf_cli.models import load_expert

    path = _tiny_expert_file(tmp_path, **change)
    with pytest.raises(BoostNerfError) as e:
        load_expert(path)
    assert "e.safetensors" in str(e.value) and "\n" not in str(e.value)


def test_mixture_file_with_the_wrong_structure_is_one_line(tmp_path):
    from helpers import toy_mixture

    from boostnerf_cli.models import load_mixture, save_mixture
    from boostnerf_cli.workspace import load_tensors

    path = tmp_path / "m.safetensors"
    save_mixture(path, toy_mixture(m=2, k=1))
    tensors, meta = load_tensors(path)
    meta["gate"]["config"]["gate_type"] = "octree"  # Gate raised ValueError outside any handler before
    meta.pop("digest"), meta.pop("format_version")
    save_tensors(path, tensors, meta)
    with pytest.raises(BoostNerfError,
                       match=r"m.safetensors does not hold a valid mixture \(ValueError: unknown gate type"):
        load_mixture(path)


def test_training_checkpoint_with_the_wrong_structure_is_one_line(tmp_path):
    from boostnerf_cli.train import RayData, Schedule, TrainCheckpoint, train
    from boostnerf_cli.workspace import FORMAT_VERSION

    class Task:
        def param_groups(self):
            return [{"params": [torch.zeros(1, requires_grad=True)], "lr": 0.1}]

        def load_state(self, state):
            self.w = state["weights"]

    ckpt = tmp_path / "c.pt"
    rays = RayData(torch.zeros(4, 3), torch.ones(4, 3), torch.zeros(4, 3))
    v = {"format_version": FORMAT_VERSION}
    for state in ({**v, "task": {}, "step": 1}, [1, 2, 3], {**v, "task": {"weights": 1}, "signature": 5},
                  {"task": {"weights": 1}}):  # the last: no file format, an earlier boostnerf's
        torch.save(state, ckpt)
        with pytest.raises(BoostNerfError, match=r"training checkpoint .*c.pt .*delete it to restart this model") as e:
            train(Task(), rays, Schedule(iters=2), 0, "t", TrainCheckpoint(ckpt, {"stage": "x"}))
        assert "\n" not in str(e.value)


@pytest.mark.parametrize("failure", [
    RuntimeError("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate memory: you tried "
                 "to allocate 864196993440 bytes. Error code 12 (Cannot allocate memory)"),
    RuntimeError("Storage size calculation overflowed with sizes=[999999475878907192, 8]"),
    torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 20.00 GiB"),
    MemoryError(),
])
def test_out_of_memory_is_one_line_naming_the_settings(monkeypatch, capsys, failure):
    """What the CPU allocator, CUDA and an unaddressable size raise when a grid does not fit (build-moe with
    gate_res 3000 raised the first before grid resolutions were capped) reaches the user as one line, exit 3."""
    from boostnerf_cli import cli

    def stage(**kwargs):
        raise failure

    monkeypatch.setattr(cli, "app", stage)
    monkeypatch.setattr("signal.signal", lambda *args: None)  # main's Ctrl-C handlers stay out of the test process
    with pytest.raises(SystemExit) as e:
        cli.main()
    assert e.value.code == 3
    out = capsys.readouterr().err.strip()
    assert "\n" not in out and out.startswith("error: out of memory") and "moe.gate_res" in out, out
    assert "data.image_size" in out and "height and width" in out, out  # an image's size, not only the recipe's


def test_make_scene_refuses_an_image_side_past_its_largest(tmp_path):
    """make-scene --size 100000 ran out of memory and blamed the recipe, which make-scene does not take."""
    from conftest import assert_clean_failure, run_cli

    assert_clean_failure(run_cli("make-scene", str(tmp_path / "s"), "--size", "100000"), "--size")
    assert not (tmp_path / "s").exists()


def test_a_runtime_error_that_is_not_memory_keeps_its_traceback(monkeypatch):
    from boostnerf_cli import cli

    def stage(**kwargs):
        raise RuntimeError("mat1 and mat2 shapes cannot be multiplied")

    monkeypatch.setattr(cli, "app", stage)
    monkeypatch.setattr("signal.signal", lambda *args: None)
    with pytest.raises(RuntimeError, match="shapes"):
        cli.main()

