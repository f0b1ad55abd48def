"""Image-quality metrics of the NeRF literature: PSNR, SSIM and (optional) LPIPS-AlexNet v0.1.

All metrics take one pair of images `pred`, `gt` of shape (H, W, C) (C = 3 for LPIPS), float values
in [0, 1], as torch tensors or numpy arrays, and return a Python float for that image pair. Values
are not clipped: clip renders to [0, 1] before calling. A scene score is the mean of the per-image
values (NeRF convention: mean of per-image PSNR, not PSNR of the mean MSE).

PSNR and SSIM are computed on the CPU in float64. LPIPS runs on the device of its model.

LPIPS is optional because its weights cannot be downloaded at run time. `load_lpips` looks for
them on local disk only and otherwise returns `(None, reason)`:

* AlexNet backbone: a torchvision state dict `alexnet-owt-7be5be79.pth` in
  `$BOOSTNERF_ALEXNET_WEIGHTS` (a file path), else in `torch.hub.get_dir()/checkpoints`
  (`$TORCH_HOME/hub/checkpoints`) or `~/.cache/torch/hub/checkpoints`.
* Linear heads: `lpips/weights/v0.1/alex.pth` of the `lpips` pip package (located with
  `importlib.util.find_spec`, never imported), or the file in `$BOOSTNERF_LPIPS_WEIGHTS`.
"""

from __future__ import annotations

import importlib.util
import math
import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn import functional as F

from boostnerf_cli.errors import BoostNerfError

ImageLike = Tensor | np.ndarray

# --------------------------------------------------------------------------------------- inputs


def _as_pair(pred: ImageLike, gt: ImageLike, name: str) -> tuple[Tensor, Tensor]:
    """Both images as CPU float64 tensors (H, W, C); raises BoostNerfError on a shape problem."""
    p = torch.as_tensor(pred).detach().to("cpu", torch.float64)
    g = torch.as_tensor(gt).detach().to("cpu", torch.float64)
    if p.shape != g.shape:
        raise BoostNerfError(
            f"{name}: prediction shape {tuple(p.shape)} differs from ground truth "
            f"{tuple(g.shape)}; render at the ground-truth resolution"
        )
    if p.ndim != 3:
        raise BoostNerfError(
            f"{name}: expected images of shape (H, W, C), got {tuple(p.shape)}; "
            "pass one image at a time"
        )
    return p, g


# ----------------------------------------------------------------------------------------- PSNR


def mse_to_psnr(mse: float) -> float:
    """PSNR in dB for a mean squared error on [0, 1] data: -10 log10(mse); inf when mse == 0."""
    return float("inf") if mse <= 0.0 else -10.0 * math.log10(mse)


def psnr(pred: ImageLike, gt: ImageLike) -> float:
    """Peak signal-to-noise ratio in dB of (H, W, C) images in [0, 1] (data range 1).

    Computed in float64 as -10 log10(mean((pred - gt)^2)). Identical images return
    `float("inf")` (no finite cap): a scene mean containing one is then inf, which is honest.
    """
    p, g = _as_pair(pred, gt, "psnr")
    return mse_to_psnr(float(torch.mean((p - g) ** 2)))


# ----------------------------------------------------------------------------------------- SSIM

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _gaussian_taps(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> Tensor:
    """Normalised 1-D Gaussian taps (size,) float64, centred on the middle tap."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    w = torch.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def _blur_valid(x: Tensor, taps: Tensor) -> Tensor:
    """Separable Gaussian filter with no padding: (N, 1, H, W) -> (N, 1, H-k+1, W-k+1)."""
    k = taps.numel()
    x = F.conv2d(x, taps.view(1, 1, k, 1))
    return F.conv2d(x, taps.view(1, 1, 1, k))


def ssim_map(pred: Tensor, gt: Tensor) -> Tensor:
    """SSIM map of float64 (H, W, C) tensors on the 'valid' region -> (C, H-10, W-10).

    Gaussian window 11x11 with sigma 1.5, K1 = 0.01, K2 = 0.03, data range 1, population
    (not sample) covariances. Like the mip-NeRF / JAX reference, variances are clamped at 0 and
    the covariance to +-sqrt(var_x var_y); both only remove float round-off.
    """
    x = pred.permute(2, 0, 1).unsqueeze(1)  # (C, 1, H, W)
    y = gt.permute(2, 0, 1).unsqueeze(1)
    c = x.shape[0]
    stats = _blur_valid(torch.cat([x, y, x * x, y * y, x * y]), _gaussian_taps())
    mu_x, mu_y, e_xx, e_yy, e_xy = stats.split(c)
    var_x = (e_xx - mu_x**2).clamp(min=0.0)
    var_y = (e_yy - mu_y**2).clamp(min=0.0)
    bound = torch.sqrt(var_x * var_y)
    cov = (e_xy - mu_x * mu_y).clamp(min=-bound, max=bound)
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    num = (2 * mu_x * mu_y + c1) * (2 * cov + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    return (num / den).squeeze(1)


def ssim(pred: ImageLike, gt: ImageLike) -> float:
    """Structural similarity of (H, W, C) images in [0, 1], mean over channels and valid pixels.

    The standard NeRF-paper SSIM (see `ssim_map`). Equal, to float round-off, to
    `skimage.metrics.structural_similarity(pred, gt, gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1.0, channel_axis=-1)`: skimage filters with reflect
    padding and then crops a 5-pixel border, which leaves exactly this 'valid' region.
    Images need H, W >= 11.
    """
    p, g = _as_pair(pred, gt, "ssim")
    if min(p.shape[0], p.shape[1]) < SSIM_WINDOW:
        raise BoostNerfError(
            f"ssim: image {p.shape[0]}x{p.shape[1]} is smaller than the {SSIM_WINDOW}x"
            f"{SSIM_WINDOW} window; evaluate at a resolution of at least {SSIM_WINDOW} pixels"
        )
    return float(ssim_map(p, g).mean())


# ---------------------------------------------------------------------------------------- LPIPS

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
LPIPS_HEAD_FILE = "alex.pth"
ALEXNET_ENV = "BOOSTNERF_ALEXNET_WEIGHTS"
LPIPS_ENV = "BOOSTNERF_LPIPS_WEIGHTS"
LPIPS_CHANNELS = (64, 192, 384, 256, 256)
LPIPS_MIN_SIZE = 31  # smallest side AlexNet's conv/pool stack accepts
_RELU_TAPS = (1, 4, 7, 9, 11)  # indices of relu1..relu5 in torchvision alexnet.features
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


def _alexnet_features() -> nn.Sequential:
    """torchvision `alexnet().features` layout (same indices, so its state dict keys load)."""
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),
        nn.ReLU(inplace=False),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(64, 192, kernel_size=5, padding=2),
        nn.ReLU(inplace=False),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(192, 384, kernel_size=3, padding=1),
        nn.ReLU(inplace=False),
        nn.Conv2d(384, 256, kernel_size=3, padding=1),
        nn.ReLU(inplace=False),
        nn.Conv2d(256, 256, kernel_size=3, padding=1),
        nn.ReLU(inplace=False),
        nn.MaxPool2d(kernel_size=3, stride=2),
    )


def _unit_normalise(f: Tensor, eps: float = 1e-10) -> Tensor:
    """Scale every spatial feature vector to unit length: (N, C, H, W) -> (N, C, H, W)."""
    return f / (torch.sqrt(torch.sum(f * f, dim=1, keepdim=True)) + eps)


class LPIPSModel(nn.Module):
    """LPIPS v0.1 with an AlexNet backbone.

    Parameters: `features.{0,3,6,8,10}.{weight,bias}` (torchvision layout) and
    `heads.{0..4}.weight` of shape (1, C_l, 1, 1), C_l = 64, 192, 384, 256, 256 (no bias).
    A fresh instance has random weights; use `load_lpips` for the real ones.
    """

    def __init__(self) -> None:
        super().__init__()
        self.features = _alexnet_features()
        self.heads = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in LPIPS_CHANNELS)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))

    @classmethod
    def random(cls, seed: int = 0) -> LPIPSModel:
        """A model with seeded random weights and non-negative heads (tests, no files needed)."""
        gen = torch.Generator().manual_seed(seed)
        model = cls()
        with torch.no_grad():
            for p in model.parameters():
                p.copy_(torch.randn(p.shape, generator=gen) * 0.05)
            for head in model.heads:
                head.weight.abs_()
        return model.eval()

    def taps(self, x: Tensor) -> list[Tensor]:
        """Activations after relu1..relu5 for network input x (N, 3, H, W) -> 5 x (N, C_l, h, w)."""
        out = []
        for i, layer in enumerate(self.features[: _RELU_TAPS[-1] + 1]):
            x = layer(x)
            if i in _RELU_TAPS:
                out.append(x)
        return out

    def forward(self, pred: Tensor, gt: Tensor) -> Tensor:
        """LPIPS distance of image batches (N, 3, H, W) in [0, 1] -> (N,), >= 0, 0 for equal inputs."""
        a = self.taps(((pred * 2 - 1) - self.shift) / self.scale)
        b = self.taps(((gt * 2 - 1) - self.shift) / self.scale)
        total = pred.new_zeros(pred.shape[0])
        for fa, fb, head in zip(a, b, self.heads):
            diff = (_unit_normalise(fa) - _unit_normalise(fb)) ** 2
            total = total + head(diff).mean(dim=(1, 2, 3))
        return total


def _hub_checkpoint_dirs() -> list[Path]:
    """Local torch-hub checkpoint folders, in search order (never triggers a download)."""
    dirs = [Path(torch.hub.get_dir()) / "checkpoints"]
    if os.environ.get("TORCH_HOME"):
        dirs.append(Path(os.environ["TORCH_HOME"]) / "hub" / "checkpoints")
    dirs.append(Path.home() / ".cache" / "torch" / "hub" / "checkpoints")
    return list(dict.fromkeys(dirs))


def _not_a_file(path: str) -> str:
    """Why `path`, named by an environment variable, is no weights file."""
    return "is a folder, not a file" if Path(path).is_dir() else "does not exist"


def _find_alexnet_file() -> tuple[Path | None, str]:
    """The AlexNet state-dict path, or None with a one-line reason naming what was not found."""
    env = os.environ.get(ALEXNET_ENV)
    if env:
        if Path(env).is_file():
            return Path(env), ""
        return None, (
            f"LPIPS unavailable: {ALEXNET_ENV}={env} {_not_a_file(env)}; point it to a torchvision "
            f"{ALEXNET_FILE} file"
        )
    candidates = [d / ALEXNET_FILE for d in _hub_checkpoint_dirs()]
    for path in candidates:
        if path.is_file():
            return path, ""
    looked = ", ".join(str(p) for p in candidates)
    return None, (
        f"LPIPS unavailable: AlexNet weights {ALEXNET_FILE} not found (looked in {looked}); "
        f"copy the file there or set {ALEXNET_ENV} to its path"
    )


def _find_head_file() -> tuple[Path | None, str]:
    """The LPIPS v0.1 alex.pth path, or None with a one-line reason naming what was not found."""
    env = os.environ.get(LPIPS_ENV)
    if env:
        if Path(env).is_file():
            return Path(env), ""
        return None, (
            f"LPIPS unavailable: {LPIPS_ENV}={env} {_not_a_file(env)}; point it to the file "
            "lpips/weights/v0.1/alex.pth of the lpips package"
        )
    spec = importlib.util.find_spec("lpips")
    roots = list(spec.submodule_search_locations or []) if spec else []
    for root in roots:
        path = Path(root) / "weights" / "v0.1" / LPIPS_HEAD_FILE
        if path.is_file():
            return path, ""
    where = f"in the lpips package at {roots[0]}" if roots else "(the lpips package is not installed)"
    return None, (
        f"LPIPS unavailable: linear-head weights weights/v0.1/{LPIPS_HEAD_FILE} not found {where}; "
        f"`pip install lpips` or set {LPIPS_ENV} to an alex.pth file"
    )


def _read_state_dict(path: Path) -> tuple[dict[str, Tensor] | None, str]:
    """A tensor state dict from a .pth file (weights_only), or None with a one-line reason."""
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is reported, not raised
        return None, f"LPIPS unavailable: cannot read {path} ({type(exc).__name__}); replace the file"
    if not isinstance(sd, dict):
        return None, f"LPIPS unavailable: {path} is not a state dict; provide a state-dict .pth file"
    return sd, ""


def _head_key(key: str) -> str:
    """Map an lpips-package head key (`lin3.model.1.weight` or `lin3.weight`) to `heads.3.weight`."""
    name = key.split(".")[0]
    if name.startswith("lin") and name[3:].isdigit() and key.endswith("weight"):
        return f"heads.{name[3:]}.weight"
    return key


def _merged_state_dict(backbone: dict[str, Tensor], heads: dict[str, Tensor]) -> dict[str, Tensor]:
    """LPIPSModel state dict from torchvision AlexNet keys (classifier ignored) and lpips heads."""
    sd = {k: v for k, v in backbone.items() if k.startswith("features.")}
    sd.update({_head_key(k): v for k, v in heads.items()})
    return sd


def lpips_from_files(alexnet_path: Path, head_path: Path) -> tuple[LPIPSModel | None, str]:
    """Build LPIPS from the two weight files; (model on CPU, "") or (None, one-line reason)."""
    backbone, reason = _read_state_dict(alexnet_path)
    if backbone is None:
        return None, reason
    heads, reason = _read_state_dict(head_path)
    if heads is None:
        return None, reason
    model = LPIPSModel()
    sd = _merged_state_dict(backbone, heads)
    sd.update({"shift": model.shift, "scale": model.scale})
    expected = model.state_dict()
    wrong = [f"{k} {tuple(v.shape)} for {tuple(expected[k].shape)}" for k, v in sd.items()
             if k in expected and v.shape != expected[k].shape]
    if wrong:
        return None, (
            f"LPIPS unavailable: weight shapes do not match ({alexnet_path}, {head_path}): {', '.join(wrong[:2])}; "
            "provide torchvision AlexNet and lpips v0.1 alex.pth files (not another network's)"
        )
    missing, unexpected = model.load_state_dict(sd, strict=False)
    if missing or unexpected:
        return None, (
            f"LPIPS unavailable: weight keys do not match ({alexnet_path}, {head_path}): "
            f"missing {missing[:3]}, unexpected {unexpected[:3]}; provide torchvision AlexNet "
            "and lpips v0.1 alex.pth files"
        )
    with torch.no_grad():
        for head in model.heads:
            head.weight.clamp_(min=0.0)  # LPIPS heads are non-negative by construction
    return model.eval(), ""


def load_lpips(device: str | torch.device = "cpu") -> tuple[LPIPSModel | None, str]:
    """LPIPS-AlexNet v0.1 from local files only: (model in eval mode on device, "") or (None, reason).

    The reason is one line naming the file that was not found and the env var that provides it.
    Never downloads.
    """
    alexnet_path, reason = _find_alexnet_file()
    if alexnet_path is None:
        return None, reason
    head_path, reason = _find_head_file()
    if head_path is None:
        return None, reason
    model, reason = lpips_from_files(alexnet_path, head_path)
    if model is None:
        return None, reason
    model.requires_grad_(False)
    return model.to(device), ""


def lpips(pred: ImageLike, gt: ImageLike, model: LPIPSModel) -> float:
    """LPIPS distance (lower is better) of (H, W, 3) images in [0, 1]; H, W >= 31."""
    p, g = _as_pair(pred, gt, "lpips")
    if p.shape[2] != 3 or min(p.shape[0], p.shape[1]) < LPIPS_MIN_SIZE:
        raise BoostNerfError(
            f"lpips: need (H, W, 3) images with H, W >= {LPIPS_MIN_SIZE}, got {tuple(p.shape)}; "
            "evaluate RGB images at a larger resolution"
        )
    dev = model.shift.device
    with torch.no_grad():
        return float(model(_to_batch(p, dev), _to_batch(g, dev))[0])


def _to_batch(img: Tensor, device: torch.device) -> Tensor:
    """(H, W, 3) -> (1, 3, H, W) float32 on device."""
    return img.permute(2, 0, 1).unsqueeze(0).to(device, torch.float32)


def image_metrics(
    pred: ImageLike, gt: ImageLike, lpips_model: LPIPSModel | None = None
) -> dict[str, float | None]:
    """{"psnr", "ssim", "lpips"} for one (H, W, 3) image pair; lpips is None without a model, ssim None for an image
    smaller than its window (`SSIM_WINDOW` px a side)."""
    return {
        "psnr": psnr(pred, gt),
        "ssim": ssim(pred, gt) if min(pred.shape[0], pred.shape[1]) >= SSIM_WINDOW else None,
        "lpips": None if lpips_model is None else lpips(pred, gt, lpips_model),
    }
