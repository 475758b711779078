"""Image metrics: PSNR (RGB or silhouettes), SSIM, and LPIPS availability (method.md §9).

PSNR is ``10 log10(max_val^2 / MSE)`` and is ``inf`` for identical images. LPIPS needs
pretrained backbone weights; holowarp never downloads them, so :func:`lpips_status` reports
whether they are on disk and why not.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

__all__ = ["psnr", "mask_psnr", "ssim", "lpips_status"]


def psnr(pred, target, *, max_val: float = 1.0) -> float:
    """PSNR in dB over all elements of two same-shaped arrays; ``inf`` when identical."""
    a = np.asarray(pred, dtype=np.float64)
    b = np.asarray(target, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"psnr: shapes differ, {a.shape} vs {b.shape}")
    mse = float(np.mean((a - b) ** 2))
    if mse == 0.0:
        return float("inf")
    return 10.0 * math.log10(max_val * max_val / mse)


def mask_psnr(pred_masks, gt_masks) -> float:
    """Silhouette agreement: PSNR of the pooled squared error of (N, H, W) masks in [0, 1].

    The error is pooled over all views before the log, so one perfectly matching view
    does not make the average infinite; ``inf`` only when every view matches exactly.
    """
    return psnr(np.clip(pred_masks, 0, 1), np.clip(gt_masks, 0, 1))


def ssim(pred, target) -> float:
    """Mean SSIM (Gaussian window 11, sigma 1.5) of (H, W, 3) or (N, H, W, 3) images in [0, 1]."""
    import torch
    from pytorch_msssim import ssim as _ssim

    a = np.asarray(pred, dtype=np.float32)
    b = np.asarray(target, dtype=np.float32)
    if a.shape != b.shape:
        raise ValueError(f"ssim: shapes differ, {a.shape} vs {b.shape}")
    if a.ndim == 3:
        a, b = a[None], b[None]
    ta = torch.from_numpy(a).permute(0, 3, 1, 2)
    tb = torch.from_numpy(b).permute(0, 3, 1, 2)
    return float(_ssim(ta, tb, data_range=1.0, size_average=True))


def lpips_status() -> tuple[bool, str]:
    """``(available, reason)``: whether LPIPS can run without downloading anything.

    LPIPS needs the ``lpips`` package, its linear-layer weights (shipped inside the
    package) and an ImageNet backbone (AlexNet/VGG) checkpoint in the torch hub cache.
    """
    try:
        import lpips  # noqa: F401
    except ImportError:
        return False, "the 'lpips' package is not installed (and its AlexNet/VGG backbone weights are not on disk)"
    hub = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch")) / "hub" / "checkpoints"
    found = sorted(p.name for p in hub.glob("*.pth") if p.name.startswith(("alexnet", "vgg16")))
    if not found:
        return False, f"no AlexNet/VGG backbone weights in {hub}; holowarp does not download them"
    return True, f"backbone weights on disk: {', '.join(found)}"
