"""Training the restorer (:mod:`watergan.nets.restorer`) on WaterGAN's paired output.

Data: a ``watergan generate`` folder (``underwater/``, ``inair/`` 8-bit sRGB PNGs, ``depth/`` and, for the
RGB-D mode (``range_input``), ``range/`` 16-bit millimetre PNGs, paired by stem; with ``water``, the stack and
each frame's intrinsics from ``manifest.json``). Pixels are the stored sRGB values scaled to 0..1 (the restorer
corrects stored images, as the paper's 8-bit ones); depth targets are relative, d_rel = d / max(d) per image,
with 0 (no value) left out of the depth loss. A frame's altitude (``altitude=True``) is the median of its valid
depth, what an altimeter reads over the scene of a downward-looking camera. The frames are split 80/20 into
training and validation by a seeded permutation.

Loss (Euclidean, per iteration on a batch drawn with replacement)::

    L = mean_valid (D(u) - d_rel)^2 + mean (C(u, up(D(u))) - a)^2

with u the underwater image, a the in-air one, D the depth net (at 56x56) and C the colour net; the
estimated depth is detached where it enters C. The paper's two-level schedule: stage 1 trains C's
core alone at ``core_hw`` (128x128: images area-averaged), stage 2 trains the whole colour net on
full-resolution random crops of ``crop_px`` (each with the context, altitude and its part of the position
maps of its whole image, see :mod:`watergan.nets.restorer`) with the core initialised from stage 1 (the depth net
trains in both). Adam, one optimiser per stage.

Files in ``out_dir``: ``checkpoint.pt`` (stage, step, model and optimiser states, RNG, split;
atomic; ``resume`` continues from it), ``train_log.jsonl`` (one line per iteration), ``restorer.pt``
(the final model, read by :func:`load_restorer`), ``validation.json`` and ``validation.md``
(per-channel colour RMSE and depth RMSE on the held-out split, paper Table III form) and
``result.json``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .data import DataError, atomic_write_bytes, depth_or_zero, read_depth, read_image
from .device import Device, pick_device
from .errors import UserInputError
from .io import quantise
from .nets.restorer import (
    HEADS,
    WIDTH_PRESETS,
    Head,
    Restorer,
    WidthPreset,
    fill_range_holes,
    image_context,
    invertible_water,
    position_maps,
    restore,
    water_fields,
)
from .progress import TrainingBar
from .training import (
    CHECKPOINT,
    TRAIN_LOG,
    Clock,
    TrainingLog,
    TrainingResult,
    read_resume_checkpoint,
    save_torch,
)

MODEL = "restorer.pt"
VALIDATION_JSON = "validation.json"
VALIDATION_MD = "validation.md"


@dataclass(frozen=True)
class RestorerConfig:
    """Options of ``train_restorer`` (and of ``watergan train-restorer``)."""

    data_dir: Path
    """A watergan generate output folder (underwater/, inair/, depth/)."""
    out_dir: Path
    """Model folder: checkpoint, log, restorer.pt and validation tables go here."""
    widths: WidthPreset = WidthPreset.cpu
    """Width preset of the nets: "cpu" (small, fast) or "paper" (SegNet-sized)."""
    skip: bool = False
    """Full-resolution skip layers in the colour net (the paper's form of the colour net; off by default: without
    them the nets cost a third as much per frame and the corrections were as good on the surveys measured)."""
    head: Head = Head.affine
    """What the colour core outputs: "affine" (gain and offset fields applied to the image) or "direct" (colours).
    "affine": per-channel gain and offset at each pixel; "direct": as the paper."""
    altitude: bool = True
    """The colour net takes each image's altitude in metres; False: the image alone, as the paper.
    Here the median of its depth map; when correcting, the navigation's altitude (nav_altitude_m)."""
    range_input: bool = False
    """RGB-D mode: the colour net takes each pixel's range in metres; False: the monocular restorer.
    Here the paired set's range/; when correcting, the range stage's maps (from the dense stage and the
    fused mesh). The monocular restorer takes the image, and the altitude with the altitude option."""
    water: bool = True
    """RGB-D mode: the colour net starts from the exact inverse of the water the pairs were rendered with.
    That water is the stack in the paired set's manifest.json, at each pixel's range; the net learns what it does
    not hold. False: it learns the whole inverse
    (ignored in monocular mode)."""
    factor: int = 4
    """Average-pool factor from full resolution to the colour core (even)."""
    depth_hw: tuple[int, int] = (56, 56)
    """Depth net input and output size (height, width), pixels; multiples of 8."""
    core_hw: tuple[int, int] = (128, 128)
    """Stage-1 training size of the colour core (height, width), pixels; multiples of 8."""
    crop_px: int = 256
    """Side of the stage-2 full-resolution training crops, pixels.
    A multiple of factor * 8; reduced to fit the smallest image."""
    batch_size: int = 8
    """Images per batch."""
    lr: float = 1e-3
    """Adam learning rate."""
    lr_decay: bool = True
    """Cosine decay of the learning rate over each stage, to 0 at its end; False: a constant rate after the warm-up.
    The end: its iterations, or its share of the budget when that ends it first."""
    warmup_iterations: int = 20
    """Iterations at the start of each stage over which the learning rate rises linearly to its value (0: none).
    Each stage starts a fresh Adam, whose first steps move every weight by about the rate whatever its gradient:
    without the warm-up the colour loss that stage 1 reached jumps at the start of stage 2 and takes many
    iterations to come back."""
    stage1_iterations: int = 2000
    """Iterations of stage 1 (colour core at core_hw)."""
    stage2_iterations: int = 1000
    """Iterations of stage 2 (full-resolution crops)."""
    budget_min: float | None = None
    """Wall-clock budget of this run, minutes (None: none); stage 1 may use its share of it (stage1-budget-share)."""
    stage1_min_iterations: int = 0
    """Iterations stage 1 runs at least, past its share of the budget if need be (a machine busy with other work
    must not cut a budgeted training to a handful of steps); its learning rate's decay then follows them."""
    stage2_min_iterations: int = 0
    """The same for stage 2."""
    stage1_budget_share: float = 0.5
    """Fraction of the budget for stage 1 (stage 2 gets the rest)."""
    val_fraction: float = 0.2
    """Fraction of frames held out for validation (at least one frame each side)."""
    seed: int = 0
    """Seed of the split, initialisation and batch sampling."""
    checkpoint_every: int = 100
    """Iterations between checkpoints (one is always written at the end of each stage)."""
    resume: bool = False
    """Continue from the model folder's checkpoint.pt when it exists."""
    device: Device = field(default=Device.auto, metadata={"hash": False})
    """"auto" (CUDA when available, else CPU), "cpu" or "cuda"."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Show progress bars."""


@dataclass
class RestorerResult(TrainingResult):
    """What ``train_restorer`` produced (file names inside ``out_dir``)."""

    out_dir: Path
    steps: tuple[int, int]
    """Iterations done in stage 1 and stage 2 (including those before a resume)."""
    seconds: float
    """Wall-clock time of this run, seconds."""
    loss: float
    """Last training loss."""
    validation: dict
    """Held-out RMSE (stored 0..1 units): {"raw": {...}, "restorer": {...}} with keys R, G, B, depth."""
    train_count: int
    val_count: int
    model: str = MODEL
    checkpoint: str = CHECKPOINT
    log: str = TRAIN_LOG
    validation_json: str = VALIDATION_JSON
    validation_md: str = VALIDATION_MD
    skipped: list[str] = field(default_factory=list)


@dataclass
class PairedSet:
    """Paired frames in memory: full-resolution uint8 (3,H,W) underwater and in-air images (stored
    sRGB values), relative depth at ``depth_hw``, the altitude and the depth file of each frame."""

    stems: list[str]
    underwater: list[torch.Tensor]
    inair: list[torch.Tensor]
    depth_small: torch.Tensor
    altitude_m: torch.Tensor
    """(N,) median of each frame's valid depth, metres."""
    depth_files: list[Path]
    range_m: list[torch.Tensor] | None = None
    """Per frame (1,H,W) float32 range in metres, holes filled (:func:`fill_range_holes`); None: not loaded."""
    water: list[dict] | None = None
    """The stack the pairs were rendered with, its effects that act pixel by pixel (``manifest.json``;
    :func:`watergan.nets.restorer.invertible_water`); None: not loaded."""
    water_fields: list[torch.Tensor] | None = None
    """Per frame (6,H,W) float32 fields of that water's inverse at the frame's range (:func:`water_fields`)."""


def _check_config(c: RestorerConfig) -> None:
    if c.widths not in WIDTH_PRESETS:
        raise UserInputError(f"widths must be one of {sorted(WIDTH_PRESETS)}, got {c.widths!r}")
    if c.head not in HEADS:
        raise UserInputError(f"head must be one of {HEADS}, got {c.head!r}")
    if c.range_input and c.water and c.head != Head.affine:
        raise UserInputError("the pairs' water (--water) is added to the affine head's fields: use --head affine, or "
                             "--no-water")
    if c.warmup_iterations < 0:
        raise UserInputError(f"RestorerConfig.warmup_iterations must be >= 0, got {c.warmup_iterations}")
    for name in ("batch_size", "checkpoint_every"):
        if getattr(c, name) < 1:
            raise UserInputError(f"RestorerConfig.{name} must be at least 1, got {getattr(c, name)}")
    if min(c.stage1_iterations, c.stage2_iterations, c.stage1_min_iterations, c.stage2_min_iterations) < 0:
        raise UserInputError("stage iterations must be >= 0")
    if c.factor < 2 or c.factor % 2:
        raise UserInputError(f"RestorerConfig.factor must be even and >= 2, got {c.factor}")
    if any(v % 8 for v in (*c.core_hw, *c.depth_hw)):
        raise UserInputError(f"core_hw {c.core_hw} and depth_hw {c.depth_hw} must be multiples of 8")
    if c.crop_px < c.factor * 8 or c.crop_px % (c.factor * 8):
        raise UserInputError(f"crop_px must be a positive multiple of {c.factor * 8}, got {c.crop_px}")
    if not 0 < c.val_fraction < 1 or not 0 <= c.stage1_budget_share <= 1:
        raise UserInputError("val_fraction must be in (0, 1) and stage1_budget_share in [0, 1]")
    if c.budget_min is not None and not c.budget_min > 0:
        raise UserInputError(f"budget_min must be positive, got {c.budget_min}")
    if not c.lr > 0:
        raise UserInputError(f"lr must be positive, got {c.lr}")


def _stored(path: Path) -> torch.Tensor:
    """An image file as (3,H,W) uint8 stored values (16-bit files are rounded to 8 bits)."""
    return torch.from_numpy(quantise(read_image(path, "linear"), 8).transpose(2, 0, 1).copy())


def relative_depth(depth_m: np.ndarray) -> np.ndarray:
    """d_rel = d / max(d) (0 stays 0: no value); all zeros stays zeros."""
    top = depth_m.max(initial=0.0)
    return depth_m / top if top > 0 else depth_m


def load_paired(data_dir: str | Path, depth_hw: tuple[int, int] = (56, 56), with_range: bool = False,
                with_water: bool = False) -> PairedSet:
    """Every frame of a ``generate`` folder, paired by stem (a missing partner is an error naming it); with
    ``with_range`` also its ``range/`` maps, and with ``with_water`` (and range) the stack of its ``manifest.json``
    and each frame's fields of that stack's inverse (:func:`water_fields`, with the intrinsics the manifest gives
    each frame)."""
    data_dir = Path(data_dir)
    names = ("underwater", "inair", "depth", "range") if with_range else ("underwater", "inair", "depth")
    folders = {name: data_dir / name for name in names}
    missing = [str(p) for p in folders.values() if not p.is_dir()]
    if missing:
        raise DataError(f"{data_dir} is not a `watergan generate` folder: missing {', '.join(missing)}")
    stems = sorted(p.stem for p in folders["underwater"].glob("*.png"))
    if len(stems) < 2:
        raise DataError(f"{folders['underwater']} holds {len(stems)} PNG images; training needs at least 2")
    under, air, small, altitude, depth_files, ranges = [], [], [], [], [], []
    for stem in stems:
        paths = {k: v / f"{stem}.png" for k, v in folders.items()}
        for p in paths.values():
            if not p.is_file():
                raise DataError(f"{p} is missing: every underwater image needs its {', '.join(names[1:])} files")
        u, a = _stored(paths["underwater"]), _stored(paths["inair"])
        d = depth_or_zero(read_depth(paths["depth"]))
        if u.shape != a.shape or u.shape[1:] != d.shape:
            raise DataError(f"frame {stem}: underwater {tuple(u.shape[1:])}, inair {tuple(a.shape[1:])} and depth "
                            f"{d.shape} sizes differ")
        if not (d > 0).any():
            raise DataError(f"depth {paths['depth']} holds no value (all 0)")
        altitude.append(float(np.median(d[d > 0])))
        d_t = torch.from_numpy(relative_depth(d)).float()[None, None]
        valid = (d_t > 0).float()
        total, weight = F.adaptive_avg_pool2d(d_t, depth_hw), F.adaptive_avg_pool2d(valid, depth_hw)
        small.append(torch.where(weight > 1e-6, total / weight.clamp_min(1e-6), torch.zeros_like(total))[0])
        under.append(u)
        air.append(a)
        depth_files.append(paths["depth"])
        if with_range:
            r = torch.from_numpy(depth_or_zero(read_depth(paths["range"]))).float()[None, None]
            if r.shape[-2:] != d.shape:
                raise DataError(f"frame {stem}: range {tuple(r.shape[-2:])} and depth {d.shape} sizes differ")
            try:
                ranges.append(fill_range_holes(r)[0][0])
            except ValueError:
                raise DataError(f"range {paths['range']} holds no value (all 0)") from None
    data = PairedSet(stems, under, air, torch.stack(small), torch.tensor(altitude), depth_files,
                     ranges if with_range else None)
    if with_range and with_water:
        data.water, intrinsics = _manifest_water(data_dir)
        data.water_fields = [water_fields(data.water, r[None], intrinsics.get(stem), exact=True)[0]
                             for stem, r in zip(stems, ranges, strict=True)]
    return data


def _manifest_water(data_dir: Path) -> tuple[list[dict], dict[str, tuple]]:
    """(the pixel-by-pixel effects of the stack a ``generate`` folder was rendered with, {stem: (fx, fy, cx, cy)}
    for the frames it gives intrinsics for)."""
    path = data_dir / "manifest.json"
    try:
        manifest = json.loads(path.read_text())
        stack = manifest["stack"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DataError(f"{path} cannot give the water the pairs were rendered with ({type(exc).__name__}: {exc}): "
                        f"run `watergan generate` again, or train without it (--no-water; in `watergan run`: "
                        f"--no-restorer-water)") from None
    intrinsics = {item["stem"]: tuple(item["intrinsics"]) for item in manifest.get("items", [])
                  if item.get("intrinsics")}
    return invertible_water(stack), intrinsics


def split_indices(count: int, val_fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """A seeded permutation split into (train, validation); each side gets at least one frame."""
    order = torch.randperm(count, generator=torch.Generator().manual_seed(seed)).tolist()
    n_val = min(count - 1, max(1, round(val_fraction * count)))
    return sorted(order[n_val:]), sorted(order[:n_val])


def _float(images: list[torch.Tensor], idx: list[int], device: torch.device) -> torch.Tensor:
    return torch.stack([images[i] for i in idx]).to(device).float().div_(255.0)


def masked_mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """mean over target > 0 of (pred - target)^2 (0 = no depth value)."""
    valid = (target > 0).float()
    return ((pred - target) ** 2 * valid).sum() / valid.sum().clamp_min(1.0)


def save_restorer(path: str | Path, model: Restorer, extra: dict | None = None) -> None:
    """The model's configuration and weights (CPU tensors), atomically (the folder is created)."""
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    save_torch(path, {"model_config": model.to_config(), "model": state, **(extra or {})})


def load_restorer(model_dir: str | Path) -> Restorer:
    """The trained restorer of a ``train_restorer`` folder (``restorer.pt``), in inference mode."""
    path = Path(model_dir) / MODEL
    if not path.is_file():
        raise UserInputError(f"no {MODEL} in {model_dir}: train one first (watergan train-restorer)")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
        model = Restorer.from_config(saved["model_config"])
        model.load_state_dict(saved["model"])
    except Exception as exc:  # a torn or foreign file, or one from before the nets changed: say which
        raise UserInputError(f"restorer {path} cannot be read ({type(exc).__name__}: {exc}); if an older "
                             f"watergan wrote it, train it again") from exc
    return model.eval()


def validate(model: Restorer, data: PairedSet, idx: list[int], device: torch.device) -> dict:
    """Root-mean-square errors over all held-out pixels at full resolution, stored 0..1 units:
    per channel RMSE_c = sqrt(mean (y_c - a_c)^2) for the raw underwater image and the restorer, and
    depth RMSE = sqrt(mean_valid (d - d_rel)^2) of the restorer."""
    model.eval()
    sums = {"raw": torch.zeros(3, dtype=torch.float64), "restorer": torch.zeros(3, dtype=torch.float64)}
    pixels, depth_sq, depth_n = 0, 0.0, 0
    with torch.no_grad():
        for i in idx:
            u, a = _float(data.underwater, [i], device), _float(data.inair, [i], device)
            range_m = data.range_m[i][None].to(device) if data.range_m is not None else None
            water = data.water_fields[i][None].to(device) if data.water_fields is not None else None
            rgb, depth = restore(model, u, data.altitude_m[i:i + 1].to(device), range_m, water=water)
            sums["raw"] += ((u - a) ** 2).sum(dim=(0, 2, 3)).double().cpu()
            sums["restorer"] += ((rgb - a) ** 2).sum(dim=(0, 2, 3)).double().cpu()
            pixels += u.shape[-1] * u.shape[-2]
            truth = torch.from_numpy(relative_depth(depth_or_zero(read_depth(data.depth_files[i])))).to(device)
            valid = truth > 0
            depth_sq += float(((depth[0, 0].double() - truth) ** 2)[valid].sum())
            depth_n += int(valid.sum())
    out = {name: {c: float(torch.sqrt(s[k] / pixels)) for k, c in enumerate("RGB")} for name, s in sums.items()}
    out["raw"]["depth"] = None
    out["restorer"]["depth"] = (depth_sq / depth_n) ** 0.5 if depth_n else None
    return out


def validation_markdown(table: dict, val_count: int, skip: bool) -> str:
    """The held-out RMSE as a Markdown table (paper Table III form: a row per method, a column per channel)."""
    name = "restorer" + (" (skip layers)" if skip else "")
    lines = [f"RMSE on the held-out synthetic split ({val_count} frames; stored sRGB values 0..1, relative depth 0..1)",
             "", "| Method | R | G | B | Depth |", "|---|---|---|---|---|"]
    for key, label in (("raw", "raw (uncorrected)"), ("restorer", name)):
        row = table[key]
        depth = "-" if row["depth"] is None else f"{row['depth']:.4f}"
        lines.append(f"| {label} | {row['R']:.4f} | {row['G']:.4f} | {row['B']:.4f} | {depth} |")
    return "\n".join(lines) + "\n"


def train_restorer(config: RestorerConfig) -> RestorerResult:
    """Train the depth and colour nets on a ``generate`` folder (see the module docstring): build the run,
    train stage 1 then stage 2 (:func:`train_stage`, checkpoints on the way), write the model, the
    validation tables and the result."""
    _check_config(config)
    run = build_restorer(config)
    log = TrainingLog.start(run.out, ("stage", "step"), (run.stage, run.start) if run.resumed else None)
    clock = Clock.minutes(config.budget_min)
    steps, loss_value = [run.stage1_steps, 0], float("nan")
    with log:
        for current, target in ((1, config.stage1_iterations), (2, config.stage2_iterations)):
            if current < run.stage:
                continue
            steps[current - 1], last_loss = train_stage(run, current, target, log, clock, steps[0])
            loss_value = loss_value if last_loss is None else last_loss
    seconds = clock.elapsed()
    return write_restorer_result(run, steps, seconds, loss_value)


@dataclass
class TrainingViews:
    """The training frames at the sizes the two stages use, on the device (made by :func:`_training_views`)."""

    small_u: torch.Tensor
    """(N,3,h,w) underwater images area-averaged to ``core_hw``, 0..1."""
    small_a: torch.Tensor
    """(N,3,h,w) in-air images at ``core_hw``."""
    depth_u: torch.Tensor
    """(N,3,h,w) underwater images at ``depth_hw`` (the depth net's input)."""
    depth_t: torch.Tensor
    """(N,1,h,w) relative depth targets at ``depth_hw``."""
    altitudes: torch.Tensor
    """(N,) each frame's altitude, metres."""
    small_pos: torch.Tensor
    """Position maps at ``core_hw``."""
    full_pos: dict[tuple[int, int], torch.Tensor]
    """Position maps at each full image size."""
    contexts: torch.Tensor
    """Context of each whole image (as at correction time)."""
    small_range: torch.Tensor | None = None
    """(N,1,h,w) range at ``core_hw``, metres (RGB-D mode; None: monocular)."""
    small_water: torch.Tensor | None = None
    """(N,6,h,w) the water's inverse fields area-averaged to ``core_hw`` (None: the net starts from no water)."""


@dataclass
class RestorerRun:
    """What a ``train_restorer`` run trains with (made by :func:`build_restorer`)."""

    config: RestorerConfig
    out: Path
    device: torch.device
    data: PairedSet
    train_idx: list[int]
    val_idx: list[int]
    crop: int
    """Side of the stage-2 crops, pixels."""
    model: Restorer
    rng: torch.Generator
    """Draws batches and crops; checkpointed, so a resume goes on with the same draws."""
    views: TrainingViews
    stage: int
    """The stage to start in: 1, or the checkpoint's on a resume."""
    start: int
    """Iterations of that stage done before this run."""
    stage1_steps: int
    """Stage-1 iterations done before this run."""
    resume_opt: dict | None
    """The optimiser state to go on with in stage ``stage`` (None: a fresh optimiser)."""
    resumed: bool
    """The model came from the checkpoint."""


# ---------------------------------------------------------------------------------------------- build
def build_restorer(config: RestorerConfig) -> RestorerRun:
    """Build a run: the output folder, the device, the paired data and its seeded train/validation split,
    the stage-2 crop side (:func:`_crop_side`), the model under ``torch.manual_seed(config.seed)``, the
    batch generator seeded by ``config.seed``, both restored on a resume (:func:`_resume`), and the
    training views (:func:`_training_views`)."""
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    device = pick_device(config.device)
    data = load_paired(config.data_dir, config.depth_hw, config.range_input, config.water)
    train_idx, val_idx = split_indices(len(data.stems), config.val_fraction, config.seed)
    crop = _crop_side(config, data)

    checkpoint = read_resume_checkpoint(out, config.resume, "train-restorer", "starting from the beginning")
    torch.manual_seed(config.seed)
    model = Restorer(WIDTH_PRESETS[config.widths], config.factor, config.skip, config.depth_hw, config.head,
                     config.altitude, config.range_input, data.water).to(device)
    rng = torch.Generator().manual_seed(config.seed)
    stage, start, stage1_steps, resume_opt = _resume(checkpoint, model, rng, val_idx, out / CHECKPOINT)
    return RestorerRun(config=config, out=out, device=device, data=data, train_idx=train_idx, val_idx=val_idx,
                       crop=crop, model=model, rng=rng, views=_training_views(config, data, device), stage=stage,
                       start=start, stage1_steps=stage1_steps, resume_opt=resume_opt,
                       resumed=checkpoint is not None)


def _crop_side(config: RestorerConfig, data: PairedSet) -> int:
    """Build: the stage-2 crop side, ``crop_px`` reduced to a multiple of factor * 8 that fits the smallest
    image (an error when none does)."""
    min_side = min(min(u.shape[1:]) for u in data.underwater)
    mult = config.factor * 8
    crop = min(config.crop_px, min_side // mult * mult)
    if crop < mult:
        raise DataError(f"the smallest image of {config.data_dir} is {min_side} px; training needs >= {mult} px")
    return crop


def _training_views(config: RestorerConfig, data: PairedSet, device: torch.device) -> TrainingViews:
    """Build: every frame at the sizes the stages train at, with its depth target, altitude, position maps
    and whole-image context, on the device."""
    small_u = torch.stack([F.adaptive_avg_pool2d(u.float()[None], config.core_hw)[0] for u in data.underwater]) / 255
    small_a = torch.stack([F.adaptive_avg_pool2d(a.float()[None], config.core_hw)[0] for a in data.inair]) / 255
    depth_u = torch.stack([F.adaptive_avg_pool2d(u.float()[None], config.depth_hw)[0] for u in data.underwater]) / 255
    small_u, small_a, depth_u = small_u.to(device), small_a.to(device), depth_u.to(device)
    depth_t, altitudes = data.depth_small.to(device), data.altitude_m.to(device)
    small_pos = position_maps(*config.core_hw, device)
    full_pos = {hw: position_maps(*hw, device)[0] for hw in {tuple(u.shape[1:]) for u in data.underwater}}
    contexts = torch.stack([image_context(F.avg_pool2d(u.float()[None] / 255, config.factor))[0]
                            for u in data.underwater]).to(device)  # of whole images, as at correction time
    small_range = None
    if data.range_m is not None:
        small_range = torch.stack([F.adaptive_avg_pool2d(r[None], config.core_hw)[0] for r in data.range_m]).to(device)
    small_water = None
    if data.water_fields is not None:
        small_water = torch.stack([F.adaptive_avg_pool2d(f[None], config.core_hw)[0]
                                   for f in data.water_fields]).to(device)
    return TrainingViews(small_u=small_u, small_a=small_a, depth_u=depth_u, depth_t=depth_t, altitudes=altitudes,
                         small_pos=small_pos, full_pos=full_pos, contexts=contexts, small_range=small_range,
                         small_water=small_water)


# ----------------------------------------------------------------------------------------------- step
def train_stage(run: RestorerRun, current: int, target: int, log: TrainingLog, clock: Clock,
                stage1_steps: int) -> tuple[int, float | None]:
    """Train stage ``current`` (1 or 2) with its own Adam (:func:`_stage_optimiser`) up to ``target``
    iterations or the stage's end in the budget (stage 1: ``stage1_budget_share`` of it); a log line every
    iteration, a checkpoint every ``checkpoint_every`` and at the end (after stage 1: stage 2 at its step 0,
    so a resume goes on from there). Returns the iterations done and the last loss (None: none done)."""
    config = run.config
    opt = _stage_optimiser(run, current)
    step = run.start if current == run.stage else 0
    budget_s = clock.budget_s
    stage_end_s = None if budget_s is None else (budget_s * config.stage1_budget_share if current == 1 else budget_s)
    run.model.train()
    stage_start_s = clock.elapsed()
    bar = TrainingBar(f"restorer stage {current}", target, step, stage_end_s, config.progress, clock.elapsed())
    loss_value = None
    least = min(config.stage1_min_iterations if current == 1 else config.stage2_min_iterations, target)
    while step < target:
        if clock.reached(stage_end_s) and step >= least:
            break
        for group in opt.param_groups:  # from the step (and budget): a resume by iterations keeps the rates
            group["lr"] = stage_lr(config, step, target, clock.elapsed() - stage_start_s,
                                   None if stage_end_s is None else stage_end_s - stage_start_s, least)
        loss, colour_loss, depth_loss = restorer_step(run, current, opt)
        step += 1
        loss_value = loss.item()
        log.write({"stage": current, "step": step, "loss": loss_value, "colour_loss": colour_loss.item(),
                   "depth_loss": depth_loss.item(), "seconds": clock.stamp()})
        bar.update(step, clock.elapsed(), loss=f"{loss_value:.4f}")
        if step % config.checkpoint_every == 0:
            log.flush()
            _save_checkpoint(run, current, step, opt.state_dict(), step if current == 1 else stage1_steps)
    bar.close()
    log.flush()
    if current == 1:  # a stage-2 checkpoint at its step 0 (fresh optimiser): a resume goes on from there
        _save_checkpoint(run, 2, 0, None, step)
    else:
        _save_checkpoint(run, 2, step, opt.state_dict(), stage1_steps)
    return step, loss_value


def stage_lr(config: RestorerConfig, step: int, target: int, elapsed_s: float, stage_s: float | None,
             least: int = 0) -> float:
    """The learning rate of a stage's iteration ``step`` (0-based): ``lr`` times a linear warm-up over
    ``warmup_iterations`` and, with ``lr_decay``, (1 + cos(pi f)) / 2 with f the stage's progress, the larger of
    step / target and elapsed_s / stage_s (its share of the budget), the latter no more than step / ``least`` (the
    iterations the stage runs at least: past its budget it decays over them)."""
    rate = config.lr * min(1.0, (step + 1) / max(config.warmup_iterations, 1))
    if config.lr_decay:
        budget = elapsed_s / stage_s if stage_s else 0.0
        progress = max(step / max(target, 1), min(budget, step / least) if least else budget)
        rate *= 0.5 * (1.0 + math.cos(math.pi * min(progress, 1.0)))
    return rate


def _stage_optimiser(run: RestorerRun, current: int) -> torch.optim.Adam:
    """Step: Adam at ``lr`` on the depth net and the colour core (stage 1) or the whole colour net (stage 2),
    restored from the checkpoint in the stage a resume starts in."""
    model = run.model
    params = (list(model.depth_net.parameters()) +
              list((model.colour_net.core if current == 1 else model.colour_net).parameters()))
    opt = torch.optim.Adam(params, run.config.lr)
    if current == run.stage and run.resume_opt is not None:
        opt.load_state_dict(run.resume_opt)
    return opt


def restorer_step(run: RestorerRun, current: int,
                  opt: torch.optim.Optimizer) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One training iteration of stage ``current``: a batch of training frames drawn with replacement from
    ``run.rng``, the stage's loss (:func:`_stage1_loss`, :func:`_stage2_loss`), one Adam step. Returns
    the loss and its colour and depth terms."""
    picks = torch.randint(len(run.train_idx), (run.config.batch_size,), generator=run.rng)
    idx = [run.train_idx[int(k)] for k in picks]
    colour_loss, depth_loss = (_stage1_loss if current == 1 else _stage2_loss)(run, idx)
    loss = colour_loss + depth_loss
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return loss, colour_loss, depth_loss


def _stage1_loss(run: RestorerRun, idx: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Step: the colour core's MSE at ``core_hw`` (fed the detached, upsampled depth estimate) and the depth
    net's masked MSE, of frames ``idx``."""
    views, model, core_hw = run.views, run.model, run.config.core_hw
    depth = model.depth_net.core(views.depth_u[idx])
    up = F.interpolate(depth.detach(), size=core_hw, mode="bilinear", align_corners=False)
    maps = [views.small_u[idx], up, views.small_pos.expand(len(idx), -1, -1, -1)]
    if views.small_range is not None:
        maps.append(views.small_range[idx])
    water = views.small_water[idx] if views.small_water is not None else None
    colour = model.colour_net.core_colours(torch.cat(maps, dim=1), views.altitudes[idx], water)
    return F.mse_loss(colour, views.small_a[idx]), masked_mse(depth, views.depth_t[idx])


def _stage2_loss(run: RestorerRun, idx: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Step: the whole colour net's MSE on a full-resolution random crop of each frame (offsets drawn from
    ``run.rng``, frame by frame) and the depth net's masked MSE, of frames ``idx``."""
    views, model, data, crop, device = run.views, run.model, run.data, run.crop, run.device
    depth = model.depth_net.core(views.depth_u[idx])
    inputs, targets, water = [], [], []
    for k, i in enumerate(idx):
        h, w = data.underwater[i].shape[1:]
        y0 = int(torch.randint(h - crop + 1, (1,), generator=run.rng))
        x0 = int(torch.randint(w - crop + 1, (1,), generator=run.rng))
        d = F.interpolate(depth[k:k + 1].detach(), size=(h, w), mode="bilinear", align_corners=False)
        u = data.underwater[i][:, y0:y0 + crop, x0:x0 + crop].to(device).float() / 255
        position = views.full_pos[(h, w)][:, y0:y0 + crop, x0:x0 + crop]
        maps = [u, d[0, :, y0:y0 + crop, x0:x0 + crop], position]
        if data.range_m is not None:
            maps.append(data.range_m[i][:, y0:y0 + crop, x0:x0 + crop].to(device))
        if data.water_fields is not None:
            water.append(data.water_fields[i][:, y0:y0 + crop, x0:x0 + crop].to(device))
        inputs.append(torch.cat(maps))
        targets.append(data.inair[i][:, y0:y0 + crop, x0:x0 + crop].to(device).float() / 255)
    colour = model.colour_net(torch.stack(inputs), views.contexts[idx], views.altitudes[idx],
                              torch.stack(water) if water else None)
    return F.mse_loss(colour, torch.stack(targets)), masked_mse(depth, views.depth_t[idx])


# ----------------------------------------------------------------------------------------- checkpoint
def _resume(checkpoint: dict | None, model: Restorer, rng: torch.Generator, val_idx: list[int],
            ckpt_path: Path) -> tuple[int, int, int, dict | None]:
    """Checkpoint: restore the model and the batch generator (the checkpoint must come from the same nets
    and split). Returns the stage and step to go on from, the stage-1 iterations done and the optimiser
    state of that stage; (1, 0, 0, None) without a checkpoint."""
    if checkpoint is None:
        return 1, 0, 0, None
    if checkpoint["model_config"] != model.to_config() or checkpoint["val_idx"] != val_idx:
        raise UserInputError(f"checkpoint {ckpt_path} was made with other nets or data: use a new --out-dir")
    model.load_state_dict(checkpoint["model"])
    rng.set_state(checkpoint["rng"])
    return (int(checkpoint["stage"]), int(checkpoint["step"]), int(checkpoint["stage1_steps"]),
            checkpoint["opt"])


def _save_checkpoint(run: RestorerRun, stage_now: int, step_now: int, opt_state: dict | None,
                     stage1_steps: int) -> None:
    """Checkpoint: ``out/checkpoint.pt`` (atomic) with the stage and step, the stage-1 iterations done, the
    model's configuration and state, the optimiser's state, the batch generator's and the split."""
    save_torch(run.out / CHECKPOINT, {
        "stage": stage_now, "step": step_now, "stage1_steps": stage1_steps, "model_config": run.model.to_config(),
        "model": run.model.state_dict(), "opt": opt_state, "rng": run.rng.get_state(), "val_idx": run.val_idx})


# ---------------------------------------------------------------------------------------------- write
def write_restorer_result(run: RestorerRun, steps: list[int], seconds: float, loss_value: float) -> RestorerResult:
    """Write the result files: the held-out RMSE (:func:`validate`) as ``validation.json`` and
    ``validation.md``, the model (``restorer.pt``) and ``result.json``; returns the result."""
    out, val_idx = run.out, run.val_idx
    table = validate(run.model, run.data, val_idx, run.device)
    atomic_write_bytes(out / VALIDATION_JSON, (json.dumps(
        {"val_count": len(val_idx), "units": "stored sRGB 0..1; relative depth 0..1", "rmse": table,
         "val_stems": [run.data.stems[i] for i in val_idx]}, indent=2) + "\n").encode())
    atomic_write_bytes(out / VALIDATION_MD, validation_markdown(table, len(val_idx), run.config.skip).encode())
    save_restorer(out / MODEL, run.model, {"steps": steps})
    result = RestorerResult(out, (steps[0], steps[1]), seconds, loss_value, table, len(run.train_idx), len(val_idx))
    result.write(out)
    return result
