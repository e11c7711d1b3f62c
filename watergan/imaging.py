"""Low-level image filters shared by the physics (:mod:`watergan.formation`) and training."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def gaussian_blur(images: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Separable Gaussian blur of (B,C,H,W) images; sigma in pixels.

    The kernel exp(-x^2 / (2 sigma^2)) over x = -R..R, R = max(1, ceil(3 sigma)), is normalised to sum 1
    and applied along the width, then the height, with reflected borders; along a side shorter than
    R + 1 pixels the kernel is cut to the R' = side - 1 pixels a reflection can reach. ``sigma_px <= 0``
    returns the images unchanged."""
    if sigma_px <= 0:
        return images
    radius = max(1, int(math.ceil(3.0 * sigma_px)))
    x = torch.arange(-radius, radius + 1, dtype=images.dtype, device=images.device)
    kernel = torch.exp(-0.5 * (x / sigma_px) ** 2)
    kernel = kernel / kernel.sum()
    c = images.shape[1]
    pad_h, pad_w = min(radius, images.shape[-2] - 1), min(radius, images.shape[-1] - 1)
    out = F.pad(images, (pad_w, pad_w, 0, 0), mode="reflect")
    out = F.conv2d(out, kernel[radius - pad_w:radius + pad_w + 1].view(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
    out = F.pad(out, (0, 0, pad_h, pad_h), mode="reflect")
    return F.conv2d(out, kernel[radius - pad_h:radius + pad_h + 1].view(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c)


def augment(images: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Per image: a random left-right and up-down flip and a random shift of up to 1/8 of each side
    (reflected border), drawn from ``generator``; the discriminator's augmentation
    (``watergan.train.GanConfig.disc_augment``)."""
    b, _, h, w = images.shape
    flips = torch.rand(b, 2, generator=generator).to(images.device) < 0.5
    out = torch.where(flips[:, 0, None, None, None], images.flip(-1), images)
    out = torch.where(flips[:, 1, None, None, None], out.flip(-2), out)
    dy, dx = max(1, h // 8), max(1, w // 8)
    padded = F.pad(out, (dx, dx, dy, dy), mode="reflect")
    oy = torch.randint(0, 2 * dy + 1, (b,), generator=generator).tolist()
    ox = torch.randint(0, 2 * dx + 1, (b,), generator=generator).tolist()
    return torch.stack([padded[i, :, oy[i]:oy[i] + h, ox[i]:ox[i] + w] for i in range(b)])
