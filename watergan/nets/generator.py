"""The WaterGAN generator: a formation stack driven by in-air RGB-D and noise.

    G(J, d, z) = clamp(S(state(J, d, z)).image, 0, 1)

where S is a :class:`~watergan.formation.Stack` of effects (by default ``attenuation`` (paper
G-I), ``backscatter_conv`` (G-II), ``vignetting`` (G-III) and ``gain``). Every stage changes colour
and intensity only: the structure of the in-air image J passes through untouched. Any registered
effect (built-in, entry point or ``--plugin`` file) can be added by name; effects are placed in
scene-to-sensor order by their class ``rank`` and their bounded parameters are learned with the rest.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import nn

from ..formation import FormationState, Stack, pixel_grid, state_from_rgbd
from ..formation.effects.backscatter_conv import BackscatterConv

DEFAULT_EFFECTS = ("attenuation", "backscatter_conv", "vignetting", "gain")
#: Initial veil of the learned backscatter: BN scale and shift of the mask (linear radiance), so
#: the first generated images are faintly veiled rather than drowned in unit-variance noise.
INITIAL_BACKSCATTER_SPREAD = 0.02
INITIAL_BACKSCATTER_LEVEL = 0.05


def generator_stack_config(effects: tuple[str, ...] | list[str] = DEFAULT_EFFECTS, depth_scale_m: float = 10.0,
                           z_dim: int = 100, mask_hw: tuple[int, int] = (48, 64),
                           gain_channels: int = 1) -> list[dict]:
    """The stack configuration of a fresh generator: the named effects at their initial values,
    sorted by class ``rank`` (stable, so effects of equal rank keep the given order), with
    ``backscatter_conv``'s fixed settings (noise length, mask size, depth normaliser) filled in and
    ``gain`` with ``gain_channels`` values (1: one exposure factor, as the paper; 3: per channel)."""
    if gain_channels not in (1, 3):
        raise ValueError(f"gain_channels must be 1 or 3, got {gain_channels}")
    names = Stack.rank_order(list(dict.fromkeys(effects)))
    config = []
    for name in names:
        params: dict[str, float] = {}
        if name == BackscatterConv.name:
            params = {"z_dim": float(z_dim), "mask_height": float(mask_hw[0]), "mask_width": float(mask_hw[1]),
                      "depth_scale_m": float(depth_scale_m)}
        if name == "gain":
            params = {"k": [1.0] * gain_channels}
        config.append({"name": name, "params": params})
    return config


def select_state(state: FormationState, index: torch.Tensor, **changes) -> FormationState:
    """The state of the images ``index`` of a batched state (fields with batch size 1 are shared),
    with ``changes`` (e.g. ``z=...``) applied.

    The geometry of an RGB-D image (range, points, normals from the intrinsics) never changes during
    training, so ``train_gan`` builds the state of the whole dataset once and selects each batch from
    it instead of recomputing it three times per iteration."""
    values = {}
    for f in dataclasses.fields(state):
        value = getattr(state, f.name)
        if isinstance(value, torch.Tensor) and value.ndim >= 1 and value.shape[0] == state.direct.shape[0]:
            value = value[index]
        values[f.name] = value
    values.update(changes)
    return FormationState(**values)


class WaterGenerator(nn.Module):
    """In-air RGB-D + noise -> underwater image, through a formation stack.

    forward(rgb, depth_m, z, intrinsics=None):
        rgb         (B,3,H,W) in-air linear radiance, 0..1
        depth_m     (B,1,H,W) z-depth, metres
        z           (B,Z) noise, uniform in [-1, 1]
        intrinsics  optional (fx, fy, cx, cy) in pixels of these images; with them range is the
                    Euclidean camera-to-point distance (and points, normals are available to
                    effects), without them range_m = depth_m.
    returns the (B,3,H,W) linear underwater image, clamped to 0..1.
    """

    def __init__(self, stack: Stack) -> None:
        super().__init__()
        self.stack = stack

    @classmethod
    def build(cls, effects: tuple[str, ...] | list[str] = DEFAULT_EFFECTS, depth_scale_m: float = 10.0,
              z_dim: int = 100, mask_hw: tuple[int, int] = (48, 64), gain_channels: int = 1) -> WaterGenerator:
        """A fresh generator (see :func:`generator_stack_config`); the learned backscatter starts as a
        faint veil (BN scale INITIAL_BACKSCATTER_SPREAD, shift INITIAL_BACKSCATTER_LEVEL)."""
        generator = cls(Stack.from_config(generator_stack_config(effects, depth_scale_m, z_dim, mask_hw,
                                                                 gain_channels)))
        if BackscatterConv.name in generator.stack.names:
            norm = generator.stack[BackscatterConv.name].norm
            with torch.no_grad():
                norm.weight.fill_(INITIAL_BACKSCATTER_SPREAD)
                norm.bias.fill_(INITIAL_BACKSCATTER_LEVEL)
        return generator

    @classmethod
    def from_config(cls, config: list[dict] | str) -> WaterGenerator:
        """A generator with the structure and physical values of a saved stack configuration (learned
        layers such as ``backscatter_conv``'s convolutions come from a checkpoint's state dict)."""
        return cls(Stack.from_config(config))

    @property
    def z_dim(self) -> int:
        """Length of the noise vector (that of ``backscatter_conv``; 100 when there is none)."""
        if BackscatterConv.name in self.stack.names:
            return int(round(self.stack[BackscatterConv.name].param("z_dim").item()))
        return 100

    def to_config(self) -> list[dict]:
        return self.stack.to_config()

    def state(self, rgb: torch.Tensor, depth_m: torch.Tensor, z: torch.Tensor,
              intrinsics: tuple[float, float, float, float] | None = None) -> FormationState:
        """The formation state of a batch (see the class docstring)."""
        if intrinsics is not None:
            fx, fy, cx, cy = intrinsics
            return state_from_rgbd(rgb, depth_m, fx, fy, cx, cy).replace(z=z)
        b, _, h, w = rgb.shape
        return FormationState(direct=rgb, range_m=depth_m, depth_m=depth_m, image_wh=(w, h), z=z, valid=depth_m > 0,
                              pixel_uv=pixel_grid(h, w, b, rgb.dtype, rgb.device))

    def forward(self, rgb: torch.Tensor, depth_m: torch.Tensor, z: torch.Tensor,
                intrinsics: tuple[float, float, float, float] | None = None) -> torch.Tensor:
        return self.render(self.state(rgb, depth_m, z, intrinsics))

    def render(self, state: FormationState) -> torch.Tensor:
        """The generated image of a ready state (from :meth:`state`, e.g. one built once for a whole
        dataset and cut into batches with :func:`select_state`), clamped to 0..1."""
        return self.stack.render(state).clamp(0.0, 1.0)

    def physical_values(self) -> dict[str, torch.Tensor]:
        """Every learnable bounded parameter as ``{"effect.param": physical value (float64)}``."""
        out = {}
        for effect in self.stack.effects:
            values = effect.values()
            for spec in effect.params:
                if spec.learnable:
                    out[f"{effect.name}.{spec.name}"] = values[spec.name]
        return out
