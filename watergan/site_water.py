"""The site water in WaterGAN's generator: the water stage's estimate, held or under a prior.

The water stage (:mod:`eval.water`, ``watergan water``) estimates the survey's formation stack from its
own geometry and writes ``water.json``: the stack at its estimate and, per fitted parameter, a 95 %
interval. WaterGAN then does not learn the water from colour statistics (which do not pin it, and which
follow the in-air set's content as much as the site's water): its generator's physical effects are that
stack, at that estimate, in one of two modes (:class:`SiteWater`; ``learned`` is the paper's way, for
comparison):

- ``held``: every parameter the water stage gives is fixed. The discriminator trains only what the stack
  lacks, the learned G-II scattering of ``backscatter_conv``, whose veil level (its batch-norm shift) is
  held at 0 (the analytic ``backscatter`` holds the level), so its zero-mean pattern adds structure, not
  light; the colour-statistics term is off (with an in-air set unlike the site it moves the water to
  match the content).
- ``prior``: the parameters train as without a site water (the colour-statistics term) plus the
  Gaussian prior of the estimate::

      L_prior = 1/2 sum_i ((theta_i - theta_hat_i) / s_i)^2,   s_i = (high_i - low_i) / (2 x 1.96)

  with [low, high] the parameter's 95 % interval; a parameter without an interval (held by the water
  stage, e.g. the gain without a board) stays held.

Effects with per-frame parameters (an auto-exposure) describe the survey's frames, not the in-air views
the generator renders: they are left out of the generator (said in :attr:`SiteWaterStack.left_out`); the
physics correction undoes them per frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import torch

from .errors import UserInputError
from .formation import Stack, get
from .formation.effects.backscatter_conv import BackscatterConv
from .water_record import read_water

#: Standard deviations per half-width of a 95 % interval.
Z95 = 1.96


class SiteWater(StrEnum):
    """How WaterGAN's generator uses the water stage's estimate (see the module docstring)."""

    held = "held"
    prior = "prior"
    learned = "learned"
    """No site water: the generator learns the water from the colour statistics, as the paper."""


@dataclass(frozen=True)
class PriorTerm:
    """One parameter of the prior: its estimate and standard deviation (physical units, per component)."""

    effect: str
    param: str
    value: torch.Tensor
    sd: torch.Tensor


@dataclass
class SiteWaterStack:
    """What the generator takes from ``water.json``."""

    config: list[dict]
    """The water stage's stack entries ({name, params}) that the generator holds."""
    prior: list[PriorTerm] = field(default_factory=list)
    """Per fitted parameter with an interval, its estimate and standard deviation."""
    left_out: list[str] = field(default_factory=list)
    """Effects of the water's stack left out of the generator (per-frame parameters)."""


def read_site_water(water_json: str | Path) -> SiteWaterStack:
    """The stack of a water stage's ``water.json`` and the prior of its intervals; a missing or malformed file
    is an error naming it."""
    path = Path(water_json)
    if not path.is_file():
        raise UserInputError(f"site water {path} does not exist: run the water stage (`watergan water --workspace "
                             f"WS`) or leave site_water unset")
    record = read_water(path)
    config, left_out = [], []
    for entry in record.stack:
        if get(entry["name"]).varies_by_frame():
            left_out.append(entry["name"])
        else:
            config.append(entry)
    kept = {entry["name"] for entry in config}
    prior = []
    for key, info in record.params.items():
        name, _, param = key.partition(".")
        if name not in kept or not info.fitted or info.low is None or info.high is None:
            continue
        value = torch.as_tensor(info.value, dtype=torch.float64)
        sd = (torch.as_tensor(info.high, dtype=torch.float64) - torch.as_tensor(info.low, dtype=torch.float64))
        prior.append(PriorTerm(name, param, value, (sd / (2 * Z95)).clamp_min(1e-9)))
    return SiteWaterStack(config, prior, left_out)


def generator_config(site: SiteWaterStack, extra: list[dict]) -> list[dict]:
    """The generator's stack: the site water's entries and the ``extra`` entries of effects it lacks (e.g.
    ``backscatter_conv``), in scene-to-sensor order."""
    names = {entry["name"] for entry in site.config}
    return Stack.rank_order([*site.config, *(e for e in extra if e["name"] not in names)])


def hold_site_water(stack: Stack, site: SiteWaterStack, mode: SiteWater) -> None:
    """Freeze what the mode holds (see the module docstring): every parameter of the site water's effects
    (``held``) or those without a prior term (``prior``); ``backscatter_conv``'s veil level at 0."""
    trained = {(t.effect, t.param) for t in site.prior} if mode == SiteWater.prior else set()
    for entry in site.config:
        effect = stack[entry["name"]]
        for name, raw in effect.raw.items():
            if (entry["name"], name) not in trained:
                raw.requires_grad_(False)
    if BackscatterConv.name in stack.names:
        bias = stack[BackscatterConv.name].norm.bias
        with torch.no_grad():
            bias.zero_()
        bias.requires_grad_(False)


def prior_loss(stack: Stack, prior: list[PriorTerm]) -> torch.Tensor:
    """L_prior = 1/2 sum ((theta - theta_hat) / s)^2 over the prior's terms (see the module docstring)."""
    total = torch.zeros((), dtype=torch.float64)
    for term in prior:
        value = stack[term.effect].param(term.param).double()
        total = total + 0.5 * ((value - term.value.to(value.device)) / term.sd.to(value.device)).square().sum()
    return total
