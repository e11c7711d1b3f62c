"""Reading an image at sub-pixel positions: the one bilinear sampler and the one footprint pyramid.

Both measurers read colours through them (the water's table, :func:`eval.observations.measure_frames`, and the
diagnosis's survey folders, :mod:`eval.diagnose_measure`), and the mesh's texture reads its frames with
:func:`bilinear`.

Footprint: a view of a surface patch at camera depth d covers f s / d pixels for a patch of size s on the surface,
so reading every view of a point through a Gaussian of sigma proportional to 1 / d averages the same patch of
surface in each. :class:`FootprintPyramid` holds the image blurred at sigma_0 STEP^j (``FOOTPRINT_STEP``) and reads
a position at its own sigma by interpolating linearly in log sigma between the two levels around it.
"""

from __future__ import annotations

import numpy as np

#: Ratio of the blurs of consecutive levels of a :class:`FootprintPyramid`.
FOOTPRINT_STEP = 1.5


def bilinear(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Values (M[,C]) of an (H,W[,C]) image at sub-pixel positions ``xy`` (M,2) (x, y; OpenCV centres), positions
    clamped to [0, W - 1.001] x [0, H - 1.001] (inside the image):

        v = (1 - f_y) ((1 - f_x) I[y0, x0] + f_x I[y0, x0 + 1]) + f_y ((1 - f_x) I[y0 + 1, x0] + f_x I[y0 + 1, x0 + 1])

    with x0 = floor(x), f_x = x - x0 (and the same in y). Float64 positions give float64 values."""
    h, w = image.shape[:2]
    x = np.clip(xy[:, 0], 0, w - 1.001)
    y = np.clip(xy[:, 1], 0, h - 1.001)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    if image.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    return ((1 - fy) * ((1 - fx) * image[y0, x0] + fx * image[y0, x0 + 1])
            + fy * ((1 - fx) * image[y0 + 1, x0] + fx * image[y0 + 1, x0 + 1]))


class FootprintPyramid:
    """An (H,W,C) image blurred by Gaussians of sigma_j = ``sigma0`` x FOOTPRINT_STEP^j pixels, j < ``levels``
    (each level made when first read; sigma 0: the image itself), read at positions each at its own blur
    (:meth:`sample`)."""

    def __init__(self, image: np.ndarray, sigma0: float, levels: int):
        self.image, self.sigma0, self.levels = image, float(sigma0), int(levels)
        self._blurred: dict[int, np.ndarray] = {}

    def level(self, j: int) -> np.ndarray:
        """The image blurred by sigma_j (OpenCV's Gaussian, the image's dtype)."""
        if j not in self._blurred:
            import cv2

            sigma = self.sigma0 * FOOTPRINT_STEP ** j
            self._blurred[j] = cv2.GaussianBlur(self.image, (0, 0), sigma) if sigma > 0 else self.image
        return self._blurred[j]

    def sample(self, xy: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """(M,C) float64 values at ``xy`` (M,2), each blurred by its ``sigma`` (M,) pixels: the position of sigma
        among the levels, p = clip(log(max(sigma, 1e-6) / sigma_0) / log(STEP), 0, levels - 1.001), j = floor(p),
        t = p - j, gives (1 - t) bilinear(level j) + t bilinear(level j + 1) (:func:`bilinear`). One level: the
        bilinear samples of it, whatever sigma."""
        if self.levels == 1:
            return bilinear(self.level(0), xy).astype(np.float64)
        pos = np.clip(np.log(np.maximum(sigma, 1e-6) / self.sigma0) / np.log(FOOTPRINT_STEP), 0, self.levels - 1.001)
        low = np.floor(pos).astype(int)
        t = (pos - low)[:, None]
        out = np.zeros((len(xy), self.image.shape[2]))
        for j in np.unique(low):
            sel = low == j
            out[sel] = (1 - t[sel]) * bilinear(self.level(j), xy[sel]) + t[sel] * bilinear(self.level(j + 1), xy[sel])
        return out
