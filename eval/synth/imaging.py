"""Underwater images from rendered frames: the full formation stack, sensor noise, sRGB, bits.

The full stack is the visible stack with the hidden effects inserted by their ``rank`` (a stable
sort, so visible effects keep their order and a hidden effect follows visible ones of equal rank).
Sensor noise on the linear image I (0..1): I' = I + N(0, I / e + s^2), e = ``shot_noise_e``
photo-electrons at I = 1 (shot noise), s = ``read_noise``; I' is clipped to 0..1, sRGB-encoded
and quantised.
"""

from __future__ import annotations

import numpy as np
import torch

from watergan.formation import Counts, FormationState, Stack, get
from watergan.io import linear_to_srgb, quantise


def full_stack_config(visible: list[dict] | tuple[dict, ...], hidden: list[dict] | tuple[dict, ...]) -> list[dict]:
    """Visible and hidden stack entries merged in scene-to-sensor order (stable sort by rank)."""
    visible_names = [e["name"] for e in visible]
    for entry in hidden:
        if entry["name"] in visible_names:
            raise ValueError(f"hidden effect '{entry['name']}' is already in the visible stack {visible_names}")
    return Stack.rank_order([*visible, *hidden])


def rig_camera_config(full: list[dict], camera_offset_m: tuple[float, float, float]) -> list[dict]:
    """The full stack configuration for a rig camera at ``camera_offset_m`` (metres, in the frame of the
    reference camera, whose configuration ``full`` is, with parallel axes: a stereo rig's right camera is
    at (baseline, 0, 0)). The lights are fixed to the rig, so a light at L in the reference frame is at
    L - offset in this camera's frame; every other effect is the same."""
    out = []
    for entry in full:
        if entry["name"] == "artificial_light":
            params = dict(entry["params"])
            params["offset_m"] = [[p - o for p, o in zip(light, camera_offset_m, strict=True)]
                                  for light in params["offset_m"]]
            entry = {"name": entry["name"], "params": params}
        out.append(entry)
    return out


def build_stacks(visible, hidden, frames: int | None = None) -> tuple[Stack, Stack, Stack]:
    """(visible, hidden, full) stacks; the hidden stack lists the hidden effects by rank. ``frames``: the
    survey's frame count, which sizes per-frame parameters (:attr:`watergan.formation.Param.per`): one not
    given starts at its initial value in every frame, one given with fewer rows repeats them in order over
    the frames (how an effect's ``simulation_params`` give a per-frame pattern without knowing the survey's
    length)."""
    counts = Counts(frames=frames)
    visible, hidden = ([per_frame_tiled(e, frames) for e in entries] for entries in (visible, hidden))
    return (Stack.from_config(visible, counts), Stack.from_config(full_stack_config([], hidden), counts),
            Stack.from_config(full_stack_config(visible, hidden), counts))


def per_frame_tiled(entry: dict, frames: int | None) -> dict:
    """A stack entry whose per-frame parameter values of fewer than ``frames`` rows are repeated in order to
    ``frames`` rows (see :func:`build_stacks`); unchanged without ``frames``."""
    params = dict(entry.get("params", {}))
    for p in get(entry["name"]).params:
        if p.per == "frame" and frames and p.name in params:
            rows = np.asarray(params[p.name], float).reshape(-1, *np.shape(p.init))
            if len(rows) < frames:
                params[p.name] = np.resize(rows, (frames, *rows.shape[1:])).tolist()
    return {**entry, "params": params}


@torch.no_grad()
def linear_image(stack: Stack, state: FormationState) -> np.ndarray:
    """The recorded linear image (H,W,3), float32, of a one-frame state (no noise)."""
    return stack.render(state)[0].permute(1, 2, 0).numpy().astype(np.float32)


def add_sensor_noise(linear: np.ndarray, shot_noise_e: float, read_noise: float,
                     rng: np.random.Generator) -> np.ndarray:
    """I' = clip(I + sqrt(max(I, 0) / e + s^2) N(0, 1), 0, 1)."""
    sigma = np.sqrt(np.clip(linear, 0.0, None) / shot_noise_e + read_noise * read_noise)
    return np.clip(linear + sigma * rng.standard_normal(linear.shape, dtype=np.float32), 0.0, 1.0)


def encode(linear: np.ndarray, bit_depth: int) -> np.ndarray:
    """sRGB-encoded, quantised image (uint8 or uint16) of a linear image in 0..1."""
    return quantise(linear_to_srgb(linear), bit_depth)
