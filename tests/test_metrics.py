"""Tests of boostnerf_cli.metrics: PSNR, SSIM against scikit-image, LPIPS architecture and loading."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers import lpips_head_layout, torchvision_alexnet_layout
from skimage.metrics import structural_similarity

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.metrics import (
    ALEXNET_ENV,
    LPIPS_ENV,
    LPIPSModel,
    image_metrics,
    load_lpips,
    lpips,
    psnr,
    ssim,
)

LPIPS_HEAD_CHANNELS = (64, 192, 384, 256, 256)


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def _skimage_ssim(a: np.ndarray, b: np.ndarray) -> float:
    return structural_similarity(
        a,
        b,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
        channel_axis=-1,
    )


def _gradient(h: int, w: int) -> np.ndarray:
    y, x = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
    return np.stack([x, y, 0.5 * (x + y)], axis=-1)


def _ssim_pairs() -> list[tuple[str, np.ndarray, np.ndarray]]:
    rng = _rng(1)
    noise = rng.random((40, 37, 3))
    grad = _gradient(48, 52)
    checker = (np.indices((33, 45)).sum(0) // 4 % 2).astype(np.float64)[..., None].repeat(3, -1)
    return [
        ("random", noise, rng.random((40, 37, 3))),
        ("random_vs_noisy", noise, np.clip(noise + 0.1 * rng.standard_normal(noise.shape), 0, 1)),
        ("gradient_vs_noisy", grad, np.clip(grad + 0.05 * rng.standard_normal(grad.shape), 0, 1)),
        ("gradient_shifted", grad, np.roll(grad, shift=(2, 3), axis=(0, 1))),
        ("checker_shifted", checker, np.roll(checker, shift=1, axis=1)),
        ("gradient_vs_flat", grad, np.full_like(grad, 0.5)),
        ("constant_images", np.full((20, 20, 3), 0.2), np.full((20, 20, 3), 0.7)),
    ]


# ----------------------------------------------------------------------------------------- PSNR


def test_psnr_matches_float64_hand_computation() -> None:
    rng = _rng(2)
    a, b = rng.random((16, 12, 3)), rng.random((16, 12, 3))
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    assert psnr(a, b) == pytest.approx(-10.0 * math.log10(mse), abs=1e-10)
    # float32 torch input gives the same answer up to the float32 rounding of the inputs
    ta, tb = torch.from_numpy(a).float(), torch.from_numpy(b).float()
    assert psnr(ta, tb) == pytest.approx(psnr(a, b), abs=1e-5)


def test_psnr_known_value() -> None:
    a = np.zeros((4, 4, 3))
    assert psnr(a, a + 0.1) == pytest.approx(20.0, abs=1e-9)


def test_psnr_identical_images_is_inf() -> None:
    a = _rng(3).random((8, 8, 3))
    assert psnr(a, a.copy()) == float("inf")


def test_psnr_rejects_shape_mismatch() -> None:
    with pytest.raises(BoostNerfError, match="differs"):
        psnr(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))


# ----------------------------------------------------------------------------------------- SSIM


@pytest.mark.parametrize("name,a,b", _ssim_pairs(), ids=[p[0] for p in _ssim_pairs()])
def test_ssim_matches_skimage(name: str, a: np.ndarray, b: np.ndarray) -> None:
    assert ssim(a, b) == pytest.approx(_skimage_ssim(a, b), abs=1e-6)


def test_ssim_torch_float32_input() -> None:
    a, b = _ssim_pairs()[2][1:]
    ta, tb = torch.from_numpy(a).float(), torch.from_numpy(b).float()
    ref = _skimage_ssim(ta.double().numpy(), tb.double().numpy())
    assert ssim(ta, tb) == pytest.approx(ref, abs=1e-6)


def test_ssim_of_identical_images_is_one() -> None:
    a = _rng(4).random((24, 30, 3))
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)


def test_ssim_rejects_images_smaller_than_window() -> None:
    with pytest.raises(BoostNerfError, match="window"):
        ssim(np.zeros((10, 20, 3)), np.zeros((10, 20, 3)))


# ---------------------------------------------------------------------------------------- LPIPS


def test_lpips_random_model_shape_and_sign() -> None:
    model = LPIPSModel.random(seed=0)
    gen = torch.Generator().manual_seed(0)
    x, y = torch.rand(2, 3, 64, 48, generator=gen), torch.rand(2, 3, 64, 48, generator=gen)
    with torch.no_grad():
        d = model(x, y)
    assert d.shape == (2,)
    assert bool((d > 0).all())
    assert torch.equal(model(x, x), torch.zeros(2))


def test_lpips_taps_have_alexnet_channels() -> None:
    taps = LPIPSModel.random().taps(torch.zeros(1, 3, 64, 64))
    assert [t.shape[1] for t in taps] == list(LPIPS_HEAD_CHANNELS)


def test_lpips_function_on_hwc_images() -> None:
    model = LPIPSModel.random(seed=1)
    rng = _rng(5)
    a, b = rng.random((40, 36, 3)), rng.random((40, 36, 3))
    assert lpips(a, a, model) == 0.0
    assert lpips(a, b, model) > 0.0
    with pytest.raises(BoostNerfError, match="31"):
        lpips(a[:20], b[:20], model)


def test_image_metrics_without_lpips_model() -> None:
    a = _rng(6).random((16, 16, 3))
    out = image_metrics(a, np.clip(a + 0.01, 0, 1))
    assert set(out) == {"psnr", "ssim", "lpips"}
    assert out["lpips"] is None
    assert out["psnr"] > 30


def test_load_lpips_reports_missing_alexnet(tmp_path, monkeypatch) -> None:
    missing = tmp_path / "nope" / "alexnet-owt-7be5be79.pth"
    monkeypatch.setenv(ALEXNET_ENV, str(missing))
    monkeypatch.setenv(LPIPS_ENV, str(tmp_path / "alex.pth"))
    model, reason = load_lpips("cpu")
    assert model is None
    assert str(missing) in reason and ALEXNET_ENV in reason
    assert "\n" not in reason


def test_load_lpips_reports_missing_heads(tmp_path, monkeypatch) -> None:
    backbone = tmp_path / "alexnet-owt-7be5be79.pth"
    torch.save(torchvision_alexnet_layout(LPIPSModel.random()), backbone)
    missing = tmp_path / "missing_alex.pth"
    monkeypatch.setenv(ALEXNET_ENV, str(backbone))
    monkeypatch.setenv(LPIPS_ENV, str(missing))
    model, reason = load_lpips("cpu")
    assert model is None
    assert str(missing) in reason and LPIPS_ENV in reason
    assert "\n" not in reason


def test_load_lpips_without_env_names_alexnet_file(tmp_path, monkeypatch) -> None:
    monkeypatch.delenv(ALEXNET_ENV, raising=False)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    monkeypatch.setattr("pathlib.Path.home", lambda: tmp_path)
    model, reason = load_lpips("cpu")
    assert model is None
    assert "alexnet-owt-7be5be79.pth" in reason and ALEXNET_ENV in reason


def test_load_lpips_from_files_in_reference_layouts(tmp_path, monkeypatch) -> None:
    src = LPIPSModel.random(seed=7)
    backbone, heads = tmp_path / "alexnet-owt-7be5be79.pth", tmp_path / "alex.pth"
    torch.save(torchvision_alexnet_layout(src), backbone)
    torch.save(lpips_head_layout(src), heads)
    assert set(torchvision_alexnet_layout(src)) >= {f"features.{i}.weight" for i in (0, 3, 6, 8, 10)}
    monkeypatch.setenv(ALEXNET_ENV, str(backbone))
    monkeypatch.setenv(LPIPS_ENV, str(heads))
    model, reason = load_lpips("cpu")
    assert reason == "" and model is not None
    assert not model.training
    assert model.state_dict().keys() == src.state_dict().keys()
    for key, value in src.state_dict().items():
        assert torch.equal(model.state_dict()[key], value), key
    rng = _rng(8)
    a, b = rng.random((32, 32, 3)), rng.random((32, 32, 3))
    assert lpips(a, b, model) == pytest.approx(lpips(a, b, src), rel=1e-6)


def test_load_lpips_reports_wrong_keys(tmp_path, monkeypatch) -> None:
    src = LPIPSModel.random()
    backbone, heads = tmp_path / "alexnet.pth", tmp_path / "alex.pth"
    torch.save(torchvision_alexnet_layout(src), backbone)
    torch.save({"something.else": torch.zeros(1)}, heads)
    monkeypatch.setenv(ALEXNET_ENV, str(backbone))
    monkeypatch.setenv(LPIPS_ENV, str(heads))
    model, reason = load_lpips("cpu")
    assert model is None and "keys" in reason and "\n" not in reason


def test_load_lpips_reports_unreadable_file(tmp_path, monkeypatch) -> None:
    backbone = tmp_path / "alexnet.pth"
    backbone.write_bytes(b"not a checkpoint")
    monkeypatch.setenv(ALEXNET_ENV, str(backbone))
    monkeypatch.setenv(LPIPS_ENV, str(backbone))
    model, reason = load_lpips("cpu")
    assert model is None and str(backbone) in reason


def test_load_lpips_reports_heads_of_another_network(tmp_path, monkeypatch) -> None:
    """The lpips package's vgg.pth (or squeeze.pth) heads, or a backbone of the right keys and other shapes: one
    line naming the files, not a 50-line traceback of load_state_dict's size mismatch."""
    src = LPIPSModel.random()
    backbone, heads = tmp_path / "alexnet.pth", tmp_path / "vgg.pth"
    torch.save(torchvision_alexnet_layout(src), backbone)
    vgg = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1) for i, c in enumerate((64, 128, 256, 512, 512))}
    torch.save(vgg, heads)
    monkeypatch.setenv(ALEXNET_ENV, str(backbone))
    monkeypatch.setenv(LPIPS_ENV, str(heads))
    model, reason = load_lpips("cpu")
    assert model is None and "shapes do not match" in reason and str(heads) in reason and "\n" not in reason


def test_load_lpips_names_a_folder_given_for_a_file(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv(ALEXNET_ENV, str(tmp_path))
    model, reason = load_lpips("cpu")
    assert model is None and f"{ALEXNET_ENV}={tmp_path} is a folder, not a file" in reason
