"""Training: the WaterGAN (``train_gan``); the restorer's training goes beside it.

WaterGAN (Li et al. 2017) learns a site's water without labels: the generator G (a formation stack,
see :mod:`watergan.nets.generator`) turns in-air RGB-D into underwater images and the discriminator
D (DCGAN) tells them from the survey's real frames. Per iteration, with BCE on logits::

    L_D = BCE(D(b(a(x)) + n), real_label) + BCE(D(b(a(G(J, d, z))) + n'), 0)    one Adam step on D
    L_G = BCE(D(b(a(G(J, d, z))) + n'), 1) + w |m(G(J, d, z)) - m(x)|^2         ``gen_steps_per_disc_step`` steps on G

with random flips and shifts a (``disc_augment``), a Gaussian blur b (``disc_blur_px``), instance
noise n, n' ~ N(0, instance_noise_std^2), one-sided label smoothing (``real_label``) and the
per-channel mean and texture contrast m of a batch weighted by w (``moment_weight``). The generator
starts at the linear map from the in-air set's colour statistics to the survey's (``init_from_data``)
with one gain for all channels (``gain_channels``); after the last iteration ``settle_steps`` full-batch
steps of the statistics term alone settle the physical parameters (:func:`settle_statistics`).
Adam (lr 2e-4, beta1 0.5) for the nets; the generator's few physical parameters use ``physics_lr``,
the backscatter veil's level ``veil_lr`` and its spread ``veil_spread_lr`` (see :class:`GanConfig`).
The geometry of every RGB-D view (range, points, normals) is computed once before training (see
:func:`~watergan.nets.generator.select_state`).

With a site water (``site_water``: the water stage's ``water.json``, as ``watergan run`` gives it) the
generator's physical effects are the water stage's stack at its estimate, held (the default: the colour
statistics term and the settling are off, and the discriminator trains the learned scattering alone) or
trained under the prior of the estimate's intervals; nothing is started from the colour statistics
(:mod:`watergan.site_water`).

Files written to ``out_dir``: ``checkpoint.pt`` (states of both nets and optimisers, step, stack
configuration, RNG state, the generator before settling for a resume; atomic), ``stack.json`` (the
learned stack), ``train_log.jsonl`` (one line per iteration: losses and every learned physical
parameter), ``samples/step_NNNNNN.png`` (in-air, generated and real rows), ``training.png``
(parameters over training, colour histograms) and ``result.json``. A run resumed from its checkpoint
continues exactly as if uninterrupted. The colour-statistics term is :mod:`watergan.gan_statistics`'s, the
pictures :mod:`watergan.gan_figures`'s, the checkpoint, log and budget :mod:`watergan.training`'s.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F

from .data import TRAIN_HW, DataError, atomic_write_bytes, load_rgbd, load_underwater
from .device import Device, pick_device
from .errors import UserInputError
from .formation import FormationState
from .formation.effects.backscatter_conv import BackscatterConv
from .gan_figures import SAMPLES, plot_training, write_gan_samples
from .gan_statistics import (
    colour_moments,
    init_from_data,
    moment_loss,
    physical_parameters,
    render_eval,
    settle_statistics,
    settle_step_seconds,
)
from .imaging import augment, gaussian_blur
from .io import Encoding, to_jsonable
from .nets.discriminator import Discriminator
from .nets.generator import (
    DEFAULT_EFFECTS,
    INITIAL_BACKSCATTER_SPREAD,
    WaterGenerator,
    generator_stack_config,
    select_state,
)
from .progress import TrainingBar
from .site_water import SiteWater, SiteWaterStack, generator_config, hold_site_water, prior_loss, read_site_water
from .training import (
    CHECKPOINT,
    TRAIN_LOG,
    Clock,
    TrainingLog,
    TrainingResult,
    load_torch,
    read_resume_checkpoint,
    save_torch,
)

STACK_JSON = "stack.json"
PLOT = "training.png"
SETTLE_TIMING_STEP = 10
"""Iterations into a budgeted run at which the time of a settling step is measured."""


# ----------------------------------------------------------------------------------------------- GAN
@dataclass(frozen=True)
class GanConfig:
    """Options of ``train_gan`` (and of ``watergan train-gan``)."""

    rgbd_dir: Path
    """In-air RGB-D folder (rgb/ + depth/, the same names in each)."""
    underwater_dir: Path
    """Folder of the survey's underwater images (PNG, JPEG or TIFF)."""
    out_dir: Path
    """Model folder: checkpoint, stack.json, log, samples and plots go here."""
    effects: tuple[str, ...] = DEFAULT_EFFECTS
    """Registered effects in the generator's stack (placed by class rank)."""
    depth_scale_m: float | None = None
    """Range normaliser of backscatter_conv, metres (the survey's maximum altitude).
    None: the largest depth in the RGB-D data."""
    image_hw: tuple[int, int] = TRAIN_HW
    """Training image size (height, width), pixels; the discriminator is built for it."""
    batch_size: int = 64
    """Images per batch (drawn with replacement, so small datasets work)."""
    z_dim: int = 100
    """Length of the noise vector z, uniform in [-1, 1]."""
    lr: float = 2e-4
    """Adam learning rate of both nets."""
    beta1: float = 0.5
    """Adam beta1 of both nets."""
    physics_lr: float = 3e-3
    """Adam learning rate of every effect's bounded physical parameters (eta, vignetting, gain...).
    At 2e-4 these few parameters move too slowly for a minutes-long CPU run; at 1e-2 Adam's normalised steps turn
    any small persistent bias of the discriminator into a steady drift. The learned layers (backscatter_conv) keep
    the nets' learning rate, since a fast rate on them grows the z mask into texture. Set it to the nets' rate for
    the paper's single rate."""
    veil_lr: float | None = 2e-3
    """Adam learning rate of backscatter_conv's batch-norm shift (the veil's level per channel); none: the nets'
    learning rate, the paper's; at it the veil moves too little in the few hundred iterations a CPU allows in minutes
    (measurements: benchmarks/RESULTS/gan.md)."""
    veil_spread_lr: float | None = None
    """Adam learning rate of backscatter_conv's batch-norm scale (the veil's spread per channel); none: the nets'
    learning rate.
    Backscatter is smooth, and a fast-growing spread lets the z mask stand in for texture contrast, a random
    pattern the restorer cannot undo."""
    site_water: Path | None = None
    """The water stage's water.json, whose stack at its estimate is the generator's physical effects; the effects
    option adds what it lacks (backscatter_conv). None: the stack of the effects option, learned from the colour
    statistics and started from them (init-from-data)."""
    site_water_mode: SiteWater = SiteWater.held
    """How the site water enters the generator: "held", "prior" or "learned".
    With a site water: "held" (the estimate is fixed; the discriminator trains the learned scattering alone) or
    "prior" (the physical parameters train under the colour-statistics term and a Gaussian prior of the estimate's
    intervals). "learned" (no site water): the paper's way, the water learned from the colour statistics
    (watergan run then gives no site water)."""
    site_water_scattering: bool = False
    """With a site water: keep the learned G-II scattering (backscatter_conv) beside the analytic backscatter.
    Off by default: the discriminator grows its per-image veil (trained by it) into a spread larger than the
    backscatter itself, which the restorer cannot undo (measurements: benchmarks/RESULTS/gan.md)."""
    gain_channels: int = 1
    """Values of the generator's gain: 1 (one exposure factor, the paper's camera model) or 3 (a white balance).
    A per-channel gain and a per-channel attenuation explain a frame's colour cast equally well; only the weak
    change of colour with range tells them apart, so with 3 the learned eta is poorly determined."""
    init_from_data: bool = True
    """Start the water at the linear map from the in-air set's colour statistics to the frames' (else initial values).
    The attenuation's channel differences, the veil's level and the gain are set so that the in-air set's
    per-channel mean and fine-texture contrast map onto the real frames', so training
    starts near the site's brightness, contrast and cast."""
    moment_weight: float = 1000.0
    """Weight of a colour-statistics term added to the generator loss; 0: the paper's loss alone.
    The term: the squared differences of the per-channel mean and texture contrast (the spread of the fine
    detail) of a generated and a real batch (linear), a form of feature
    matching (Salimans et al. 2016) on the raw colours. Texture contrast, not the standard deviation: the
    transmission scales fine texture alone, while the spread of whole frames also holds how much the in-air scenes
    and the site vary from metre to metre, which no water changes."""
    adversarial_physics: bool = False
    """Let the discriminator's loss move the physical parameters (bounded values, veil level and spread), as the paper.
    False: they follow the colour-statistics term alone, which holds the data-driven start, while the
    discriminator trains the learned veil pattern (backscatter_conv's layers); the adversarial gradient pushed
    eta away from that start in every setting tried (measurements: benchmarks/RESULTS/gan.md)."""
    settle_steps: int = 100
    """Full-batch steps of the colour-statistics term alone after training (0: none).
    Every in-air view against every real frame at once: minibatch training leaves the generated means off the
    real ones by the noise of its batches, which the restorer would learn as water."""
    gen_steps_per_disc_step: int = 2
    """Generator updates per discriminator update (2 in the original code)."""
    instance_noise_std: float = 0.1
    """Standard deviation of Gaussian noise added to every discriminator input, linear units; 0: off.
    Real and generated alike. It hides fine texture that tells the in-air dataset from the survey apart, so the
    discriminator judges colour and brightness, which the physical stack can match."""
    disc_blur_px: float = 1.5
    """Standard deviation, pixels, of a Gaussian blur applied to every discriminator input; 0: off.
    Real and generated alike, before the instance noise: the discriminator then judges colour, brightness and
    coarse structure rather than the fine texture in which the in-air scenes and the site differ and which no
    physical stage can change."""
    disc_augment: bool = True
    """Randomly flip and shift every discriminator input, real and generated alike (differentiable augmentation).
    Flips left-right and up-down, shifts up to an eighth of the training image size with a reflected border (Zhao
    et al. 2020).
    A survey gives few frames; without it the discriminator memorises them and its gradients push the physical
    parameters off. The augmentations change neither colour nor the radial vignetting, so the generator is not
    taught to imitate them."""
    real_label: float = 0.9
    """Target of the discriminator on real images (one-sided label smoothing); 1.0: no smoothing.
    Generated images keep 0 and the generator's target stays 1. The in-air RGB-D scenes and the survey differ in
    content that no physical stage can change, so an unsmoothed discriminator soon becomes certain and its
    saturated gradients push the physical parameters far off; 0.9 keeps it from becoming overconfident."""
    disc_width: int = 16
    """Channels of the discriminator's first convolution (the paper: 64).
    The discriminator is most of an iteration's cost (batch 64, 4 passes per iteration): 16 both fits several
    times more iterations into the budget and keeps the discriminator from overpowering the few physical
    parameters (measurements: benchmarks/RESULTS/gan.md)."""
    iterations: int | None = None
    """Stop after this many iterations (one discriminator update each).
    Counted from the start of training, so a resumed run stops at the same place."""
    epochs: int | None = None
    """Stop after this many epochs of max(1, min(N_rgbd, N_underwater) // batch_size) iterations."""
    budget_min: float | None = 5.0
    """Stop after this many minutes of this run's wall-clock time (None: no time limit)."""
    seed: int = 0
    """Seed of initialisation, batch sampling and noise (same seed, same run on the same device)."""
    encoding: Encoding = Encoding.srgb
    """Encoding of the image files: "srgb" (decoded to linear) or "linear"."""
    skip_bad: bool = False
    """Skip (and report) unreadable or unpaired files instead of stopping with an error."""
    use_intrinsics: bool = True
    """Use camera.json beside the RGB-D data when present (range from the rays); else range = depth."""
    checkpoint_every: int = 100
    """Iterations between checkpoints (one is always written at the end)."""
    sample_every: int = 250
    """Iterations between sample grids (one is always written at the end)."""
    resume: bool = False
    """Continue from the model folder's checkpoint.pt when it exists."""
    device: Device = field(default=Device.auto, metadata={"hash": False})
    """"auto" (CUDA when available, else CPU), "cpu" or "cuda"."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Show a progress bar."""


@dataclass
class GanResult(TrainingResult):
    """What ``train_gan`` produced (paths are inside ``out_dir``)."""

    out_dir: Path
    steps: int
    """Iterations done in total (including those before a resume)."""
    seconds: float
    """Wall-clock time of this run, seconds."""
    iterations_per_s: float
    """Iterations per second of this run."""
    stopped_by: str
    """"iterations", "epochs", "budget" or "nothing to train" (a held site water and no learned effect)."""
    d_loss: float
    g_loss: float
    params: dict[str, list | float]
    """Learned physical parameters, ``{"effect.param": value}``."""
    colour_mean: dict[str, list[float]]
    """Per-channel mean of the generated ("generated") and real ("real") training images, linear."""
    colour_std: dict[str, list[float]]
    """Per-channel standard deviation of the same, linear."""
    skipped: list[str] = field(default_factory=list)
    """Files left out with ``skip_bad``."""
    settle_loss: float | None = None
    """The colour-statistics term after :func:`settle_statistics` (None: not run)."""
    site_water: dict | None = None
    """With a site water: its file, the mode ("held" or "prior") and the effects of its stack left out of the
    generator (per-frame); None: the water was learned from the colour statistics."""
    checkpoint: str = CHECKPOINT
    stack_json: str = STACK_JSON
    log: str = TRAIN_LOG
    plot: str = PLOT
    samples: str = SAMPLES


def _check_config(config: GanConfig) -> None:
    if config.iterations is None and config.epochs is None and config.budget_min is None:
        raise UserInputError("train_gan needs a limit: iterations, epochs or budget_min")
    if config.instance_noise_std < 0:
        raise UserInputError(f"GanConfig.instance_noise_std must be >= 0, got {config.instance_noise_std}")
    if not 0.5 < config.real_label <= 1.0:
        raise UserInputError(f"GanConfig.real_label must be in (0.5, 1], got {config.real_label}")
    for name in ("veil_lr", "veil_spread_lr"):
        if getattr(config, name) is not None and not getattr(config, name) > 0:
            raise UserInputError(f"GanConfig.{name} must be positive or None, got {getattr(config, name)}")
    if not (config.lr > 0 and config.physics_lr > 0):
        raise UserInputError(f"learning rates must be positive, got lr={config.lr}, physics_lr={config.physics_lr}")
    if config.gain_channels not in (1, 3):
        raise UserInputError(f"GanConfig.gain_channels must be 1 or 3, got {config.gain_channels}")
    if config.disc_blur_px < 0:
        raise UserInputError(f"GanConfig.disc_blur_px must be >= 0, got {config.disc_blur_px}")
    if config.moment_weight < 0:
        raise UserInputError(f"GanConfig.moment_weight must be >= 0, got {config.moment_weight}")
    if config.site_water is not None and config.site_water_mode == SiteWater.learned:
        raise UserInputError("GanConfig: site_water_mode 'learned' learns the water from the statistics and would "
                             "ignore site_water; give 'held' or 'prior', or no site_water")
    if config.moment_weight == 0 and not config.adversarial_physics and not _held(config):
        raise UserInputError("with moment_weight 0 and adversarial_physics off nothing moves the physical "
                             "parameters: set moment_weight > 0 or adversarial_physics")
    for name in ("iterations", "epochs", "batch_size", "gen_steps_per_disc_step", "disc_width", "z_dim",
                 "checkpoint_every", "sample_every"):
        value = getattr(config, name)
        if value is not None and value < 1:
            raise UserInputError(f"GanConfig.{name} must be at least 1, got {value}")
    if config.budget_min is not None and not config.budget_min > 0:
        raise UserInputError(f"GanConfig.budget_min must be positive, got {config.budget_min}")
    if config.depth_scale_m is not None and not config.depth_scale_m > 0:
        raise UserInputError(f"GanConfig.depth_scale_m must be positive, got {config.depth_scale_m}")


def _held(config: GanConfig) -> bool:
    """Whether the generator holds the site water fixed (:class:`SiteWater` ``held``)."""
    return config.site_water is not None and config.site_water_mode == SiteWater.held


def _moment_weight(config: GanConfig) -> float:
    """The colour-statistics term's weight: ``moment_weight``, or 0 when the site water is held (nothing
    physical trains, and the term would teach the learned scattering the in-air set's content)."""
    return 0.0 if _held(config) else config.moment_weight


def generator_param_groups(generator: WaterGenerator, lr: float, physics_lr: float,
                           veil_lr: float | None = None, veil_spread_lr: float | None = None) -> list[dict]:
    """Optimiser groups: each effect's bounded physical (``raw``) parameters at ``physics_lr``, the
    learned layers at ``lr``; with ``veil_lr`` the batch-norm shift of ``backscatter_conv`` (the
    veil's level) and with ``veil_spread_lr`` its scale (the veil's spread) in groups of their own at
    those rates. Fixed settings (``learnable=False``) are left out."""
    special = {id(p): physics_lr for effect in generator.stack.effects for p in effect.raw.parameters()}
    if BackscatterConv.name in generator.stack.names:
        norm = generator.stack[BackscatterConv.name].norm
        for param, rate in ((norm.bias, veil_lr), (norm.weight, veil_spread_lr)):
            if rate is not None:
                special[id(param)] = rate
    trainable = [p for p in generator.parameters() if p.requires_grad]
    groups = [{"params": [p for p in trainable if id(p) not in special], "lr": lr}]
    for rate in dict.fromkeys(special.values()):
        groups.append({"params": [p for p in trainable if special.get(id(p)) == rate], "lr": rate})
    return [g for g in groups if g["params"]]


def _json_ready(values: dict[str, torch.Tensor]) -> dict[str, list | float]:
    return {k: (v.item() if v.ndim == 0 else v.tolist()) for k, v in values.items()}


def _config_json(config: GanConfig) -> dict:
    """The configuration as plain JSON values (paths and choices as strings: a checkpoint loads with
    ``weights_only``)."""
    return to_jsonable(config)


def _save_checkpoint(run: GanRun, step: int, trained_generator: dict | None = None) -> None:
    """Checkpoint: ``out/checkpoint.pt`` (atomic) with the states of both nets, their optimisers and the
    batch generator at ``step``, the stack configuration and the run's configuration.
    ``trained_generator``: the generator's state before :func:`settle_statistics`, which a resumed run
    trains on from (``generator`` is then the settled one, which ``generate`` uses); without it a resume
    trains on from ``generator``."""
    save_torch(run.out / CHECKPOINT, {
        "step": step,
        "generator": run.generator.state_dict(),
        **({"generator_trained": trained_generator} if trained_generator is not None else {}),
        "discriminator": run.discriminator.state_dict(),
        "opt_g": run.opt_g.state_dict() if run.opt_g is not None else {},
        "opt_d": run.opt_d.state_dict(),
        "stack": run.generator.to_config(),
        "rng": run.rng.get_state(),
        "depth_scale_m": run.depth_scale_m,
        "config": _config_json(run.config),
    })


def load_checkpoint(path: str | Path) -> dict:
    """A checkpoint written by ``train_gan`` (tensors on the CPU)."""
    return load_torch(path, f"no checkpoint at {path}: train a WaterGAN first (watergan train-gan)")


def _resume(checkpoint: dict | None, generator: WaterGenerator, discriminator: Discriminator,
            opt_g: torch.optim.Optimizer | None, opt_d: torch.optim.Optimizer, rng: torch.Generator) -> int:
    """Checkpoint: restore both nets (the generator as it was before settling when the checkpoint holds
    that), both optimisers and the batch generator; returns the iteration to go on from (0 without one)."""
    if checkpoint is None:
        return 0
    generator.load_state_dict(checkpoint.get("generator_trained", checkpoint["generator"]))
    discriminator.load_state_dict(checkpoint["discriminator"])
    if opt_g is not None:
        opt_g.load_state_dict(checkpoint["opt_g"])
    opt_d.load_state_dict(checkpoint["opt_d"])
    rng.set_state(checkpoint["rng"])
    return int(checkpoint["step"])


def train_gan(config: GanConfig) -> GanResult:
    """Train a WaterGAN on in-air RGB-D and underwater images (see the module docstring): build the run,
    iterate :func:`gan_step` up to a limit (checkpoints and samples on the way), settle the physical
    parameters, write the last checkpoint and the result files."""
    _check_config(config)
    run = build_gan(config)
    log = TrainingLog.start(run.out, ("step",), (run.start,) if run.resumed else None)
    clock = Clock.minutes(config.budget_min)
    if run.opt_g is None:  # a held site water and no learned effect: the generator is the site water
        step, d_loss, g_loss, stopped_by = run.start, float("nan"), float("nan"), "nothing to train"
    else:
        with log:
            step, d_loss, g_loss, stopped_by = _train_iterations(run, log, clock)
    trained, settle_loss = _settle(run)
    seconds = clock.elapsed()
    _save_checkpoint(run, step, trained)
    return write_gan_result(run, step=step, seconds=seconds, stopped_by=stopped_by, d_loss=d_loss, g_loss=g_loss,
                            settle_loss=settle_loss)


@dataclass
class GanRun:
    """What a ``train_gan`` run trains with (made by :func:`build_gan`)."""

    config: GanConfig
    out: Path
    device: torch.device
    generator: WaterGenerator
    discriminator: Discriminator
    opt_g: torch.optim.Optimizer | None
    """None when nothing of the generator trains (a held site water and no learned effect)."""
    opt_d: torch.optim.Optimizer
    physics: list[torch.nn.Parameter]
    """The generator's physical parameters (:func:`physical_parameters`)."""
    rng: torch.Generator
    """Draws batches, noise vectors, instance noise and augmentations; checkpointed, so a resume goes on
    with the same draws."""
    air: torch.Tensor
    """(N,3,H,W) in-air views, linear, on the device."""
    depth: torch.Tensor
    """(N,1,H,W) their depth, metres."""
    real: torch.Tensor
    """(M,3,H,W) the survey's frames, linear."""
    air_state: FormationState
    """The geometry of every in-air view, computed once (see :func:`~watergan.nets.generator.select_state`)."""
    intrinsics: tuple[float, float, float, float] | None
    depth_scale_m: float
    start: int
    """Iterations done before this run: 0, or the checkpoint's on a resume."""
    resumed: bool
    """The nets and optimisers came from the checkpoint."""
    skipped: list[str]
    """Files left out with ``skip_bad``."""
    site: SiteWaterStack | None = None
    """The site water the generator holds or trains under a prior (None: learned from the statistics)."""


# ---------------------------------------------------------------------------------------------- build
def build_gan(config: GanConfig) -> GanRun:
    """Build a run: the output folders, the device and the data (:func:`_load_gan_data`); under
    ``torch.manual_seed(config.seed)`` the generator (:func:`_build_generator`) and the discriminator;
    their Adam optimisers (:func:`generator_param_groups`) and the batch generator seeded by ``config.seed``;
    on a resume the states of all of these from the checkpoint (:func:`_resume`)."""
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / SAMPLES).mkdir(exist_ok=True)
    device = pick_device(config.device)
    rgbd, water, skipped, intrinsics = _load_gan_data(config)

    checkpoint = read_resume_checkpoint(out, config.resume, "train-gan", "starting from iteration 0")
    torch.manual_seed(config.seed)
    site = read_site_water(config.site_water) if config.site_water is not None else None
    generator, depth_scale_m = _build_generator(config, checkpoint, rgbd, water, intrinsics, out / CHECKPOINT, site)
    discriminator = Discriminator(config.disc_width, config.image_hw)
    generator.to(device).train()
    discriminator.to(device).train()
    betas = (config.beta1, 0.999)
    groups = generator_param_groups(generator, config.lr, config.physics_lr, config.veil_lr, config.veil_spread_lr)
    physics = [] if _held(config) else physical_parameters(generator)  # held: what trains is the scattering
    opt_g = torch.optim.Adam(groups, config.lr, betas) if groups else None
    opt_d = torch.optim.Adam(discriminator.parameters(), config.lr, betas)
    rng = torch.Generator().manual_seed(config.seed)
    start = _resume(checkpoint, generator, discriminator, opt_g, opt_d, rng)

    air, depth, real = rgbd.rgb.to(device), rgbd.depth_m.to(device), water.images.to(device)
    with torch.no_grad():  # the geometry of every RGB-D view, once (see select_state)
        air_state = generator.state(air, depth, None, intrinsics)
    return GanRun(config=config, out=out, device=device, generator=generator, discriminator=discriminator,
                  opt_g=opt_g, opt_d=opt_d, physics=physics, rng=rng, air=air, depth=depth, real=real,
                  air_state=air_state, intrinsics=intrinsics, depth_scale_m=depth_scale_m, start=start,
                  resumed=checkpoint is not None, skipped=skipped, site=site)


def _load_gan_data(config: GanConfig):
    """Build: the in-air RGB-D set and the survey's frames at ``image_hw`` (bad files skipped and reported
    with ``skip_bad``), the skipped files and the RGB-D camera intrinsics (None: range = depth)."""
    rgbd = load_rgbd(config.rgbd_dir, config.image_hw, config.encoding, config.skip_bad)
    water = load_underwater(config.underwater_dir, config.image_hw, config.encoding, config.skip_bad)
    skipped = rgbd.skipped + water.skipped
    if skipped:
        print(f"train-gan: skipped {len(skipped)} bad file(s):\n  " + "\n  ".join(skipped), file=sys.stderr)
    intrinsics = rgbd.intrinsics.as_tuple() if (config.use_intrinsics and rgbd.intrinsics) else None
    return rgbd, water, skipped, intrinsics


def _build_generator(config: GanConfig, checkpoint: dict | None, rgbd, water, intrinsics, ckpt_path: Path,
                     site: SiteWaterStack | None) -> tuple[WaterGenerator, float]:
    """Build: the generator and its range normaliser, metres. On a resume the checkpoint's stack (which
    must hold the same effects); else a new stack: with a site water, its stack at its estimate and the
    effects of ``config.effects`` it lacks (:func:`watergan.site_water.generator_config`), the learned
    scattering starting as a faint zero-mean pattern; without, ``config.effects`` started from the data
    (:func:`init_from_data`) when ``init_from_data``. What the site water's mode holds is frozen
    (:func:`watergan.site_water.hold_site_water`)."""
    depth_scale_m = (float(checkpoint["depth_scale_m"]) if checkpoint is not None
                     else config.depth_scale_m or float(rgbd.depth_m.max()))
    if not depth_scale_m > 0:
        raise DataError(f"every depth in {config.rgbd_dir} is 0: no depth to learn the water from")
    fresh = generator_stack_config(config.effects, depth_scale_m, config.z_dim, config.image_hw,
                                   config.gain_channels)
    if site is not None:
        keep = [c for c in fresh if c["name"] != BackscatterConv.name or config.site_water_scattering]
        fresh = generator_config(site, keep)
    if checkpoint is not None:
        generator = WaterGenerator.from_config(checkpoint["stack"])
        if generator.stack.names != [c["name"] for c in fresh]:
            raise UserInputError(f"checkpoint {ckpt_path} holds effects {generator.stack.names}, not "
                                 f"{[c['name'] for c in fresh]}: resume with the same effects and site water or use "
                                 f"a new --out-dir")
    elif site is not None:
        generator = WaterGenerator.from_config(fresh)
        if BackscatterConv.name in generator.stack.names:
            with torch.no_grad():
                generator.stack[BackscatterConv.name].norm.weight.fill_(INITIAL_BACKSCATTER_SPREAD)
    else:
        generator = WaterGenerator.build(config.effects, depth_scale_m, config.z_dim, config.image_hw,
                                         config.gain_channels)
        if config.init_from_data:
            init_from_data(generator, rgbd.rgb, rgbd.depth_m, water.images, intrinsics)
    if site is not None:
        hold_site_water(generator.stack, site, config.site_water_mode)
    return generator, depth_scale_m


# ----------------------------------------------------------------------------------------------- step
def gan_step(run: GanRun) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """One training iteration (see the module docstring): a batch (:func:`_draw_batch`), one step on D
    (:func:`_discriminator_step`), ``gen_steps_per_disc_step`` steps on G (:func:`_generator_steps`).
    Returns D's loss, G's last loss and D's logits on the real and the generated batch."""
    state_b, real_b, noise_real, noise_fake = _draw_batch(run)
    loss_d, d_real, d_fake = _discriminator_step(run, state_b, real_b, noise_real, noise_fake)
    loss_g = _generator_steps(run, state_b, real_b, noise_fake)
    return loss_d, loss_g, d_real, d_fake


def _draw_batch(run: GanRun) -> tuple[FormationState, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Step: from ``run.rng``, in this order, ``batch_size`` in-air views and real frames (with replacement),
    noise vectors z uniform in [-1, 1] and the instance noise of the real and the generated batch."""
    config, rng, device, batch = run.config, run.rng, run.device, run.config.batch_size
    i_air = torch.randint(run.air.shape[0], (batch,), generator=rng).to(device)
    i_water = torch.randint(run.real.shape[0], (batch,), generator=rng).to(device)
    z = (torch.rand(batch, run.generator.z_dim, generator=rng) * 2 - 1).to(device)
    state_b, real_b = select_state(run.air_state, i_air, z=z), run.real[i_water]
    noise_real, noise_fake = (config.instance_noise_std * torch.randn(2, *real_b.shape, generator=rng)).to(device)
    return state_b, real_b, noise_real, noise_fake


def _disc_input(run: GanRun, images: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """Step: what the discriminator sees: augmented (``disc_augment``, drawn from ``run.rng``), blurred, with
    instance noise."""
    images = augment(images, run.rng) if run.config.disc_augment else images
    return gaussian_blur(images, run.config.disc_blur_px) + noise


def _discriminator_step(run: GanRun, state_b: FormationState, real_b: torch.Tensor, noise_real: torch.Tensor,
                        noise_fake: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Step: one Adam step on D, BCE of its logits against ``real_label`` on real and 0 on generated
    images. Returns the loss and the logits on both."""
    batch, device = run.config.batch_size, run.device
    fake = run.generator.render(state_b)
    d_real = run.discriminator(_disc_input(run, real_b, noise_real))
    d_fake = run.discriminator(_disc_input(run, fake.detach(), noise_fake))
    real_target = torch.full((batch,), run.config.real_label, device=device)
    loss_d = (F.binary_cross_entropy_with_logits(d_real, real_target)
              + F.binary_cross_entropy_with_logits(d_fake, torch.zeros(batch, device=device)))
    run.opt_d.zero_grad(set_to_none=True)
    loss_d.backward()
    run.opt_d.step()
    return loss_d, d_real, d_fake


def _generator_steps(run: GanRun, state_b: FormationState, real_b: torch.Tensor,
                     noise_fake: torch.Tensor) -> torch.Tensor:
    """Step: ``gen_steps_per_disc_step`` Adam steps on G (D frozen): BCE against 1 plus the colour-statistics
    term (:func:`moment_loss`, with ``moment_weight`` > 0); without ``adversarial_physics`` the physical
    parameters get the statistics term's gradient alone. Returns the last loss."""
    config = run.config
    ones = torch.ones(config.batch_size, device=run.device)
    run.discriminator.requires_grad_(False)
    weight = _moment_weight(config)
    real_moments = colour_moments(real_b) if weight > 0 else None
    for _ in range(config.gen_steps_per_disc_step):
        fake = run.generator.render(state_b)
        loss_g = F.binary_cross_entropy_with_logits(run.discriminator(_disc_input(run, fake, noise_fake)), ones)
        run.opt_g.zero_grad(set_to_none=True)
        loss_g.backward(retain_graph=real_moments is not None)
        if not config.adversarial_physics:  # the physical parameters follow the statistics alone
            for param in run.physics:
                param.grad = None
        if real_moments is not None:
            loss_moments = moment_loss(fake, real_moments, weight)
            loss_moments.backward()
            loss_g = loss_g + loss_moments
        if run.site is not None and config.site_water_mode == SiteWater.prior:
            loss_prior = prior_loss(run.generator.stack, run.site.prior)
            loss_prior.backward()
            loss_g = loss_g + loss_prior.to(loss_g)
        run.opt_g.step()
    run.discriminator.requires_grad_(True)
    return loss_g


def _stop_plan(config: GanConfig, n_air: int, n_water: int) -> tuple[int | None, str]:
    """Step: the iteration to stop at (the lower of ``iterations`` and ``epochs`` of
    max(1, min(N_rgbd, N_underwater) // batch_size) iterations; None: the budget alone) and its name."""
    iters_per_epoch = max(1, min(n_air, n_water) // config.batch_size)
    limits = {"iterations": config.iterations,
              "epochs": None if config.epochs is None else config.epochs * iters_per_epoch}
    target = min((v for v in limits.values() if v is not None), default=None)
    stopped_by = min((k for k, v in limits.items() if v is not None), key=lambda k: limits[k], default="budget")
    return target, stopped_by


def _will_settle(config: GanConfig) -> bool:
    """Whether :func:`settle_statistics` runs after training."""
    return _moment_weight(config) > 0 and config.settle_steps > 0


def _train_iterations(run: GanRun, log: TrainingLog, clock: Clock) -> tuple[int, float, float, str]:
    """Iterate :func:`gan_step` from ``run.start`` up to the iteration or epoch limit or the time budget
    (less the time :func:`settle_statistics` will take, measured ``SETTLE_TIMING_STEP`` iterations in);
    a log line every iteration, a checkpoint every ``checkpoint_every``, samples every ``sample_every``.
    Returns the iteration reached, the last D and G losses and what stopped it."""
    config = run.config
    target, stopped_by = _stop_plan(config, run.air.shape[0], run.real.shape[0])
    settle_reserve_s = 0.0  # time kept for settle_statistics inside the budget, measured once warm
    step, d_loss, g_loss = run.start, float("nan"), float("nan")
    bar = TrainingBar("train-gan", target, run.start, clock.budget_s, config.progress)
    while target is None or step < target:
        if clock.reached(clock.budget_s, settle_reserve_s):
            stopped_by = "budget"
            break
        loss_d, loss_g, d_real, d_fake = gan_step(run)
        step += 1
        if _will_settle(config) and clock.budget_s is not None and step == run.start + SETTLE_TIMING_STEP:
            settle_reserve_s = config.settle_steps * settle_step_seconds(run.generator, run.air_state, run.real)
        d_loss, g_loss = loss_d.item(), loss_g.item()
        log.write({"step": step, "d_loss": d_loss, "g_loss": g_loss,
                   "d_real": torch.sigmoid(d_real).mean().item(), "d_fake": torch.sigmoid(d_fake).mean().item(),
                   "seconds": clock.stamp(), "params": _json_ready(run.generator.physical_values())})
        bar.update(step, clock.elapsed(), d=f"{d_loss:.3f}", g=f"{g_loss:.3f}")
        if step % config.checkpoint_every == 0:
            log.flush()
            _save_checkpoint(run, step)
        if step % config.sample_every == 0:
            write_gan_samples(run, step)
    bar.close()
    return step, d_loss, g_loss, stopped_by


def _settle(run: GanRun) -> tuple[dict | None, float | None]:
    """Step: :func:`settle_statistics` when it runs (:func:`_will_settle`), noise from ``seed + 3``. Returns
    the generator's state before it (for the checkpoint) and the final statistics term; else (None, None)."""
    config = run.config
    if not _will_settle(config):
        return None, None
    trained = {name: value.clone() for name, value in run.generator.state_dict().items()}
    return trained, settle_statistics(run.generator, run.air_state, run.real, config.settle_steps,
                                      config.moment_weight, config.seed + 3, run.site)


# ---------------------------------------------------------------------------------------------- write
def write_gan_result(run: GanRun, *, step: int, seconds: float, stopped_by: str, d_loss: float, g_loss: float,
                     settle_loss: float | None) -> GanResult:
    """Write the result files: ``stack.json``, the last samples, ``training.png`` (with histograms of the
    generator's output for every in-air view, noise from ``seed + 2``) and ``result.json``; returns the result."""
    out, generator, real = run.out, run.generator, run.real
    atomic_write_bytes(out / STACK_JSON, (generator.stack.to_json() + "\n").encode())
    write_gan_samples(run, step)
    stats_z = torch.rand(run.air.shape[0], generator.z_dim,
                         generator=torch.Generator().manual_seed(run.config.seed + 2))
    generated = render_eval(generator, run.air, run.depth, stats_z.mul(2).sub(1).to(run.device), run.intrinsics)
    plot_training(out / TRAIN_LOG, generated, real, out / PLOT)
    result = GanResult(
        out_dir=out, steps=step, seconds=seconds, iterations_per_s=(step - run.start) / max(seconds, 1e-9),
        stopped_by=stopped_by, d_loss=d_loss, g_loss=g_loss, params=_json_ready(generator.physical_values()),
        colour_mean={
            "generated": generated.mean(dim=(0, 2, 3)).tolist(),
            "real": real.mean(dim=(0, 2, 3)).tolist()},
        colour_std={
            "generated": generated.std(dim=(0, 2, 3)).tolist(),
            "real": real.std(dim=(0, 2, 3)).tolist()},
        skipped=run.skipped, settle_loss=settle_loss,
        site_water=None if run.site is None else {"water_json": str(run.config.site_water),
                                                  "mode": str(run.config.site_water_mode),
                                                  "left_out": run.site.left_out},
    )
    result.write(out)
    return result
