"""SfM tracks as arrays: the sparse reconstruction every measurement reuses (written by the sfm stage)."""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from watergan.errors import UserInputError
from watergan.io import atomic_write_bytes


@dataclass
class Tracks:
    """The sparse reconstruction as arrays (the contents of ``tracks.npz``). Image index k refers to
    ``image_names[k]``; unregistered images have ``registered[k] = False`` and a NaN pose."""

    image_names: np.ndarray
    """(N,) file names in the images folder, sorted."""
    registered: np.ndarray
    """(N,) bool."""
    world_from_cam: np.ndarray
    """(N,4,4) camera-to-world poses in the survey frame (OpenCV camera axes: x right, y down, z forward)."""
    K: np.ndarray
    """(3,3) pinhole intrinsics, OpenCV pixel convention."""
    width: int
    height: int
    point_id: np.ndarray
    """(P,) COLMAP point3D id."""
    xyz: np.ndarray
    """(P,3) point positions, survey frame (metres when scaled)."""
    rgb: np.ndarray
    """(P,3) uint8 colour COLMAP extracted from the raw images."""
    obs_point: np.ndarray
    """(M,) row of the observed point in ``xyz``."""
    obs_image: np.ndarray
    """(M,) index of the observing image."""
    obs_xy: np.ndarray
    """(M,2) pixel position of the observation (OpenCV convention), float32."""

    def save(self, path: str | Path) -> None:
        buffer = io.BytesIO()
        np.savez_compressed(buffer, **{k: np.asarray(v) for k, v in self.__dict__.items()})
        atomic_write_bytes(Path(path), buffer.getvalue())

    @classmethod
    def load(cls, path: str | Path) -> Tracks:
        path = Path(path)
        if not path.is_file():
            raise UserInputError(f"no sparse tracks at {path}: run the sfm stage first")
        with np.load(path, allow_pickle=False) as data:
            values = {k: data[k] for k in data.files}
        values["width"], values["height"] = int(values["width"]), int(values["height"])
        return cls(**values)

    def track_lengths(self) -> np.ndarray:
        """(P,) observations per point."""
        return np.bincount(self.obs_point, minlength=len(self.xyz))

    def depths(self) -> np.ndarray:
        """(M,) camera z of each observation's point in its image, p_c = R^T (p_w - t)."""
        pose = self.world_from_cam[self.obs_image]
        rel = self.xyz[self.obs_point] - pose[:, :3, 3]
        return np.einsum("mi,mi->m", rel, pose[:, :3, 2])
