"""Image-quality metrics: PSNR, SSIM (NeRF-paper definition) and optional LPIPS-AlexNet v0.1."""

from boostnerf_cli.metrics.image import (
    ALEXNET_ENV,
    LPIPS_ENV,
    LPIPSModel,
    image_metrics,
    load_lpips,
    lpips,
    lpips_from_files,
    mse_to_psnr,
    psnr,
    ssim,
    ssim_map,
)

__all__ = [
    "ALEXNET_ENV",
    "LPIPS_ENV",
    "LPIPSModel",
    "image_metrics",
    "load_lpips",
    "lpips",
    "lpips_from_files",
    "mse_to_psnr",
    "psnr",
    "ssim",
    "ssim_map",
]
