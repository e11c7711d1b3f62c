"""Fidelity against the in-air truth (simulated surveys): PSNR (dB) and SSIM of each method's sRGB-encoded frames,
over every pixel or over the pixels a method corrected (its mask), and the share it marked as not corrected.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from watergan.io import frame_file

SSIM_WINDOW_PX = 7
"""Side of SSIM's uniform window: scikit-image's default, which these tables have always used (Wang et al. 2004 weigh
an 11x11 window by a Gaussian instead)."""


def ssim_map(a: np.ndarray, b: np.ndarray, data_range: float = 1.0) -> np.ndarray:
    """(H,W,C) float32 SSIM of (H,W,C) images at each pixel, channel by channel, as scikit-image's
    ``structural_similarity(b, a, channel_axis=2, full=True)`` computes it: local means, sample variances and
    covariance over a 7x7 uniform window (edges mirrored), S = (2 u_a u_b + C1)(2 s_ab + C2) / ((u_a^2 + u_b^2 + C1)
    (s_a^2 + s_b^2 + C2)) with C1 = (0.01 L)^2, C2 = (0.03 L)^2 and L = ``data_range``. OpenCV's box filter does the
    windows in float32, as scikit-image does with SciPy's (benchmarks/RESULTS/restorer.md compares the two)."""
    import cv2

    def mean(x: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(x, -1, (SSIM_WINDOW_PX, SSIM_WINDOW_PX), normalize=True, borderType=cv2.BORDER_REFLECT)

    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    n = SSIM_WINDOW_PX * SSIM_WINDOW_PX
    cov_norm = n / (n - 1)
    ua, ub = mean(a), mean(b)
    va = cov_norm * (mean(a * a) - ua * ua)
    vb = cov_norm * (mean(b * b) - ub * ub)
    vab = cov_norm * (mean(a * b) - ua * ub)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    return (2 * ua * ub + c1) * (2 * vab + c2) / ((ua * ua + ub * ub + c1) * (va + vb + c2))


def ssim(a: np.ndarray, b: np.ndarray, data_range: float = 1.0) -> float:
    """Mean SSIM of (H,W,C) images (:func:`ssim_map`) over the pixels whose window lies inside the image, as
    scikit-image's ``structural_similarity`` averages it."""
    pad = (SSIM_WINDOW_PX - 1) // 2
    return float(ssim_map(a, b, data_range)[pad:-pad, pad:-pad].mean(dtype=np.float64))


def fidelity(folder: Path, truth_dir: Path, names: list[str], mask_dir: Path | None = None) -> tuple[float, float]:
    """Mean over frames of PSNR (dB) and SSIM of the sRGB-encoded frames against the in-air truth. With
    ``mask_dir`` (``<stem>.png``, 0 = a pixel the method marked as not corrected, e.g. the physics correction's
    pixels without range) both are taken over the pixels the method corrected: PSNR = 10 log10(1 / MSE) over them,
    and the mean of the SSIM map over them (a mark is not a guess; the share marked is reported beside)."""
    return fidelities({"method": folder}, truth_dir, names, {"method": mask_dir})["method"]


def fidelities(folders: dict[str, Path], truth_dir: Path, names: list[str],
               mask_dirs: dict[str, Path | None] | None = None, threads: int = 2) -> dict[str, tuple[float, float]]:
    """:func:`fidelity` of each method's folder (the means of :func:`frame_fidelities`)."""
    per_frame = frame_fidelities(folders, truth_dir, names, mask_dirs, threads)
    return {m: (float(np.mean(v[:, 0])), float(np.mean(v[:, 1]))) for m, v in per_frame.items()}


def frame_fidelities(folders: dict[str, Path], truth_dir: Path, names: list[str],
                     mask_dirs: dict[str, Path | None] | None = None, threads: int = 2) -> dict[str, np.ndarray]:
    """Each method's (PSNR, SSIM) per frame, (N,2) in the order of ``names``, each truth frame read once, ``threads``
    frames at a time (OpenCV's decoding and filters release the GIL)."""
    from concurrent.futures import ThreadPoolExecutor

    from eval.colour import read_rgb

    mask_dirs = mask_dirs or {}

    def frame(name: str) -> dict[str, tuple[float, float]]:
        truth = read_rgb(frame_file(truth_dir, name), linear=False)
        out = {}
        for method, folder in folders.items():
            image = read_rgb(frame_file(folder, name), linear=False)
            mask_dir = mask_dirs.get(method)
            keep = _mask(mask_dir / f"{Path(name).stem}.png", image.shape[:2]) if mask_dir is not None else None
            if keep is None:
                mse = float(np.mean((image.astype(np.float64) - truth) ** 2))
                out[method] = (10.0 * np.log10(1.0 / max(mse, 1e-12)), ssim(truth, image))
                continue
            mse = float(np.mean((image[keep] - truth[keep]) ** 2)) if keep.any() else float("nan")
            out[method] = (10.0 * np.log10(1.0 / max(mse, 1e-12)),
                           float(ssim_map(truth, image)[keep].mean()) if keep.any() else float("nan"))
        return out

    with ThreadPoolExecutor(max(1, threads)) as pool:
        per_frame = list(pool.map(frame, names))
    return {m: np.array([f[m] for f in per_frame], float).reshape(-1, 2) for m in folders}


def marked_share(mask_dir: Path, names: list[str]) -> float:
    """The share of the frames' pixels a method marked as not corrected (0 in ``mask_dir/<stem>.png``)."""
    shares = [1.0 - float(_mask(mask_dir / f"{Path(name).stem}.png", None).mean()) for name in names]
    return float(np.mean(shares)) if shares else 0.0


def _mask(path: Path, hw: tuple[int, int] | None) -> np.ndarray:
    from watergan.io import read_grey8

    mask = read_grey8(path, "mask")
    if hw is not None and mask.shape != hw:
        raise ValueError(f"mask {path} is {mask.shape[1]}x{mask.shape[0]}, the frame {hw[1]}x{hw[0]}")
    return mask > 0
