"""Reading a simulated survey's truth back (for tests and evaluation; pipeline stages must not
need it)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from watergan.io import read_depth, read_json

from .camera import Intrinsics
from .config import SimulationConfig, config_from_dict


@dataclass(frozen=True)
class BoardTruth:
    names: list[str]
    corners_world: np.ndarray  # (24,4,3) metres
    linear_rgb: np.ndarray     # (24,3)
    srgb: np.ndarray           # (24,3)
    frames: list[str]          # frames in which the board is visible


@dataclass(frozen=True)
class Truth:
    frames: list[str]
    intrinsics: Intrinsics
    world_from_cam: np.ndarray               # (N,4,4)
    world_from_cam_right: np.ndarray | None  # (N,4,4) for a stereo rig
    baseline_m: float | None
    board: BoardTruth | None
    effects: dict                            # {"visible", "hidden", "full"} stack configurations
    config: SimulationConfig
    root: Path

    def depth_m(self, index: int) -> np.ndarray:
        """True camera-z depth (H,W) of frame ``index``, metres (1 mm steps; NaN: no value)."""
        return read_depth(self.root / "truth" / "depth" / self.frames[index])

    def range_m(self, index: int) -> np.ndarray:
        """True ray length (H,W) of frame ``index``, metres (1 mm steps)."""
        return read_depth(self.root / "truth" / "range" / self.frames[index])


def load_truth(out_dir: str | Path) -> Truth:
    """Poses, intrinsics, board, effects and configuration of a survey written by simulate_survey."""
    root = Path(out_dir)
    if not (root / "truth" / "poses.json").is_file():
        raise FileNotFoundError(f"{root} is not a simulated survey (no truth/poses.json)")
    camera = read_json(root / "camera.json")
    poses = read_json(root / "truth" / "poses.json")["frames"]
    board = read_json(root / "truth" / "board.json")
    right = [p["world_from_cam_right"] for p in poses if "world_from_cam_right" in p]
    board_truth = None
    if board["patches"]:
        board_truth = BoardTruth(
            names=[p["name"] for p in board["patches"]],
            corners_world=np.array([p["corners_world"] for p in board["patches"]]),
            linear_rgb=np.array([p["linear_rgb"] for p in board["patches"]]),
            srgb=np.array([p["srgb"] for p in board["patches"]]),
            frames=[f["name"] for f in board["frames"]],
        )
    return Truth(
        frames=[p["name"] for p in poses],
        intrinsics=Intrinsics.from_json(camera),
        world_from_cam=np.array([p["world_from_cam"] for p in poses]),
        world_from_cam_right=np.array(right) if right else None,
        baseline_m=camera.get("baseline_m"),
        board=board_truth,
        effects=read_json(root / "truth" / "effects.json"),
        config=config_from_dict(SimulationConfig, read_json(root / "truth" / "config.json")),
        root=root,
    )
