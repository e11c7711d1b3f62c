"""Marine snow: sparse particles in the water lit by the camera's light."""

from __future__ import annotations

import torch

from ...imaging import gaussian_blur
from ..effect import RANK_SCATTER, Effect
from ..params import Param
from ..registry import register


def snow_particles(range_m: torch.Tensor, frame: torch.Tensor, density_per_mpx: float, seed: int):
    """Particles per frame: pixel index, distance (metres) and visibility, drawn from a generator
    seeded by (seed, frame) so the same frame always shows the same snow. A particle lies uniformly
    between 0.3 m and 95% of the scene range behind its pixel (it sits in front of the scene)."""
    b, _, h, w = range_m.shape
    count = max(1, int(round(density_per_mpx * h * w / 1e6)))
    out = []
    for i in range(b):
        g = torch.Generator().manual_seed(int(seed) * 1_000_003 + int(frame[i]))
        idx = torch.randint(0, h * w, (count,), generator=g)
        frac = torch.rand(count, generator=g, dtype=torch.float64)
        far = range_m[i, 0].reshape(-1)[idx].detach().cpu().double() * 0.95
        dist = 0.3 + frac * (far - 0.3).clamp_min(0.0)
        out.append((idx, dist.to(range_m.dtype), far > 0.3))
    return out


def render_snow(range_m: torch.Tensor, frame: torch.Tensor, brightness: torch.Tensor, density_per_mpx: float,
                size_px: float, seed: int) -> torch.Tensor:
    """S = G_sigma * sum_p (brightness / d_p^2) delta(x - x_p), grey, added to the backscatter.

    Each particle p at distance d_p (metres) is lit by a light at the camera (inverse square), so
    near particles are brighter; sigma = ``size_px`` x W / 640 pixels. Returns (B,3,H,W).
    """
    b, _, h, w = range_m.shape
    sparse = torch.zeros(b, 1, h * w, dtype=range_m.dtype, device=range_m.device)
    for i, (idx, dist, seen) in enumerate(snow_particles(range_m, frame, density_per_mpx, seed)):
        sparse[i, 0].index_add_(0, idx[seen].to(sparse.device), (1.0 / dist[seen] ** 2).to(sparse.device))
    spots = gaussian_blur(sparse.view(b, 1, h, w), size_px * w / 640.0)
    spots = spots / spots.amax(dim=(2, 3), keepdim=True).clamp_min(1e-12) * sparse.amax(dim=2).view(b, 1, 1, 1)
    return (brightness * spots).expand(b, 3, h, w)


@register
class MarineSnow(Effect):
    name = "marine_snow"
    summary = "sparse bright particles in front of the scene, lit by the camera's light (inverse square)"
    signature = "frame and spatial frequency: isolated bright outliers in single views of a point"
    axis = "frame"
    rank = RANK_SCATTER + 2
    simulation_params = {"brightness": 0.3, "density_per_mpx": 3000.0}
    needs_image = True
    params = (
        Param("brightness", 0.05, 0.0, 10.0, "linear radiance m^2", "particle radiance at 1 m"),
        Param("density_per_mpx", 400.0, 0.0, 1e5, "1/Mpx", "particles per million pixels", learnable=False),
        Param("size_px", 1.0, 0.3, 10.0, "px", "particle blur sigma at 640 px width", learnable=False),
        Param("seed", 0.0, 0.0, 1e6, "", "random seed of the particle field", learnable=False),
    )
    neutral = {"brightness": 0.0}

    def forward(self, state):
        like = state.direct
        frame = state.frame_index if state.frame_index is not None else torch.arange(like.shape[0])
        snow = render_snow(state.range_m, frame, self.param("brightness", like),
                           self.param("density_per_mpx").item(), self.param("size_px").item(),
                           int(round(self.param("seed").item())))
        return state.replace(backscatter=state.backscatter + snow)
