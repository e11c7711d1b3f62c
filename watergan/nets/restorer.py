"""The restorer: a depth net and a colour net that turn an underwater image into an in-air one (paper Fig. 3).

Both nets share a SegNet-style core :class:`SegNetCore` (Badrinarayanan et al.): conv blocks
(3x3 conv, batch norm, ReLU) with three levels of 2x2 max pooling whose argmax indices drive
``MaxUnpool2d`` in the decoder, and the core's input concatenated to the decoded features before the
final convolution, so the output is ``y = conv([dec(enc(x)), x])``. The core needs sides divisible by 8.

- :class:`DepthNet`: the core at ``depth_hw`` (56x56 by default); image in, relative depth
  (0..1, 1 = the farthest pixel of the image) out. The full-resolution image is area-averaged to
  56x56 first (the aspect ratio is not kept, as in the paper).
- :class:`ColourNet`: the core at 1/``factor`` of the full resolution (the paper trains it at
  128x128), wrapped by an average pool P (``factor`` x ``factor``) and a depthwise ``ConvTranspose2d``
  U initialised as bilinear interpolation (it reproduces ``F.interpolate(mode="bilinear",
  align_corners=False)`` away from the borders before training). Input: the image, its upsampled
  estimated depth and position maps (7 channels; see "Position" below); output RGB::

      y = U(C(P(x))) + S([U(C(P(x))), F(x)], x)

  with F a full-resolution conv block (skip layer 1: its features are concatenated to the upsampled
  output) and S a 1x1 block followed by a 3x3 conv over [features, x] (skip layer 2: the full-resolution
  input itself is concatenated), so texture survives the low-resolution core. The last conv of S
  starts at zero, so a net whose core comes from the 128x128 stage starts as exactly its upsampled
  output. ``skip=False`` (the ablation) gives y = U(C(P(x))).

  ``head="affine"`` (the default): the core does not output colours but a per-pixel gain and offset
  per channel, (g_c, o_c) = U(C(P(x))), applied to the image itself in linear light (:func:`apply_affine`):

      y_c = srgb(exp(g_c) lin(x_c) + o_c)

  The formation model is of that form: the camera records k V (J t + B) per channel, whose inverse
  J = I / (k V t) - B / t is affine in the recorded I with coefficients that vary smoothly with range
  and image position. The net only learns those smooth fields, so it corrects colours that its
  training images never held (the colour board's saturated patches) and full-resolution texture
  passes through. The skip layers then add their correction to this y. ``head="direct"`` is the
  paper's: the core outputs the colours.

  Global context: the core's input also holds the per-channel mean and standard deviation of the
  whole image at its resolution (:func:`image_context`, 6 constant maps). The correction depends on
  the absolute range, which relative depth does not hold and the core's receptive field cannot see
  across a frame; without them a restorer corrects each frame's red differently, in step with the
  frame's range. Training crops take the context of their whole image.

  Altitude (``altitude=True``): the camera's height above the seafloor in metres, as the vehicle's
  altimeter reads it, enters the core as one more constant map. Relative depth and colour statistics
  leave the absolute range ambiguous (a dim red frame may be far or of dark sediment), and the
  inverse's gain exp(eta r) depends on it. Training frames take the median of their depth map.

  Range (``range_input=True``, the RGB-D mode): the colour net's input also holds each pixel's range in
  metres (the dense stage's, where the survey has it), one more map beside the estimated depth; the inverse's
  gain exp(eta r) and offset follow it pixel by pixel, which neither relative depth nor the altitude gives.
  Holes take the image's median range (:func:`fill_range_holes`). With the affine head the inverse's fields
  are per-pixel functions of range and image position alone, g_c = eta_c r - ln(k_c V(u, v)) and
  o_c = -B_c(r) exp(eta_c r) with B_c(r) = b_c (1 - exp(-beta_c r)), whatever the scene; a geometry branch, a
  per-pixel MLP (1x1 convolutions, ``GEOMETRY_WIDTH`` wide, its last layer starting at zero) on [r, u, v, rho^2],
  adds its fields to the core's, so the core only learns what the content adds.

  Water (``water``, RGB-D mode): the stack the training pairs were rendered with (``generate``'s manifest; the site
  water when WaterGAN holds it), inverted at each pixel's range (:func:`water_fields`, the fields of
  :func:`watergan.formation.inverse.inverse_fields`: g_c = -ln A_c, o_c = -C_c / A_c) and added to the core's fields
  at full resolution before they are applied. The net then starts as the exact inverse of that water, the physics
  correction's, and the core, the geometry branch and the skip layers learn what the stack does not hold (the
  clipping and 8-bit rounding of the pairs, a learned scattering, what the discriminator added). Without it the
  geometry branch has to learn those fields from zero. Measurements of these inputs: benchmarks/RESULTS/restorer.md.

  Position: the colour net's input also holds each pixel's place in the whole image
  (:func:`position_maps`: u, v in [-1, 1] and the squared radius, 1 at a corner), since vignetting
  darkens the corners and a convolutional net cannot otherwise tell a corner from the centre (without
  them the raw frames' centre-to-corner falloff stays in place). Training crops take their part of the
  whole image's maps.

Pixels are the stored (sRGB-encoded) values scaled to 0..1. :func:`restore` pads any size to a
multiple of :func:`Restorer.multiple` (replicating the border), runs both nets and crops back.
"""

from __future__ import annotations

import copy
import threading
from dataclasses import asdict, dataclass
from enum import StrEnum

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from watergan.formation.inverse import SIGNAL_FLOOR

LEVELS = 3
"""Max-pooling levels of the core: its input sides must be multiples of 2**LEVELS."""
class Head(StrEnum):
    """What the colour core outputs: per-channel gain and offset fields, or the colours themselves."""

    affine = "affine"
    direct = "direct"


HEADS = tuple(Head)


@dataclass(frozen=True)
class RestorerWidths:
    """Channel widths of the restorer's nets."""

    depth_core: tuple[int, int, int, int] = (16, 24, 32, 48)
    """Depth core channels at full, 1/2, 1/4 and 1/8 of its 56x56 input."""
    colour_core: tuple[int, int, int, int] = (16, 24, 32, 48)
    """Colour core channels at 1, 1/2, 1/4, 1/8 of its (1/factor of full) resolution."""
    full_res: int = 8
    """Channels of the colour net's full-resolution skip layers (the cost at 640x480 is mostly here)."""
    blocks_per_level: int = 1
    """Conv blocks per encoder and decoder level (SegNet: 2-3)."""


#: A small setting that corrects 640x480 at several frames per second on a 2-core CPU.
CPU_WIDTHS = RestorerWidths()
#: SegNet-sized widths as in the paper (for a GPU).
PAPER_WIDTHS = RestorerWidths(depth_core=(64, 128, 256, 512), colour_core=(64, 128, 256, 512), full_res=64,
                              blocks_per_level=2)
class WidthPreset(StrEnum):
    """Net widths: small for the CPU, or SegNet-sized as the paper (for a GPU)."""

    cpu = "cpu"
    paper = "paper"


WIDTH_PRESETS = {WidthPreset.cpu: CPU_WIDTHS, WidthPreset.paper: PAPER_WIDTHS}


def conv_block(c_in: int, c_out: int, kernel: int = 3) -> nn.Sequential:
    """k x k convolution (same size, k odd), batch norm, ReLU."""
    return nn.Sequential(nn.Conv2d(c_in, c_out, kernel, padding=kernel // 2, bias=False), nn.BatchNorm2d(c_out),
                         nn.ReLU(inplace=True))


def _blocks(c_in: int, c_out: int, count: int) -> nn.Sequential:
    return nn.Sequential(conv_block(c_in, c_out), *(conv_block(c_out, c_out) for _ in range(count - 1)))


class SegNetCore(nn.Module):
    """SegNet encoder-decoder: enc_k -> maxpool (indices kept) three times, a bottleneck, then
    MaxUnpool with the same indices -> dec_k; finally y = conv3x3([decoded features, input])."""

    def __init__(self, c_in: int, c_out: int, widths: tuple[int, int, int, int], blocks: int = 1) -> None:
        super().__init__()
        w = widths
        self.enc = nn.ModuleList([_blocks(a, b, blocks) for a, b in ((c_in, w[0]), (w[0], w[1]), (w[1], w[2]))])
        self.bottleneck = nn.Sequential(_blocks(w[2], w[3], blocks), conv_block(w[3], w[2]))
        self.dec = nn.ModuleList([_blocks(a, b, blocks) for a, b in ((w[0], w[0]), (w[1], w[0]), (w[2], w[1]))])
        self.pool = nn.MaxPool2d(2, 2, return_indices=True)
        self.unpool = nn.MaxUnpool2d(2, 2)
        self.head = nn.Conv2d(w[0] + c_in, c_out, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-2] % 2**LEVELS or x.shape[-1] % 2**LEVELS:
            raise ValueError(f"SegNetCore needs sides divisible by {2**LEVELS}, got {tuple(x.shape[-2:])}")
        h, indices = x, []
        for enc in self.enc:
            h, idx = self.pool(enc(h))
            indices.append(idx)
        h = self.bottleneck(h)
        for level in reversed(range(LEVELS)):
            h = self.dec[level](self.unpool(h, indices[level]))
        return self.head(torch.cat([h, x], dim=1))


class DepthNet(nn.Module):
    """Relative depth at ``depth_hw`` from an image of any size (area-averaged to ``depth_hw``)."""

    def __init__(self, widths: RestorerWidths = CPU_WIDTHS, depth_hw: tuple[int, int] = (56, 56)) -> None:
        super().__init__()
        if depth_hw[0] % 2**LEVELS or depth_hw[1] % 2**LEVELS:
            raise ValueError(f"depth_hw must be multiples of {2**LEVELS}, got {depth_hw}")
        self.depth_hw = tuple(depth_hw)
        self.core = SegNetCore(3, 1, widths.depth_core, widths.blocks_per_level)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """(B,3,H,W) -> (B,1,*depth_hw) relative depth (unclamped)."""
        return self.core(F.adaptive_avg_pool2d(image, self.depth_hw))


def srgb_decode(v: torch.Tensor) -> torch.Tensor:
    """IEC 61966-2-1 decoding of 0..1 values: v / 12.92 for v <= 0.04045, else ((v + 0.055) / 1.055)^2.4."""
    v = v.clamp(0.0, 1.0)
    return torch.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def srgb_encode(x: torch.Tensor) -> torch.Tensor:
    """IEC 61966-2-1 encoding of linear values >= 0: 12.92 x for x <= 0.0031308, else 1.055 x^(1/2.4) - 0.055
    (values above 1 are encoded on the same curve, not clipped, so the loss still sees them)."""
    x = x.clamp(min=0.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def apply_affine(fields: torch.Tensor, image: torch.Tensor, linear: torch.Tensor | None = None) -> torch.Tensor:
    """y = srgb(max(exp(g) lin(x) + o, s exp(g) lin(x))) per channel (s:
    :data:`watergan.formation.inverse.SIGNAL_FLOOR`): ``fields`` (B,6,H,W) holds the log gains g and offsets o
    (linear light), ``image`` (B,3,H,W) the sRGB-encoded 0..1 input; zero fields give y = x. Without gradients
    (correcting frames) the same equation in fewer full-resolution passes (:func:`_apply_affine_in_place`), with
    lin(x) taken from ``linear`` (B,3,H,W) where the caller decoded it already (a table lookup when reading)."""
    if torch.is_grad_enabled() and (fields.requires_grad or image.requires_grad):
        gained = srgb_decode(image) * torch.exp(fields[:, :3])
        return srgb_encode(torch.maximum(gained + fields[:, 3:], SIGNAL_FLOOR * gained))
    return _apply_affine_in_place(fields, image, linear)


def _apply_affine_in_place(fields: torch.Tensor, image: torch.Tensor,
                           linear: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`apply_affine` for inference: the powers as exp(a ln v), each step in place on one of a few buffers
    (the same values to float rounding; on a CPU each new full-resolution tensor costs more than its arithmetic)."""
    if linear is None:
        lin = image.clamp(0.0, 1.0)
        dark = lin <= 0.04045
        curve = lin.add(0.055).mul_(1 / 1.055).log_().mul_(2.4).exp_()
        lin = torch.where(dark, lin.mul_(1 / 12.92), curve).mul_(fields[:, :3].exp())
    else:
        lin = fields[:, :3].exp().mul_(linear)
    floor = lin.mul(SIGNAL_FLOOR)
    torch.maximum(lin.add_(fields[:, 3:]), floor, out=lin).clamp_(min=0.0)
    dark = lin <= 0.0031308
    curve = torch.clamp(lin, min=0.0031308).log_().mul_(1 / 2.4).exp_().mul_(1.055).sub_(0.055)
    return torch.where(dark, lin.mul_(12.92), curve)


CONTEXT_CHANNELS = 6
"""Channels of :func:`image_context`."""
ALTITUDE_CHANNELS = 1
"""The altitude map's channels (``altitude=True``)."""
POSITION_CHANNELS = 3
"""Channels of :func:`position_maps`."""
IMAGE_CHANNELS = 4 + POSITION_CHANNELS
"""The colour net's input: RGB, estimated depth and the position maps."""
RANGE_CHANNELS = 1
"""The range map's channels (``range_input=True``)."""
GEOMETRY_WIDTH = 32
"""Hidden channels of the RGB-D colour net's geometry branch (see the module docstring)."""


def fill_range_holes(range_m: torch.Tensor) -> tuple[torch.Tensor, float]:
    """(B,1,H,W) range in metres with holes (0 or NaN) -> the same with each image's holes set to the median of
    its valid pixels (:func:`fill_holes`), and the share of pixels filled. An image without any range is an error."""
    if range_m.device.type == "cpu":
        filled = [fill_holes(r[0].numpy()) for r in range_m]
        out = torch.stack([torch.from_numpy(f[0]) for f in filled])[:, None].to(range_m.dtype)
        return out, float(np.mean([f[1] for f in filled]))
    valid = torch.isfinite(range_m) & (range_m > 0)
    out = range_m.clone()
    for b in range(range_m.shape[0]):
        values = range_m[b][valid[b]]
        if not len(values):
            raise ValueError(NO_RANGE)
        out[b][~valid[b]] = float(values.median())
    return out, float((~valid).float().mean())


NO_RANGE = "an image has no range at any pixel: the RGB-D restorer needs range (use the monocular restorer, " \
           "range_input=False)"


def fill_holes(range_m: np.ndarray) -> tuple[np.ndarray, float]:
    """(H,W) range in metres with holes (0 or NaN) -> the same with its holes set to the median of its valid pixels
    (the lower middle value, as torch's median), and the share of pixels filled; no range at all is an error."""
    valid = np.isfinite(range_m) & (range_m > 0)
    values = range_m[valid]
    if not len(values):
        raise ValueError(NO_RANGE)
    k = (len(values) - 1) // 2
    return np.where(valid, range_m, np.partition(values, k)[k]), 1.0 - len(values) / range_m.size


def invertible_water(stack: list[dict]) -> list[dict]:
    """The effects of a stack configuration that act pixel by pixel on any frame: effects on whole-image
    neighbourhoods (``needs_image``: blur, the learned scattering's masks) have no per-pixel inverse, and effects
    with a value per survey frame (``frame_gain``, a plugin's exposure) none for an image of no known frame; the nets
    learn them."""
    from watergan.formation import get

    return [e for e in stack if not get(e["name"]).needs_image and not get(e["name"]).varies_by_frame()]


def water_fields(water: list[dict], range_m: torch.Tensor,
                 intrinsics: tuple[float, float, float, float] | None = None, exact: bool = False) -> torch.Tensor:
    """(B,6,H,W) the affine head's fields (log gain g, offset o, per channel) of the inverse of a stack
    configuration ``water`` (effects acting pixel by pixel, :func:`invertible_water`) at each pixel's range:
    J = (I - C) / A in linear light, so g = -ln A and o = -C / A (:func:`apply_affine`) with A, C of
    :func:`watergan.formation.inverse.inverse_fields` (``exact``, and always for a water that reads surface
    normals, such as strobes), else interpolated from a grid of positions and ranges
    (:class:`watergan.formation.inverse.FieldTable`, with its accuracy). For many frames, :class:`WaterFields`
    keeps the grid between calls.

    range_m: (B,1,H,W) metres, holes filled (:func:`fill_range_holes`).
    intrinsics: (fx, fy, cx, cy) pixels of these images; effects that read camera-frame points or normals (the
    lights) need them; without them depth = range."""
    return WaterFields(water, exact)(range_m, intrinsics)


class WaterFields:
    """The fields of :func:`water_fields` for a sequence of frames: the grid (a
    :class:`watergan.formation.inverse.FieldTable`) is kept while it covers the frames' size, camera and ranges,
    and rebuilt over the union of its span and theirs when it does not; evaluating the stack on the grid costs
    more than looking up a frame. Safe to call from several threads."""

    def __init__(self, water: list[dict], exact: bool = False) -> None:
        from watergan.formation import Stack
        from watergan.formation.inverse import needs_normals

        self.stack = Stack.from_config(water)
        self.exact = exact or needs_normals(self.stack)
        self._table = None
        self._lock = threading.Lock()

    def __call__(self, range_m: torch.Tensor,
                 intrinsics: tuple[float, float, float, float] | None = None) -> torch.Tensor:
        """(B,6,H,W) the fields at every pixel of range maps (B,1,H,W) (metres, holes filled) of images with these
        ``intrinsics`` (fx, fy, cx, cy)."""
        import numpy as np

        from watergan.formation.inverse import FieldTable, inverse_fields, range_span

        K = None
        if intrinsics is not None:
            fx, fy, cx, cy = intrinsics
            K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        if self.exact:
            out = []
            for r in range_m[:, 0].detach().cpu().numpy():
                a, c, _ = inverse_fields(r, self.stack, K, dtype=torch.float32)
                a = a.clamp_min(1e-6)
                out.append(torch.cat([-torch.log(a), -c / a], dim=1))
            return torch.cat(out).to(range_m.device)
        with self._lock:
            table = self._table
            if table is None or not table.covers(range_m, K):
                lo, hi = range_span(range_m)
                if table is not None and table.serves(*range_m.shape[-2:], K):
                    lo, hi = min(lo, table.r_lo_m), max(hi, table.r_hi_m)
                table = self._table = FieldTable.build(self.stack, range_m.shape[-1], range_m.shape[-2], K, lo, hi)
        return table.sample(range_m)


def position_maps(height: int, width: int, device: torch.device | None = None) -> torch.Tensor:
    """(1,3,H,W): u and v of each pixel centre in [-1, 1] (left/top to right/bottom) and the squared
    radius (u^2 + v^2) / 2, 1 at the corners."""
    v = (torch.arange(height, device=device, dtype=torch.float32) + 0.5) / height * 2 - 1
    u = (torch.arange(width, device=device, dtype=torch.float32) + 0.5) / width * 2 - 1
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu, vv, (uu * uu + vv * vv) / 2])[None]


def image_context(small: torch.Tensor) -> torch.Tensor:
    """(B,6): the per-channel mean and standard deviation of the colour channels of a (B,C,h,w) image
    at the colour core's resolution."""
    rgb = small[:, :3].flatten(2)
    return torch.cat([rgb.mean(dim=2), rgb.std(dim=2)], dim=1)


def bilinear_kernel(factor: int) -> torch.Tensor:
    """The (2f, 2f) kernel k(i, j) = t(i) t(j), t(i) = 1 - |i - (2f - 1)/2| / f, which as a transposed
    convolution with stride f and padding f/2 equals bilinear upsampling by f with half-pixel centres
    (``align_corners=False``) away from the borders."""
    centre = (2 * factor - 1) / 2.0
    t = 1.0 - (torch.arange(2 * factor, dtype=torch.float64) - centre).abs() / factor
    return (t[:, None] * t[None, :]).float()


def bilinear_upsampler(channels: int, factor: int) -> nn.ConvTranspose2d:
    """A depthwise ``ConvTranspose2d`` (kernel 2f, stride f, padding f/2; output size f x input)
    initialised with :func:`bilinear_kernel`; it stays learnable."""
    if factor < 2 or factor % 2:
        raise ValueError(f"the upsampling factor must be even and >= 2, got {factor}")
    up = nn.ConvTranspose2d(channels, channels, 2 * factor, stride=factor, padding=factor // 2, groups=channels,
                            bias=False)
    with torch.no_grad():
        up.weight.copy_(bilinear_kernel(factor).expand(channels, 1, 2 * factor, 2 * factor))
    return up


class ColourNet(nn.Module):
    """In-air RGB at full resolution from the image and its estimated depth (see the module docstring)."""

    def __init__(self, widths: RestorerWidths = CPU_WIDTHS, factor: int = 4, skip: bool = True,
                 head: str = "affine", altitude: bool = False, range_input: bool = False) -> None:
        super().__init__()
        if head not in HEADS:
            raise ValueError(f"head must be one of {HEADS}, got {head!r}")
        self.factor, self.skip, self.head, self.altitude, self.range_input = factor, skip, head, altitude, range_input
        self.in_channels = IMAGE_CHANNELS + (RANGE_CHANNELS if range_input else 0)
        channels = 6 if head == "affine" else 3
        c_in = self.in_channels + CONTEXT_CHANNELS + (ALTITUDE_CHANNELS if altitude else 0)
        self.core = SegNetCore(c_in, channels, widths.colour_core, widths.blocks_per_level)
        if head == "affine":  # zero fields: the net starts as the identity
            nn.init.zeros_(self.core.head.weight)
            nn.init.zeros_(self.core.head.bias)
        self.geometry = None
        if range_input and head == "affine":  # per-pixel fields of range and position (module docstring)
            g = GEOMETRY_WIDTH
            self.geometry = nn.Sequential(nn.Conv2d(RANGE_CHANNELS + POSITION_CHANNELS, g, 1), nn.ReLU(inplace=True),
                                          nn.Conv2d(g, g, 1), nn.ReLU(inplace=True), nn.Conv2d(g, channels, 1))
            nn.init.zeros_(self.geometry[-1].weight)
            nn.init.zeros_(self.geometry[-1].bias)
        self.up = bilinear_upsampler(channels, factor)
        if skip:
            f = widths.full_res
            self.skip1 = conv_block(self.in_channels, f)
            self.fuse = conv_block(3 + f, f, kernel=1)  # 1x1: the full-resolution cost is in skip1 and out
            self.out = nn.Conv2d(f + self.in_channels, 3, 3, padding=1)
            nn.init.zeros_(self.out.weight)
            nn.init.zeros_(self.out.bias)

    def colours(self, core_out: torch.Tensor, x: torch.Tensor, linear: torch.Tensor | None = None) -> torch.Tensor:
        """The colours of a core output at the size of the input x (B,C,H,W): the output itself
        (``head="direct"``) or its fields applied to x (:func:`apply_affine`; ``linear``: x's colours decoded)."""
        return core_out if self.head == "direct" else apply_affine(core_out, x[:, :3], linear)

    def run_core(self, x_small: torch.Tensor, context: torch.Tensor | None = None,
                 altitude_m: torch.Tensor | None = None) -> torch.Tensor:
        """The core on (B,C,h,w) image, depth, position [and range] at its resolution, with the image's context (B,6)
        (:func:`image_context`; None: that of ``x_small`` itself) and, when the net takes it, the altitude
        (B,) in metres, as constant maps."""
        context = image_context(x_small) if context is None else context
        if self.altitude:
            if altitude_m is None:
                raise ValueError("this colour net takes each image's altitude (metres): give altitude_m")
            context = torch.cat([context, altitude_m.reshape(-1, 1).to(context)], dim=1)
        maps = context[:, :, None, None].expand(-1, -1, *x_small.shape[-2:])
        out = self.core(torch.cat([x_small, maps], dim=1))
        if self.geometry is not None:  # position (channels 4-6) and range (the last) at the core's resolution
            out = out + self.geometry(torch.cat([x_small[:, 4:IMAGE_CHANNELS], x_small[:, IMAGE_CHANNELS:]], dim=1))
        return out

    def core_colours(self, x_small: torch.Tensor, altitude_m: torch.Tensor | None = None,
                     water: torch.Tensor | None = None) -> torch.Tensor:
        """(B,C,h,w) image, depth, position [and range] at the core's resolution -> (B,3,h,w): the core alone
        (stage 1); ``water``: the water's fields at that resolution (:func:`water_fields`), added to the core's."""
        out = self.run_core(x_small, None, altitude_m)
        return self.colours(out if water is None else out + water, x_small)

    def coarse(self, x_small: torch.Tensor, image: torch.Tensor, context: torch.Tensor | None = None,
               altitude_m: torch.Tensor | None = None, water: torch.Tensor | None = None,
               linear: torch.Tensor | None = None) -> torch.Tensor:
        """(B,3,H,W) y = colours(U(C(x_small)) [+ water], image): the net without its skip layers, from the input
        average-pooled by ``factor`` (``x_small``) and the full-resolution image (B,3,H,W) (``linear``: its colours
        decoded, :meth:`colours`); the other arguments as :meth:`forward`'s."""
        fields = self.up(self.run_core(x_small, context, altitude_m))
        if water is not None:  # in place when correcting: one full-resolution tensor fewer
            fields = fields + water if torch.is_grad_enabled() else fields.add_(water)
        return self.colours(fields, image, linear)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None,
                altitude_m: torch.Tensor | None = None, water: torch.Tensor | None = None) -> torch.Tensor:
        """(B,C,H,W) image, depth, position [and range], sides multiples of factor * 8 -> (B,3,H,W); ``context``:
        that of the whole image when x is a crop of it (None: x's own); ``altitude_m`` (B,): see :meth:`run_core`;
        ``water`` (B,6,H,W): the water's fields (:func:`water_fields`), added to the upsampled core's."""
        coarse = self.coarse(F.avg_pool2d(x, self.factor), x[:, :3], context, altitude_m, water)
        if not self.skip:
            return coarse
        h = self.fuse(torch.cat([coarse, self.skip1(x)], dim=1))
        return coarse + self.out(torch.cat([h, x], dim=1))


class Restorer(nn.Module):
    """Depth net + colour net. ``forward(image)`` -> (rgb, depth), both at the image's size."""

    def __init__(self, widths: RestorerWidths = CPU_WIDTHS, factor: int = 4, skip: bool = True,
                 depth_hw: tuple[int, int] = (56, 56), head: str = "affine", altitude: bool = False,
                 range_input: bool = False, water: list[dict] | None = None) -> None:
        super().__init__()
        if water is not None and not (range_input and head == "affine"):
            raise ValueError("a restorer starts from a water's inverse only in RGB-D mode (range_input) with the "
                             "affine head")
        self.widths, self.factor, self.skip, self.depth_hw = widths, factor, skip, tuple(depth_hw)
        self.water = None if water is None else invertible_water(water)
        """The stack configuration whose inverse the colour net starts from (see the module docstring)."""
        self.depth_net = DepthNet(widths, depth_hw)
        self.colour_net = ColourNet(widths, factor, skip, head, altitude, range_input)

    @property
    def altitude(self) -> bool:
        """Whether the colour net takes each image's altitude (metres)."""
        return self.colour_net.altitude

    @property
    def range_input(self) -> bool:
        """Whether the colour net takes each pixel's range (metres): the RGB-D mode."""
        return self.colour_net.range_input

    @property
    def multiple(self) -> int:
        """Full-resolution sides must be multiples of this (factor * 2**LEVELS)."""
        return self.factor * 2**LEVELS

    def for_inference(self) -> Restorer:
        """A copy in eval mode for correcting frames, with the same outputs (to float rounding): each batch norm
        folded into the convolution before it, and the weights of the full-resolution 3x3 output convolution laid
        out channels-last, which oneDNN runs faster on a CPU (measurements: benchmarks/RESULTS/restorer.md)."""
        from torch.nn.utils.fusion import fuse_conv_bn_eval

        model = copy.deepcopy(self).eval()
        for block in model.modules():
            if isinstance(block, nn.Sequential) and len(block) == 3 and isinstance(block[0], nn.Conv2d) \
                    and isinstance(block[1], nn.BatchNorm2d):
                block[0], block[1] = fuse_conv_bn_eval(block[0], block[1]), nn.Identity()
        if model.colour_net.skip:
            model.colour_net.out.to(memory_format=torch.channels_last)
        return model

    def to_config(self) -> dict:
        return {"widths": asdict(self.widths), "factor": self.factor, "skip": self.skip,
                "depth_hw": list(self.depth_hw), "head": str(self.colour_net.head),
                "altitude": self.altitude, "range_input": self.range_input, "water": self.water}

    @classmethod
    def from_config(cls, config: dict) -> Restorer:
        w = config["widths"]
        widths = RestorerWidths(tuple(w["depth_core"]), tuple(w["colour_core"]), int(w["full_res"]),
                                int(w["blocks_per_level"]))
        return cls(widths, int(config["factor"]), bool(config["skip"]), tuple(config["depth_hw"]), config["head"],
                   bool(config["altitude"]), bool(config.get("range_input", False)), config.get("water"))

    def forward(self, image: torch.Tensor, position: torch.Tensor | None = None,
                altitude_m: torch.Tensor | None = None, range_m: torch.Tensor | None = None,
                water: torch.Tensor | None = None,
                linear: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(B,3,H,W), H and W multiples of ``multiple`` -> RGB (B,3,H,W) and relative depth (B,1,H,W):
        depth d = bilinear(DepthNet(x)) and rgb = ColourNet([x, d, p(, r)]) with p the position maps (1,3,H,W)
        (None: :func:`position_maps` of the image itself), r each pixel's range (B,1,H,W) in metres without holes
        when the net takes it (RGB-D mode) and, when it takes it, each image's altitude (B,) in metres; ``water``
        (B,6,H,W): the fields of :func:`water_fields` at r, for a restorer that starts from a water; ``linear``: the
        image's colours decoded to linear light, where the caller has them (a restorer without skip layers then skips
        decoding them, :func:`apply_affine`)."""
        h, w = image.shape[-2:]
        depth = F.interpolate(self.depth_net(image), size=(h, w), mode="bilinear", align_corners=False)
        position = position_maps(h, w, image.device) if position is None else position
        maps = [image, depth, position.expand(image.shape[0], -1, -1, -1)]
        if self.range_input:
            if range_m is None:
                raise ValueError("this restorer takes each pixel's range (metres): give range_m")
            maps.append(range_m.to(image))
        if self.water is not None and water is None:
            raise ValueError("this restorer starts from a water's inverse: give its fields (water_fields)")
        if self.colour_net.skip:
            return self.colour_net(torch.cat(maps, dim=1), None, altitude_m, water), depth
        # without skip layers the full-resolution input is only pooled: pool its parts (the position maps once)
        f = self.factor
        parts = [area_pool(image, f), area_pool(depth, f), area_pool(position, f).expand(image.shape[0], -1, -1, -1)]
        small = torch.cat(parts + [area_pool(m, f) for m in maps[3:]], dim=1)
        return self.colour_net.coarse(small, image, None, altitude_m, water, linear), depth


def area_pool(t: torch.Tensor, factor: int) -> torch.Tensor:
    """``F.avg_pool2d(t, factor)`` of (B,C,H,W) with sides divisible by ``factor``; on a CPU, in float32, without
    gradients, for channels-last or single-channel maps, OpenCV's area resize of each image instead: the same means to
    float rounding, two to five times faster (torch pools the channels-last frames that NumPy hands over slowly)."""
    b, c, h, w = t.shape
    if t.device.type != "cpu" or t.dtype != torch.float32 or (torch.is_grad_enabled() and t.requires_grad) \
            or h % factor or w % factor or c > 4 or (c > 1 and t.is_contiguous()):  # torch's own layout: its pooling
        return F.avg_pool2d(t, factor)
    import cv2

    size = (w // factor, h // factor)
    pooled = [cv2.resize(np.ascontiguousarray(x), size, interpolation=cv2.INTER_AREA).reshape(size[1], size[0], c)
              for x in t.detach().permute(0, 2, 3, 1).numpy()]
    return torch.from_numpy(np.stack(pooled)).permute(0, 3, 1, 2)


def restore(model: Restorer, image: torch.Tensor, altitude_m: torch.Tensor | None = None,
            range_m: torch.Tensor | None = None, intrinsics: tuple[float, float, float, float] | None = None,
            water: torch.Tensor | None = None, linear: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Correct (B,3,H,W) images of any size (``altitude_m`` (B,) metres when the model takes it; ``range_m``
    (B,1,H,W) metres without holes in RGB-D mode; for a model that starts from a water, its fields ``water``
    (:func:`water_fields`), computed here from ``range_m`` and the images' ``intrinsics`` (fx, fy, cx, cy) when not
    given; ``linear``, optional: the images decoded to linear light, :meth:`Restorer.forward`): replicate-pad the
    bottom and right to multiples of ``model.multiple``, run the model, crop back; both outputs clamped to 0..1."""
    h, w = image.shape[-2:]
    m = model.multiple

    def pad(t: torch.Tensor) -> torch.Tensor:
        return F.pad(t, (0, -w % m, 0, -h % m), mode="replicate") if (h % m or w % m) else t

    position = pad(position_maps(h, w, image.device))  # of the image itself, padded like it
    if model.water is not None and water is None:
        if range_m is None:
            raise ValueError("this restorer takes each pixel's range (metres): give range_m")
        water = water_fields(model.water, range_m, intrinsics)
    rgb, depth = model(pad(image), position, altitude_m, pad(range_m) if range_m is not None else None,
                       pad(water) if water is not None else None, pad(linear) if linear is not None else None)
    return rgb[..., :h, :w].clamp(0.0, 1.0), depth[..., :h, :w].clamp(0.0, 1.0)
