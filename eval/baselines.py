"""Baseline colour corrections to compare the restorer ("ours") against (paper Table I and II).

Every baseline is a plain function from a linear-RGB float image ``image`` (H,W,3), 0..1, to a
linear-RGB float image (H,W,3), 0..1 (clipped); the range-based ones also take ``range_m`` (H,W),
the camera-to-scene distance along each pixel's ray in metres (NaN or <= 0: unknown).

- ``raw``: the image unchanged.
- ``histogram_equalisation``: each channel equalised on its own, on the sRGB-encoded values (what
  image tools do; per channel, so it also stretches away a colour cast), 256 bins:
  V'_c = CDF_c(V_c), then decoded back to linear.
- ``clahe``: contrast-limited adaptive histogram equalisation (OpenCV, clip limit 2, 8 x 8 tiles) of
  the L channel of CIE Lab of the 8-bit sRGB image; a and b (hence the cast) are kept.
- ``gray_world``: one gain per channel so that every channel has the mean of the three channel
  means: J_c = I_c mean(I) / mean(I_c) (linear).
- ``jaffe_mcglamery``: the modified Jaffe-McGlamery inversion with given (ideal) coefficients,
  gain k, attenuation eta (1/m), veiling light B_inf and backscatter coefficient beta (1/m):
  J_c = (I_c / k_c - B_inf,c (1 - exp(-beta_c r))) / exp(-eta_c r). It knows neither vignetting nor
  any other effect.
- ``seathru``: a Sea-thru-style per-image fit (Akkaynak and Treibitz 2019) using range, see
  :func:`seathru`.
- ``oracle``: the true simulated formation stack inverted with the true geometry, see :func:`oracle`.

:data:`BASELINES` maps each name to its function and what it needs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from watergan.errors import UserInputError
from watergan.io import linear_to_srgb, quantise, srgb_to_linear


def _check(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise UserInputError(f"a baseline takes an (H,W,3) RGB image, got shape {image.shape}")
    return image.astype(np.float64, copy=False)


def _range(range_m: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    if range_m is None:
        raise UserInputError("this baseline needs the range (H,W) in metres: give --range-source truth or run the "
                             "dense stage")
    range_m = np.asarray(range_m, np.float64)
    if range_m.shape != tuple(shape[:2]):
        raise UserInputError(f"range map {range_m.shape} does not match the image {tuple(shape[:2])}")
    return range_m


def raw(image: np.ndarray) -> np.ndarray:
    """The uncorrected image: J = I."""
    return np.clip(_check(image), 0.0, 1.0)


def histogram_equalisation(image: np.ndarray, bins: int = 256) -> np.ndarray:
    """Per-channel histogram equalisation of the sRGB-encoded values: V'_c = CDF_c(V_c) (0..1),
    decoded back to linear."""
    from skimage.exposure import equalize_hist

    encoded = linear_to_srgb(_check(image))
    out = np.empty_like(encoded)
    for c in range(3):
        channel = encoded[..., c]
        out[..., c] = equalize_hist(channel, nbins=bins) if np.ptp(channel) > 0 else channel
    return np.clip(srgb_to_linear(out), 0.0, 1.0)


def clahe(image: np.ndarray, clip_limit: float = 2.0, tiles: int = 8) -> np.ndarray:
    """CLAHE (OpenCV) on the L channel of CIE Lab of the 8-bit sRGB image; a, b kept."""
    import cv2

    encoded = quantise(linear_to_srgb(_check(image)), 8)
    lab = cv2.cvtColor(encoded, cv2.COLOR_RGB2LAB)
    lab[..., 0] = cv2.createCLAHE(clipLimit=clip_limit, tileGridSize=(tiles, tiles)).apply(lab[..., 0])
    rgb = cv2.cvtColor(lab, cv2.COLOR_LAB2RGB).astype(np.float64) / 255.0
    return np.clip(srgb_to_linear(rgb), 0.0, 1.0)


def gray_world(image: np.ndarray) -> np.ndarray:
    """J_c = I_c mean(I) / mean(I_c): the channel means made equal (linear RGB), clipped to 0..1."""
    image = _check(image)
    means = image.reshape(-1, 3).mean(0)
    gains = means.mean() / np.maximum(means, 1e-12)
    return np.clip(image * gains, 0.0, 1.0)


def jaffe_mcglamery(image: np.ndarray, range_m: np.ndarray, eta_per_m, b_inf, beta_per_m,
                    k=(1.0, 1.0, 1.0)) -> np.ndarray:
    """J_c = (I_c / k_c - B_inf,c (1 - exp(-beta_c r))) / exp(-eta_c r), clipped to 0..1; pixels
    without a range keep I / k. Coefficients are per channel (R, G, B) or one value."""
    image = _check(image)
    r = _range(range_m, image.shape)
    known = np.isfinite(r) & (r > 0)
    r = np.where(known, r, 0.0)[..., None]
    eta, binf, beta = (np.broadcast_to(np.asarray(v, np.float64), (3,)) for v in (eta_per_m, b_inf, beta_per_m))
    gain = np.broadcast_to(np.asarray(k, np.float64).reshape(-1), (3,))
    backscatter = binf * -np.expm1(-beta * r)
    out = (image / gain - backscatter) * np.exp(eta * r)
    return np.clip(out, 0.0, 1.0)


def jaffe_coefficients(stack_config: list[dict]) -> dict:
    """The Jaffe-McGlamery coefficients (eta_per_m, b_inf, beta_per_m, k) of a formation stack
    configuration (``[{name, params}]``): attenuation's eta, backscatter's B_inf and beta, gain's k;
    an effect that is absent contributes nothing (eta 0, B_inf 0, k 1). Other effects are ignored
    (the Jaffe-McGlamery model does not know them)."""
    from watergan.formation import Stack

    values = {e.name: e.values() for e in Stack.from_config(list(stack_config)).effects}
    out = {"eta_per_m": [0.0] * 3, "b_inf": [0.0] * 3, "beta_per_m": [0.0] * 3, "k": [1.0] * 3}
    if "attenuation" in values:
        out["eta_per_m"] = values["attenuation"]["eta_per_m"].tolist()
    if "backscatter" in values:
        out["b_inf"] = values["backscatter"]["b_inf"].tolist()
        out["beta_per_m"] = values["backscatter"]["beta_per_m"].tolist()
    if "gain" in values:
        out["k"] = np.broadcast_to(values["gain"]["k"].numpy().reshape(-1), (3,)).tolist()
    return out


def _fit_backscatter(r: np.ndarray, values: np.ndarray) -> tuple[float, float, float, float]:
    """Least-squares (B_inf, beta, J', beta') of values ~ B_inf (1 - exp(-beta r)) + J' exp(-beta' r)
    over a few starting points; all parameters >= 0, B_inf and J' <= 1, betas <= 5 1/m."""
    from scipy.optimize import least_squares

    def residual(p):
        return p[0] * -np.expm1(-p[1] * r) + p[2] * np.exp(-p[3] * r) - values

    def jacobian(p):
        e1, e2 = np.exp(-p[1] * r), np.exp(-p[3] * r)
        return np.stack([1 - e1, p[0] * r * e1, e2, -p[2] * r * e2], 1)

    best = None
    top = float(max(values.max(), 1e-3))
    for start in ((top, 0.5, 0.0, 1.0), (top, 2.0, 0.1 * top, 0.5), (0.5 * top, 0.2, 0.0, 2.0)):
        fit = least_squares(residual, start, jac=jacobian, bounds=([0, 0, 0, 0], [1, 5, 1, 5]), loss="soft_l1",
                            f_scale=0.02)
        if best is None or fit.cost < best.cost:
            best = fit
    return tuple(float(v) for v in best.x)


def seathru(image: np.ndarray, range_m: np.ndarray, n_bins: int = 10, dark_fraction: float = 0.01,
            min_bin_pixels: int = 20) -> np.ndarray:
    """A Sea-thru-style per-image correction from the image and its range r (metres).

    1. Backscatter: the range (1st..99th percentile) is cut into ``n_bins`` bins; in each, the
       darkest ``dark_fraction`` of pixels (by R + G + B) are nearly pure backscatter. Per channel,
       fit those samples to B_c(r) = B_inf (1 - exp(-beta r)) + J' exp(-beta' r) (the second term
       takes up what is left of the direct signal in the darkest pixels) and subtract only the
       backscatter: D_c = max(I_c - B_inf (1 - exp(-beta r)), 0).
    2. Attenuation: the local illuminant at range r is the mean of D_c over the pixels of the range
       bin (a space-average colour per range); fit log E_c(r) = log E_c(0) - eta_c r by weighted least
       squares over the bins (eta_c in 0..5 1/m).
    3. Invert and white-balance: with a_c = mean over pixels of D_c exp(eta_c r) (the channel's
       attenuation-compensated average), J_c = D_c exp(eta_c r) mean(I) / a_c, so every channel has the
       input's mean over all pixels and channels (gray world on the attenuation-compensated image, the
       exposure kept as in :func:`gray_world`); clipped to 0..1.

    Pixels without a range take the median range.
    """
    image = _check(image)
    r = _range(range_m, image.shape)
    known = np.isfinite(r) & (r > 0)
    if known.sum() < n_bins * min_bin_pixels:
        raise UserInputError(f"Sea-thru needs a range for at least {n_bins * min_bin_pixels} pixels, "
                             f"got {int(known.sum())}")
    r = np.where(known, r, np.median(r[known]))
    flat_r, flat = r.reshape(-1), image.reshape(-1, 3)
    lo, hi = np.percentile(flat_r, [1, 99])
    if hi - lo < 1e-6:
        hi = lo + 1e-6
    edges = np.linspace(lo, hi, n_bins + 1)
    which = np.clip(np.digitize(flat_r, edges) - 1, 0, n_bins - 1)
    brightness = flat.sum(1)
    dark_r, dark_v = [], []
    for b in range(n_bins):
        idx = np.flatnonzero(which == b)
        if idx.size < min_bin_pixels:
            continue
        n = max(int(round(dark_fraction * idx.size)), 3)
        dark = idx[np.argpartition(brightness[idx], n - 1)[:n]]
        dark_r.append(flat_r[dark])
        dark_v.append(flat[dark])
    dark_r, dark_v = np.concatenate(dark_r), np.concatenate(dark_v)
    direct = np.empty_like(flat)
    for c in range(3):
        b_inf, beta, _, _ = _fit_backscatter(dark_r, dark_v[:, c])
        direct[:, c] = np.maximum(flat[:, c] - b_inf * -np.expm1(-beta * flat_r), 0.0)

    centres, means, counts = [], [], []
    for b in range(n_bins):
        sel = which == b
        if sel.sum() >= min_bin_pixels:
            centres.append(flat_r[sel].mean())
            means.append(direct[sel].mean(0))
            counts.append(sel.sum())
    centres, means, weights = np.array(centres), np.array(means), np.sqrt(np.array(counts, float))
    a, eta = np.empty(3), np.empty(3)
    for c in range(3):
        ok = means[:, c] > 1e-6
        if ok.sum() >= 2 and np.ptp(centres[ok]) > 1e-6:
            design = np.stack([np.ones(ok.sum()), -centres[ok]], 1) * weights[ok, None]
            (_, slope), *_ = np.linalg.lstsq(design, np.log(means[ok, c]) * weights[ok], rcond=None)
            eta[c] = float(np.clip(slope, 0.0, 5.0))
        else:
            eta[c] = 0.0
        a[c] = max(float(np.average(direct[:, c] * np.exp(eta[c] * flat_r))), 1e-6)
    out = direct * np.exp(eta * flat_r[:, None]) * (flat.mean() / a)
    return np.clip(out.reshape(image.shape), 0.0, 1.0)


def oracle(image: np.ndarray, state, stack, n_levels: int = 33) -> np.ndarray:
    """Invert the true formation stack, pixel by pixel, with the true geometry ``state`` (a one-frame
    :class:`watergan.formation.FormationState`; its ``direct`` is ignored).

    The stack is rendered with a constant in-air image J = t for levels t in 0..1. When it is affine
    in J per pixel (attenuation, backscatter, vignetting, gain, lights, caustics, marine snow...),
    I = A J + C with C = render(J = 0) and A = render(J = 1) - C, so J = (I - C) / A exactly. Otherwise
    (a nonlinear sensor response) J is read off the per-pixel curve render(J = t), t on ``n_levels``
    levels, by piecewise-linear inversion. Effects that mix neighbouring pixels (forward-scatter
    blur) are not undone. Pixels without a scene (``state.valid`` False) are 0."""
    import torch

    image = _check(image)
    h, w = image.shape[:2]
    if tuple(state.direct.shape[-2:]) != (h, w):
        raise UserInputError(f"the oracle's state is {tuple(state.direct.shape[-2:])}, the image {(h, w)}")

    def render(level: float) -> np.ndarray:
        direct = torch.full_like(state.direct[:1], level)
        with torch.no_grad():
            out = stack.render(state.replace(direct=direct, backscatter=None))
        return out[0].permute(1, 2, 0).double().numpy()

    c0, c_half, c1 = render(0.0), render(0.5), render(1.0)
    if np.abs(c_half - 0.5 * (c0 + c1)).max() < 1e-5:
        levels, curves = np.array([0.0, 1.0]), np.stack([c0, c1])
    else:
        levels = np.linspace(0.0, 1.0, n_levels)
        curves = np.stack([render(float(t)) for t in levels])
    # segment k: curves[k] <= I < curves[k+1] (curves increase with t); ends extrapolate linearly
    seg = np.clip((image[None] >= curves[1:-1]).sum(0), 0, len(levels) - 2)
    lo = np.take_along_axis(curves, seg[None], 0)[0]
    hi = np.take_along_axis(curves, seg[None] + 1, 0)[0]
    slope = np.where(np.abs(hi - lo) > 1e-12, hi - lo, np.nan)
    out = levels[seg] + (image - lo) / slope * (levels[1] - levels[0])
    out = np.nan_to_num(out, nan=0.0)
    if state.valid is not None:
        out[~state.valid[0, 0].numpy()] = 0.0
    return np.clip(out, 0.0, 1.0)


@dataclass(frozen=True)
class Baseline:
    """A registered baseline: its function and what it needs besides the image."""

    fn: Callable[..., np.ndarray]
    label: str
    """Name in tables and sentences."""
    needs_range: bool
    """Takes ``range_m`` (H,W) metres."""
    needs_truth: bool
    """Needs what only the simulator (or the user) knows: true coefficients or the true stack and geometry."""
    summary: str


BASELINES: dict[str, Baseline] = {
    "raw": Baseline(raw, "raw", False, False, "the uncorrected image"),
    "histeq": Baseline(histogram_equalisation, "hist. eq.", False, False,
                       "per-channel histogram equalisation of the sRGB values"),
    "clahe": Baseline(clahe, "CLAHE", False, False, "CLAHE on the Lab L channel"),
    "gray_world": Baseline(gray_world, "gray world", False, False, "channel means equalised (linear RGB)"),
    "jaffe": Baseline(jaffe_mcglamery, "Jaffe-McGlamery", True, True,
                      "modified Jaffe-McGlamery inversion with the ideal attenuation, backscatter and gain"),
    "seathru": Baseline(seathru, "Sea-thru", True, False,
                        "per-image backscatter and attenuation fit on range (Sea-thru style)"),
    "oracle": Baseline(oracle, "oracle", False, True,
                       "the true formation stack inverted with the true geometry (simulated surveys only)"),
}
