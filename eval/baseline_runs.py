"""The baselines run over a survey's frames for the evaluation (:mod:`eval.tables`): each frame through every method
into ``baselines/<method>/<name>`` (8-bit sRGB PNG), the range per frame for the range-based ones (the dense stage's
z-depth turned into ray length, or the simulator's truth), the oracle's re-rendered true geometry, the speed table's
timing, and chunks of frames on a Dask cluster.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eval.baselines import BASELINES, jaffe_coefficients
from eval.tables import RANGE_SOURCES, EvaluateConfig
from watergan.errors import UserInputError
from watergan.io import frame_file, z_to_range


def _camera_K(survey: Path, tracks) -> np.ndarray:
    from watergan.survey_files import read_camera_json

    cam = read_camera_json(survey / "camera.json")
    if cam is None:
        return np.asarray(tracks.K, float)
    return np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])


def fill_nearest(values: np.ndarray) -> np.ndarray:
    """Non-finite entries of (H,W) replaced by the nearest finite one (all NaN: unchanged)."""
    from scipy.ndimage import distance_transform_edt

    bad = ~np.isfinite(values)
    if not bad.any() or bad.all():
        return values
    idx = distance_transform_edt(bad, return_distances=False, return_indices=True)
    return values[tuple(idx)]


class RangeSource:
    """Range (H,W) metres per frame name from the dense stage or the simulator's truth."""

    def __init__(self, kind: str, dense_dir: Path | None, survey: Path, tracks) -> None:
        self.kind = kind
        self.dense_dir = Path(dense_dir).resolve() if dense_dir else None  # absolute: also read on a cluster's workers
        self.truth_dir = (survey / "truth" / "range").resolve()
        self.K = _camera_K(survey, tracks)
        self.fallback: list[str] = []
        depths = tracks.depths()
        names = [str(n) for n in tracks.image_names]
        self.sparse_m = {names[k]: float(np.median(depths[tracks.obs_image == k]))
                         for k in np.unique(tracks.obs_image)}
        self.sparse_all_m = float(np.median(depths)) if len(depths) else 1.0

    @staticmethod
    def choose(requested: str, dense_dir: Path | None, survey: Path) -> str:
        """The range source to use; ``dense_dir``: the dense stage's depth maps (None: it did not run)."""
        if requested not in RANGE_SOURCES:
            raise UserInputError(f"range source must be one of {', '.join(RANGE_SOURCES)}, got '{requested}'")
        dense = dense_dir is not None and Path(dense_dir).is_dir() and any(Path(dense_dir).glob("*.png"))
        truth = (survey / "truth" / "range").is_dir()
        if requested == "dense" and not dense:
            raise UserInputError(f"no dense depth maps ({dense_dir or 'the dense stage did not run'}): run "
                                 f"`watergan dense` first or use --range-source truth on a simulated survey")
        if requested == "truth" and not truth:
            raise UserInputError(f"no simulator range in {survey / 'truth' / 'range'}: --range-source truth needs a "
                                 f"simulated survey; use --range-source dense")
        if requested == "auto":
            return "dense" if dense else "truth" if truth else "none"
        return requested

    def __call__(self, name: str, shape: tuple[int, int]) -> np.ndarray:
        from watergan.io import read_depth

        if self.kind == "truth":
            r = read_depth(frame_file(self.truth_dir, name))
        else:
            path = self.dense_dir / f"{Path(name).stem}.png"
            z = read_depth(path) if path.is_file() else np.full(shape, np.nan)
            if z.shape != shape:
                raise UserInputError(f"dense depth {path} is {z.shape}, the image {shape}")
            r = z_to_range(z, self.K)
        if np.isfinite(r).mean() < 0.01:  # no usable depth: the frame's median sparse depth, everywhere
            self.fallback.append(name)
            return np.full(shape, self.sparse_m.get(name, self.sparse_all_m))
        return fill_nearest(r)


class OracleGeometry:
    """The simulator's true geometry and full stack: one formation state per frame (re-rendered)."""

    def __init__(self, survey: Path) -> None:
        from eval.synth import load_truth
        from eval.synth.camera import intrinsics_for
        from eval.synth.render import make_raycaster
        from eval.synth.scene import build_scene
        from watergan.formation import Stack

        self.survey = Path(survey)
        self.truth = load_truth(survey)
        cfg = self.truth.config
        self.scene = build_scene(cfg.scene, cfg.seed)
        self.caster = make_raycaster(self.scene)
        self.intr = intrinsics_for(cfg.camera)
        self.stack = Stack.from_config(self.truth.effects["full"])
        self.index = {name: k for k, name in enumerate(self.truth.frames)}
        self.stems = {Path(name).stem: k for k, name in enumerate(self.truth.frames)}  # a survey in another format

    def state(self, name: str):
        from eval.synth.render import frame_state, render_view

        cfg = self.truth.config
        k = self.index.get(name, self.stems.get(Path(name).stem))
        if k is None:
            raise UserInputError(f"frame {name} is not in the simulator's truth of {self.truth.root}")
        view = render_view(self.caster, self.scene, self.intr, self.truth.world_from_cam[k], cfg.render)
        return frame_state(view, k, cfg.render.site_depth_m)


def _write_srgb8(path: Path, linear: np.ndarray) -> None:
    """A baseline's frame as an 8-bit sRGB PNG (``path``'s stem; lossless whatever the survey's format: a JPEG's
    block artefacts would be measured as the method's)."""
    from watergan.io import write_srgb8

    write_srgb8(path.with_suffix(".png"), linear)


@dataclass(frozen=True, eq=False)
class BaselineChunk:
    """Frames to correct with every method (plain, picklable values: it may run on a Dask worker)."""

    names: tuple[str, ...]
    images: Path
    methods: tuple[str, ...]
    out_dir: Path
    ranges: RangeSource | None
    """Range per frame (plain data; the frames that fell back to a constant range are returned)."""
    coefficients: dict | None
    oracle_survey: Path | None
    """The simulated survey whose true geometry the oracle re-renders (built once per chunk)."""


#: Frames of a local run that every baseline corrects one at a time, timed, before the rest run two at a time: the
#: speed table's seconds per frame are theirs, each method alone on the machine.
TIMED_FRAMES = 8


#: Frames corrected at once after the timed ones in a local run (the methods and the file I/O release the GIL in
#: OpenCV, NumPy and torch; each lane on one torch thread).
BASELINE_LANES = 2


def baseline_chunk(job: BaselineChunk, geometry=None, progress: bool = False, timed: int | None = None
                   ) -> tuple[dict[str, float], int, list[str]]:
    """Every frame of ``job`` through every method into ``out_dir/<method>/<name>`` (8-bit sRGB, atomically).
    Returns each method's correction seconds summed over the first ``timed`` frames (None: all), which run one at a
    time, the number of those frames, and the frames without a usable range (in ``job.names`` order); the frames
    after them run ``BASELINE_LANES`` at a time, untimed. ``geometry``: the oracle's, when already built (local
    runs); else built here from ``oracle_survey``."""
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    from watergan.device import single_torch_thread

    seconds = dict.fromkeys(job.methods, 0.0)
    if "oracle" in job.methods and geometry is None:
        geometry = OracleGeometry(job.oracle_survey)
    before = len(job.ranges.fallback) if job.ranges is not None else 0
    timed = len(job.names) if timed is None else min(timed, len(job.names))

    def correct(name: str, spent: dict[str, float]) -> None:
        _correct_frame(name, job.images, list(job.methods), job.out_dir, spent, job.ranges, job.coefficients,
                       geometry)
        bar.update(1)

    with single_torch_thread(), tqdm(total=len(job.names), desc="baselines", unit="frame",
                                     disable=not progress) as bar:  # the oracle's renders: torch's pool contends
        for name in job.names[:timed]:
            correct(name, seconds)
        with ThreadPoolExecutor(BASELINE_LANES) as pool:
            list(pool.map(lambda name: correct(name, dict.fromkeys(job.methods, 0.0)), job.names[timed:]))
    fallback = set(job.ranges.fallback[before:]) if job.ranges is not None else set()
    return seconds, timed, [n for n in job.names if n in fallback]


def run_baselines(names: list[str], images: Path, methods: list[str], out_dir: Path, ranges=None,
                  coefficients: dict | None = None, geometry=None, scheduler=None,
                  chunk_size: int = 8, progress: bool = True) -> dict[str, float]:
    """Correct every frame with every method into ``out_dir/<method>/<name>`` (8-bit sRGB); returns
    the seconds per frame of each method's correction alone.

    ``scheduler``: empty or None runs here: the first ``TIMED_FRAMES`` frames one at a time (the seconds per frame
    are theirs), the rest ``BASELINE_LANES`` at a time; a Dask scheduler address or ``distributed.Client`` sends
    ``chunk_size`` frames per task to the cluster (:mod:`watergan.parallel`; folders on a file system the workers
    share; the oracle's geometry is rebuilt once per chunk; every frame timed). The files are the same either way.
    ``ranges.fallback`` lists the frames that had no usable range."""
    from watergan.parallel import chunks, is_distributed, map_tasks, shared_path

    needs_range = any(BASELINES[m].needs_range for m in methods)
    frame_ranges = ranges if needs_range else None
    if not is_distributed(scheduler):
        results = [baseline_chunk(BaselineChunk(tuple(names), images, tuple(methods), out_dir, frame_ranges,
                                                coefficients, None), geometry, progress, TIMED_FRAMES)]
    else:
        survey = shared_path(geometry.survey) if geometry is not None else None
        jobs = [BaselineChunk(tuple(part), shared_path(images), tuple(methods), shared_path(out_dir), frame_ranges,
                              coefficients, survey) for part in chunks(names, chunk_size)]
        results = map_tasks(baseline_chunk, jobs, scheduler, desc="baselines", unit="chunk", progress=progress)
    if frame_ranges is not None:
        frame_ranges.fallback = [n for *_, fell_back in results for n in fell_back]
    seconds = {m: sum(part[m] for part, *_ in results) for m in methods}
    timed = sum(count for _, count, _ in results)
    return {m: s / max(timed, 1) for m, s in seconds.items()}


def _correct_frame(name: str, images: Path, methods: list[str], out_dir: Path, seconds: dict[str, float], ranges,
                   coefficients: dict | None, geometry) -> None:
    """One frame through every method (adds each method's correction time to ``seconds``)."""
    from eval.colour import read_rgb

    image = read_rgb(images / name)
    range_m = ranges(name, image.shape[:2]) if ranges is not None else None
    state = geometry.state(name) if "oracle" in methods else None
    for m in methods:
        start = time.perf_counter()
        if m == "jaffe":
            corrected = BASELINES[m].fn(image, range_m, **coefficients)
        elif m == "oracle":
            corrected = BASELINES[m].fn(image, state, geometry.stack)
        elif BASELINES[m].needs_range:
            corrected = BASELINES[m].fn(image, range_m)
        else:
            corrected = BASELINES[m].fn(image)
        seconds[m] += time.perf_counter() - start
        _write_srgb8(out_dir / m / name, corrected)


def method_inputs(cfg: EvaluateConfig, survey: Path, tracks, simulated: bool, dense_dir: Path | None):
    """(methods that can run, skipped method -> why, range source or None, Jaffe coefficients, oracle geometry).
    ``dense_dir``: the dense stage's depth maps, None when it did not run."""
    skipped: dict[str, str] = {}
    range_kind = RangeSource.choose(cfg.range_source, dense_dir, survey)
    ranges = RangeSource(range_kind, dense_dir, survey, tracks) if range_kind != "none" else None
    coefficients = None
    if "jaffe" in cfg.methods:
        if cfg.jaffe_stack:
            path = Path(cfg.jaffe_stack)
            if not path.is_file():
                raise UserInputError(f"Jaffe-McGlamery stack file {path} does not exist")
            coefficients = jaffe_coefficients(json.loads(path.read_text()))
        elif simulated:
            coefficients = jaffe_coefficients(json.loads((survey / "truth" / "effects.json").read_text())["full"])
        else:
            skipped["jaffe"] = "no coefficients: give a formation-stack JSON with --jaffe-stack"
    geometry = None
    if "oracle" in cfg.methods:
        if simulated:
            geometry = OracleGeometry(survey)
        else:
            skipped["oracle"] = "needs the simulator's truth (not a simulated survey)"
    methods = []
    for m in cfg.methods:
        if m in skipped:
            continue
        if BASELINES[m].needs_range and ranges is None:
            skipped[m] = "no range: run the dense stage (or --range-source truth on a simulated survey)"
            continue
        methods.append(m)
    return methods, skipped, ranges, coefficients, geometry
