"""Image metrics: PSNR (RGB or silhouettes), SSIM, and LPIPS availability (method.md §9).

PSNR is ``10 log10(max_val^2 / MSE)`` and is ``inf`` for identical images. SSIM is holowarp's
own differentiable torch implementation (Gaussian window 11, sigma 1.5, valid convolution,
the constants of Wang et al. 2004; checked against ``pytorch-msssim`` in the tests); the
photometric loss of :mod:`holowarp.losses` uses the same function. LPIPS needs
pretrained backbone weights; holowarp never downloads them, so :func:`lpips_status` reports
whether they are on disk and why not.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["SSIM_WINDOW", "SSIM_SIGMA", "psnr", "mask_psnr", "ssim", "lpips_status"]

#: SSIM Gaussian window size and standard deviation (Wang et al. 2004).
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
_SSIM_K1 = 0.01
_SSIM_K2 = 0.03


def _to_bchw(img: torch.Tensor) -> torch.Tensor:
    if img.ndim == 3:  # [H, W, C]
        return img.permute(2, 0, 1).unsqueeze(0)
    if img.ndim == 4:
        return img
    raise ValueError(f"expected an image [H, W, C] or [B, C, H, W], got shape {tuple(img.shape)}")


def _gaussian_window(size: int, sigma: float, dtype, device) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return g / g.sum()


_BAND_CACHE: dict = {}
#: Up to this image side the valid Gaussian filter runs as two banded matrix products; above
#: it as a separable depthwise convolution. The band's products grow with the square of the
#: side, the convolution's work with the side times the window. SSIM forward and backward of a
#: square RGB image on this project's CPU (one torch thread, torch 2.13, alternating runs):
#: band / convolution 2.3 / 3.1 ms at 96, 5.1 / 5.3 at 128, 8.7 / 7.4 at 160, 13.0 / 9.6 at
#: 192, 30 / 17 at 256. So 128² runs keep the band (and their numbers), and a 256² run's
#: photometric loss costs 13 ms less per step. (The former bound, 320, cost 2x at 256.)
_BAND_MAX_SIDE = 144


def _band(n: int, size: int, sigma: float, dtype, device) -> torch.Tensor:
    """[n - size + 1, n] matrix whose rows hold the window at successive offsets."""
    key = (n, size, sigma, dtype, str(device))
    band = _BAND_CACHE.get(key)
    if band is None:
        g = _gaussian_window(size, sigma, dtype, device)
        m = n - size + 1
        band = torch.zeros(m, n, dtype=dtype, device=device)
        rows = torch.arange(m, device=device)
        for k in range(size):
            band[rows, rows + k] = g[k]
        if len(_BAND_CACHE) > 32:
            _BAND_CACHE.clear()
        _BAND_CACHE[key] = band
    return band


def _gaussian_blur_valid(t: torch.Tensor, size: int, sigma: float) -> torch.Tensor:
    """Separable Gaussian filter without padding of [B, C, H, W] -> [B, C, H', W']."""
    h, w = t.shape[-2:]
    if max(h, w) <= _BAND_MAX_SIDE:
        bh = _band(h, size, sigma, t.dtype, t.device)
        bw = _band(w, size, sigma, t.dtype, t.device)
        return bh @ t @ bw.T
    c = t.shape[1]
    g = _gaussian_window(size, sigma, t.dtype, t.device)
    wx = g.view(1, 1, 1, -1).expand(c, 1, 1, size)
    wy = g.view(1, 1, -1, 1).expand(c, 1, size, 1)
    return F.conv2d(F.conv2d(t, wx, groups=c), wy, groups=c)


def ssim(
    img1: torch.Tensor,
    img2: torch.Tensor,
    *,
    data_range: float = 1.0,
    window_size: int = SSIM_WINDOW,
    sigma: float = SSIM_SIGMA,
    reduce: bool = True,
) -> torch.Tensor:
    """Structural similarity of two images (same shape, ``[H, W, C]`` or ``[B, C, H, W]``).

    Gaussian-weighted local statistics with a separable window and *valid* convolution (no
    padding), the convention of Wang et al.'s reference code and ``pytorch-msssim``.

    Returns:
        the mean SSIM (scalar) if ``reduce``, else the SSIM map ``[B, C, H', W']``.
    """
    if img1.shape != img2.shape:
        raise ValueError(f"ssim: image shapes differ: {tuple(img1.shape)} vs {tuple(img2.shape)}")
    x, y = _to_bchw(img1), _to_bchw(img2)
    c = x.shape[1]
    if min(x.shape[-2:]) < window_size:
        raise ValueError(f"ssim: images {tuple(x.shape[-2:])} are smaller than the {window_size}-pixel window")
    # The five local moments in two filtering passes: those of x (and x y), and those of y
    # alone, so that a loss whose target needs no gradient (the training images) runs the
    # filter's backward on three moments instead of five.
    mu_x, exx, exy = _gaussian_blur_valid(torch.cat([x, x * x, x * y], dim=1), window_size, sigma).split(c, dim=1)
    mu_y, eyy = _gaussian_blur_valid(torch.cat([y, y * y], dim=1), window_size, sigma).split(c, dim=1)
    sxx = exx - mu_x * mu_x
    syy = eyy - mu_y * mu_y
    sxy = exy - mu_x * mu_y
    c1 = (_SSIM_K1 * data_range) ** 2
    c2 = (_SSIM_K2 * data_range) ** 2
    cs = (2.0 * sxy + c2) / (sxx + syy + c2)
    smap = ((2.0 * mu_x * mu_y + c1) / (mu_x * mu_x + mu_y * mu_y + c1)) * cs
    return smap.mean() if reduce else smap




def _np64(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def psnr(pred, target, *, max_val: float = 1.0) -> float:
    """PSNR in dB over all elements of two same-shaped arrays or tensors; ``inf`` when
    identical."""
    a = _np64(pred)
    b = _np64(target)
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
