"""The workspace's correct stage (``watergan correct --workspace WS``): every survey frame through the water's physics
inverse (:func:`pipeline.correct_physics.correct_physics_folder`) into ``physics/`` and through the restorer the
restorer stage trained (:func:`watergan.restore_folder.correct_folder`) into ``restorer/``. This module finds their
inputs in the workspace and names the set the mesh textures with."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from watergan.correction_range import CorrectMode
from watergan.data import DataError
from watergan.restore_folder import CorrectOptions, CorrectResult, correct_folder

if TYPE_CHECKING:
    from .correct_physics import PhysicsInputs
    from .workspace import Workspace


@dataclass(frozen=True)
class CorrectStage(CorrectOptions):
    """The workspace's correct stage: every survey frame through the water's physics inverse (``physics/``) and
    through the restorer the restorer stage trained (``restorer/``)."""

    images_dir: str = ""
    """Frames to correct (SfM's names); empty: the survey's images."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Progress bars."""


@dataclass
class CorrectStageResult:
    physics: str
    """Workspace-relative folder of the physics correction (images/, mask/, range_from/); empty: the water stage has
    not run."""
    physics_images: str
    """Its corrected frames: sRGB, the input's bit depth; every pixel corrected (:func:`fill_range`), but those
    outside the scene mask, written raw."""
    physics_mask: str
    """Its masks: 255 where the pixel was corrected at its measured range, 0 where its range was filled (from its
    neighbours or the far range) or it is not the scene (what the evaluation scores: measured range only)."""
    filled_fraction: float
    """Share of the scene's pixels whose range the physics correction interpolated from their neighbours."""
    far_fraction: float
    """Share of the scene's pixels the physics correction corrected at the survey's far range."""
    physics_seconds: float
    """Wall time of the physics correction (files included)."""
    restorer: str
    """Workspace-relative folder of the restorer's correction (images/, depth/, summary.json); empty: the restorer
    stage has not run."""
    images: str
    """The restorer's corrected frames."""
    depth: str
    """The restorer's relative depth maps."""
    corrected: int
    """Frames the restorer corrected."""
    failed: list[str]
    """Frames it could not read."""
    seconds: float
    """Wall time of the restorer's correction (files and model loading included)."""
    fps: float
    """The restorer's frames per second, file I/O and model loading included."""
    mode: str
    """"rgb-d" (each pixel's range from the range stage), "monocular" (the image and, when the restorer takes
    them, the altitude and a flat seafloor's range at it), or "" (no restorer)."""
    mesh_images: str
    """The corrected frames the mesh stage textures with: the physics correction's when every scene pixel of it had
    a measured range (or there is no restorer), else the restorer's."""
    range_source: str = ""
    """The restorer's range: "range maps", "flat seafloor" or "site depth net" (:class:`CorrectResult`)."""
    range_why: str = ""
    """Why monocular mode took the site depth net or kept the flat seafloor."""
    physics_range_source: str = ""
    """The physics correction's range: "range maps", "flat seafloor" or "site depth net"
    (:class:`pipeline.correct_physics.PhysicsResult`)."""
    physics_range_from: str = ""
    """Its per-pixel sources of range: ``range_from/<stem>.png``, :class:`watergan.correction_range.RangeFrom`
    (0 measured, 1 from the neighbours, 2 the far range, 3 not the scene, 4 the frame's plane)."""
    far_range_m: float = 0.0
    """The survey's far range (metres; 0: no pixel needed it, or monocular mode)."""


def physics_inputs(ws: Workspace, images: Path) -> PhysicsInputs:
    """What the physics correction of the frames ``images`` reads, found in the workspace: the water stage's estimate,
    the range stage's range maps and normals' smoothing, the dense stage's depth, the sfm stage's tracks and scene
    mask, and the restorer stage's folder (its site depth net) when it ran. A stage that has not run is a clear
    error."""
    from .correct_physics import PhysicsInputs

    water = ws.require("water", "the physics correction")
    ranges = ws.require("range", "the physics correction")
    dense = ws.require("dense", "the physics correction")
    sfm = ws.require("sfm", "the physics correction")
    return PhysicsInputs(images, ws.path(sfm.tracks), water.stack, ranges.normal_smooth_px, ws.path(ranges.range_dir),
                         ws.path(dense.depth_dir),
                         ws.path(sfm.scene_mask) if getattr(sfm, "scene_mask", "") else None,
                         ws.folder("restorer") if ws.result("restorer") is not None else None)


def run_correct_stage(ws: Workspace, cfg: CorrectStage) -> CorrectStageResult:
    """Correct the survey's frames into the stage's folder: ``physics/`` with the water stage's estimate and the range
    stage's maps (:func:`pipeline.correct_physics.correct_physics_folder`) when the water stage ran, ``restorer/`` with
    the restorer stage's model when it ran (a restorer in RGB-D mode takes the range stage's maps, ``cfg.mode``); at
    least one of them. Names the set the mesh textures with (``mesh_images``)."""
    from .correct_physics import correct_physics_folder

    water, restorer = ws.result("water"), ws.result("restorer")
    if water is None and restorer is None:
        raise DataError(f"the correction needs the water stage or the restorer stage in {ws.root}: run "
                        f"{ws.stage('water').how_to_run()} or {ws.stage('restorer').how_to_run()} first")
    images = Path(cfg.images_dir) if cfg.images_dir else ws.folder("survey") / "images"
    folder = ws.stage_dir("correct")
    physics = restored = physics_source = ""
    filled = far = physics_s = 0.0
    far_range_m = None
    sfm = ws.result("sfm")
    scene_mask = ws.path(sfm.scene_mask) if sfm is not None and getattr(sfm, "scene_mask", "") else None
    if water is not None:
        done = correct_physics_folder(physics_inputs(ws, images), folder / "physics", cfg.progress,
                                      str(cfg.image_format),
                                      CorrectMode.monocular if cfg.mode == CorrectMode.monocular else CorrectMode.rgbd,
                                      cfg.fill_px, cfg.far_range_pct, cfg.far_max_gain)
        filled, far, physics_s, physics_source = done.filled_fraction, done.far_fraction, done.seconds, \
            done.range_source
        far_range_m = done.far_range_m if np.isfinite(done.far_range_m) else None
        physics = ws.relative(folder / "physics")
    result = CorrectResult(folder / "restorer", 0, 0, mode="")
    if restorer is not None:
        done_range = ws.result("range")
        ranges = ws.path(done_range.range_dir) if done_range is not None else None
        result = correct_folder(restorer.out_dir, images, folder / "restorer", force=True, batch_size=cfg.batch_size,
                                progress=cfg.progress, scheduler=cfg.scheduler or None, range_dir=ranges,
                                mode=str(cfg.mode), image_format=str(cfg.image_format), scene_mask=scene_mask,
                                far_range_m=far_range_m, fill_px=cfg.fill_px, far_max_gain=cfg.far_max_gain,
                                far_range_pct=cfg.far_range_pct)
        restored = ws.relative(folder / "restorer")
    measured = filled == 0.0 and far == 0.0
    mesh = f"{physics}/images" if physics and (measured or not restored) else f"{restored}/images"
    return CorrectStageResult(
        physics=physics, physics_images=f"{physics}/images" if physics else "",
        physics_mask=f"{physics}/mask" if physics else "", filled_fraction=filled, far_fraction=far,
        physics_seconds=physics_s, restorer=restored, images=f"{restored}/images" if restored else "",
        depth=f"{restored}/depth" if restored else "", corrected=result.corrected, failed=result.failed,
        seconds=result.seconds, fps=result.corrected / max(result.seconds, 1e-9), mode=result.mode,
        mesh_images=mesh, range_source=result.range_source, range_why=result.range_why,
        physics_range_source=physics_source, physics_range_from=f"{physics}/range_from" if physics else "",
        far_range_m=far_range_m or 0.0)
