"""The site depth net: each pixel's depth as a factor on a flat seafloor's, learned from the survey's own range.

    z(x) = z_floor(x) exp(D(u)(x))

``z_floor`` is the camera-z depth of a flat, level seafloor at the frame's navigation altitude and attitude
(:func:`watergan.formation.inverse.flat_floor_depth`), what monocular correction uses without a net. ``u`` is the
linear image (values 0..1, as the restorer takes it) and ``z_floor``, area-averaged to 1/``scale`` of the image's
size and standardised in log (:meth:`SiteDepthNet.forward`), with two channels of the pixel's position (-1..1 across
the image: a tilt or a falloff fixed to the image is told from the scene by where it is). ``D`` is a U-Net (two 3x3
convolutions and ReLU per level, average-pool down, bilinear up with skip connections, a 1x1 output) whose output
is upsampled bilinearly to the image. ``D = 0`` (nearly where it starts) is the flat seafloor: the net learns where
and by how much the scene leaves it (rocks, mounds, coral), and the altimeter gives the metric scale.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

LOG_FLOOR = 0.01
"""Added to the linear values before the log of the net's input."""


def _block(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=1), nn.ReLU(inplace=True),
                         nn.Conv2d(c_out, c_out, 3, padding=1), nn.ReLU(inplace=True))


class SiteDepthNet(nn.Module):
    """D: (B,3,h,w) stored images at 1/``scale`` size -> (B,1,h,w) log factor on the flat seafloor's depth."""

    def __init__(self, widths: tuple[int, ...] = (16, 32, 64, 96), scale: int = 16):
        super().__init__()
        self.widths, self.scale = tuple(widths), int(scale)
        self.register_buffer("log_mean", torch.full((1, 4, 1, 1), -2.5))
        self.register_buffer("log_sd", torch.ones(1, 4, 1, 1))
        self.down = nn.ModuleList(_block(6 if i == 0 else widths[i - 1], widths[i]) for i in range(len(widths)))
        self.up = nn.ModuleList(_block(widths[i] + widths[i + 1], widths[i]) for i in range(len(widths) - 1))
        self.out = nn.Conv2d(widths[0], 1, 1)
        nn.init.normal_(self.out.weight, std=1e-3)  # starts within a millimetre per metre of the flat seafloor
        nn.init.zeros_(self.out.bias)

    def normalise(self, inputs: torch.Tensor) -> None:
        """Set the input's standardisation from the training inputs (:meth:`small`'s, stacked): per channel the
        mean and standard deviation of log(x + 0.01)."""
        log = torch.log(inputs + LOG_FLOOR)
        self.log_mean.copy_(log.mean((0, 2, 3), keepdim=True))
        self.log_sd.copy_(log.std((0, 2, 3), keepdim=True).clamp_min(1e-3))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B,4,h,w) inputs (:meth:`small`: the linear image and the flat seafloor's depth) -> (B,1,h,w) log factors.
        The inputs are standardised in log (underwater frames are dark and their channels far apart in level; a
        frame's brightness and colour, which tell its distance through the water, are kept: the standardisation is
        the training set's, not each image's); the flat seafloor's depth tells the net how far the water is
        expected to be, so that a colour can be read as nearer or farther than that."""
        x = (torch.log(x + LOG_FLOOR) - self.log_mean) / self.log_sd
        b, _, h, w = x.shape
        v, u = torch.meshgrid(torch.linspace(-1, 1, h, dtype=x.dtype, device=x.device),
                              torch.linspace(-1, 1, w, dtype=x.dtype, device=x.device), indexing="ij")
        x = torch.cat([x, u.expand(b, 1, h, w), v.expand(b, 1, h, w)], 1)
        skips = []
        for i, level in enumerate(self.down):
            x = level(x if i == 0 else F.avg_pool2d(x, 2, ceil_mode=True))
            skips.append(x)
        for i in reversed(range(len(self.up))):
            x = F.interpolate(x, size=skips[i].shape[-2:], mode="bilinear", align_corners=False)
            x = self.up[i](torch.cat([skips[i], x], 1))
        return self.out(x)

    def small(self, image: np.ndarray, floor_z: np.ndarray) -> torch.Tensor:
        """(1,4,h,w) the net's input: an (H,W,3) linear image and its flat seafloor's depth (H,W, metres),
        area-averaged to 1/scale."""
        import cv2

        h, w = image.shape[0] // self.scale, image.shape[1] // self.scale
        rgb, z = (cv2.resize(np.ascontiguousarray(a, np.float32), (w, h), interpolation=cv2.INTER_AREA)
                  for a in (image[..., :3], floor_z))  # each averaged alone: no full-resolution copy of both
        return torch.from_numpy(np.concatenate([rgb, z[..., None]], -1)).permute(2, 0, 1)[None]

    @torch.no_grad()
    def factor(self, image: np.ndarray, floor_z: np.ndarray) -> np.ndarray:
        """(H,W) exp(D): the factor on the flat seafloor's depth (and range: both lie along the same ray) of an
        image (H,W,3, linear values 0..1) whose flat seafloor's depth is ``floor_z``."""
        import cv2

        self.eval()
        log_factor = self(self.small(image, floor_z).to(next(self.parameters()).device))[0, 0].cpu().numpy()
        h, w = floor_z.shape
        return np.exp(cv2.resize(log_factor, (w, h), interpolation=cv2.INTER_LINEAR))

    def depth(self, image: np.ndarray, floor_z: np.ndarray) -> np.ndarray:
        """(H,W) camera-z depth (metres) of an image over its flat seafloor's: floor_z exp(D)."""
        return floor_z * self.factor(image, floor_z)

    def to_checkpoint(self) -> dict:
        return {"widths": list(self.widths), "scale": self.scale, "state": self.state_dict()}

    @classmethod
    def from_checkpoint(cls, data: dict) -> SiteDepthNet:
        net = cls(tuple(data["widths"]), int(data["scale"]))
        net.load_state_dict(data["state"])
        return net.eval()
