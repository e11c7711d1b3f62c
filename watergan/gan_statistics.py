"""The WaterGAN's colour-statistics term and what is built on it (see :mod:`watergan.train`).

With m(x) the per-channel mean and texture contrast of a batch (:func:`colour_moments`), the term
w |m(G(J, d, z)) - m(x)|^2 (:func:`moment_loss`) pulls the generator's physical parameters
(:func:`physical_parameters`) towards the survey's colours during training, starts them at the linear
map between the two sets' statistics (:func:`init_from_data`) and settles them after training on
every view at once (:func:`settle_statistics`).
"""

from __future__ import annotations

import math
import time

import torch

from .formation import FormationState
from .formation.effects.backscatter_conv import BackscatterConv
from .imaging import gaussian_blur
from .nets.generator import WaterGenerator
from .site_water import SiteWaterStack, prior_loss


def physical_parameters(generator: WaterGenerator) -> list[torch.nn.Parameter]:
    """The generator's physical parameters that train: every effect's bounded (``raw``) values and the
    batch-norm scale and shift of ``backscatter_conv`` (the veil's spread and level), those held left out."""
    params = [p for effect in generator.stack.effects for p in effect.raw.parameters() if p.requires_grad]
    if BackscatterConv.name in generator.stack.names:
        params += [p for p in generator.stack[BackscatterConv.name].norm.parameters() if p.requires_grad]
    return params


SETTLE_LR = 2e-3
"""Starting Adam learning rate of :func:`settle_statistics` (cosine-decayed to 0)."""


def settle_statistics(generator: WaterGenerator, air_state: FormationState, real: torch.Tensor, steps: int,
                      weight: float, seed: int, site: SiteWaterStack | None = None) -> float:
    """Full-batch steps on the generator's physical parameters (:func:`physical_parameters`) of

        L = weight |m(G(J, d, z)) - m(x)|^2 [+ L_prior]

    (L_prior: the site water's prior, :func:`watergan.site_water.prior_loss`, when ``site`` is given)
    with every in-air view (one fixed noise vector z each) against every real frame x, m the
    per-channel mean and texture contrast (:func:`colour_moments`), batch norm on its running
    statistics as at generation, Adam at SETTLE_LR decayed to 0 (cosine); z is drawn from ``seed``.
    The generator's mode and which parameters train are restored. Returns the final L."""
    physics = physical_parameters(generator)
    was_training = generator.training
    trainable = {name: p.requires_grad for name, p in generator.named_parameters()}
    generator.eval()
    generator.requires_grad_(False)
    for param in physics:
        param.requires_grad_(True)
    z = torch.rand(air_state.direct.shape[0], generator.z_dim, generator=torch.Generator().manual_seed(seed))
    state = air_state.replace(z=z.mul(2).sub(1).to(air_state.direct.device))
    target = colour_moments(real)
    opt = torch.optim.Adam(physics, SETTLE_LR)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(steps, 1))

    def objective() -> torch.Tensor:
        loss = moment_loss(generator.render(state), target, weight)
        return loss + prior_loss(generator.stack, site.prior).to(loss) if site is not None else loss

    loss = objective()
    for _ in range(steps):
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        schedule.step()
        loss = objective()
    for name, param in generator.named_parameters():
        param.requires_grad_(trainable[name])
    generator.train(was_training)
    return loss.item()


def settle_step_seconds(generator: WaterGenerator, air_state: FormationState, real: torch.Tensor) -> float:
    """Seconds of one full-batch render, statistics and backward pass (a step of settle_statistics), the
    faster of two; ``train_gan`` measures it a few iterations in, once start-up costs are paid (before
    the first iteration they inflate it)."""
    z = torch.zeros(air_state.direct.shape[0], generator.z_dim, device=air_state.direct.device)
    was_training = generator.training
    generator.eval()  # batch norm's running statistics stay as they are
    seconds = math.inf
    for _ in range(2):
        began = time.perf_counter()
        loss = moment_loss(generator.render(air_state.replace(z=z)), colour_moments(real))
        loss.backward()
        seconds = min(seconds, time.perf_counter() - began)
    generator.zero_grad(set_to_none=True)
    generator.train(was_training)
    return seconds


def colour_moments(images: torch.Tensor) -> torch.Tensor:
    """(2,3): the per-channel mean and texture contrast (:func:`texture_contrast`) of a (B,3,H,W) batch."""
    return torch.stack([images.mean(dim=(0, 2, 3)), texture_contrast(images)])


def moment_loss(images: torch.Tensor, target: torch.Tensor, weight: float = 1.0) -> torch.Tensor:
    """The colour-statistics term w |m(images) - target|^2, m = :func:`colour_moments`, target (2,3)."""
    return weight * (colour_moments(images) - target).square().sum()



def texture_contrast(images: torch.Tensor, sigma_px: float = 2.0) -> torch.Tensor:
    """(3,) per-channel standard deviation of the high-pass images x - blur(x) (Gaussian, ``sigma_px``):
    the contrast of fine texture, which a smooth veil does not change and a transmission T scales by T."""
    return (images - gaussian_blur(images, sigma_px)).std(dim=(0, 2, 3))


def init_from_data(generator: WaterGenerator, air: torch.Tensor, depth_m: torch.Tensor, real: torch.Tensor,
                   intrinsics: tuple[float, float, float, float] | None, count: int = 256) -> dict[str, list[float]]:
    """Start the attenuation, the veil and the gain at the per-channel linear map that carries the in-air
    set's colour statistics onto the survey's (see ``GanConfig.init_from_data``).

    With D the generated image without water (eta 0, no veil, gain 1; vignetting kept), mu0_c its
    per-channel mean and s0_c its texture contrast (:func:`texture_contrast`), mu_c, s_c the real
    frames' and r the mean range of the RGB-D views: the transmission T_c = s_c / s0_c and the veil
    V_c = mu_c - T_c mu0_c (so T D + V has the real mean and texture contrast). T_c = k exp(-eta_c r)
    fixes how eta_c differ between channels, d_c = -ln(T_c) / r; their common level cannot be told
    from frames at one range (a common shift is undone by k), so it stays at the stack's initial mean
    eta: eta_c = mean(eta_init) + d_c - mean(d). Then k = exp(mean_c(ln T_c + eta_c r)) (per channel
    with three gains) and the veil's batch-norm shift V_c / k (the backscatter sits before the gain).
    Returns the values set."""
    stack = generator.stack
    n = min(count, air.shape[0])
    r_mean, r_contrast = real.mean(dim=(0, 2, 3)).double(), texture_contrast(real.double())
    norm = stack[BackscatterConv.name].norm if BackscatterConv.name in stack.names else None
    saved = {}
    if norm is not None:
        saved["veil"] = norm.weight.detach().clone()
        with torch.no_grad():
            norm.weight.zero_()
            norm.bias.zero_()
    if "attenuation" in stack.names:
        saved["eta"] = stack["attenuation"].param("eta_per_m").detach().clone()
        stack["attenuation"].set_values(eta_per_m=[0.0, 0.0, 0.0])
    if "gain" in stack.names:
        stack["gain"].set_values(k=[1.0] * stack["gain"].param("k").numel())
    z = torch.zeros(n, generator.z_dim)
    plain = render_eval(generator, air[:n], depth_m[:n], z, intrinsics).double()
    d_mean, d_contrast = plain.mean(dim=(0, 2, 3)), texture_contrast(plain)
    state = generator.state(air[:n], depth_m[:n], z, intrinsics)
    range_m = float(state.range_m[state.valid].double().mean())  # WaterGenerator.state always sets valid
    transmission = (r_contrast / d_contrast.clamp_min(1e-4)).clamp(1e-3, 50.0)
    veil = (r_mean - transmission * d_mean).clamp_min(0.0)
    values: dict[str, list[float]] = {}
    log_t = transmission.log()
    if "attenuation" in stack.names:
        d = -log_t / max(range_m, 1e-3)
        eta = (saved["eta"].double().mean() + d - d.mean()).clamp(0.0, 5.0)
        stack["attenuation"].set_values(eta_per_m=eta.tolist())
        values["attenuation.eta_per_m"] = eta.tolist()
    else:
        eta = torch.zeros(3, dtype=torch.float64)
    k = torch.ones(1, dtype=torch.float64)
    if "gain" in stack.names:
        log_k = log_t + eta * range_m
        k = (log_k.mean().reshape(1) if stack["gain"].param("k").numel() == 1 else log_k).exp().clamp(0.05, 50.0)
        stack["gain"].set_values(k=k.tolist())
        values["gain.k"] = k.tolist()
    if norm is not None:
        level = (veil / k).float()
        with torch.no_grad():
            norm.weight.copy_(saved["veil"])
            norm.bias.copy_(level)
        values["veil_level"] = level.tolist()
    return values



def render_eval(generator: WaterGenerator, rgb, depth, z, intrinsics) -> torch.Tensor:
    """Generator output in inference mode (batch norm from running statistics), state untouched."""
    was_training = generator.training
    generator.eval()
    with torch.no_grad():
        out = generator(rgb, depth, z, intrinsics)
    generator.train(was_training)
    return out


