"""The run's report: one self-contained HTML page people read, and the same facts as JSON.

``write_report(ws)`` writes ``WORKSPACE/11_report/report.html``, ``report.json`` and ``report.md`` (the
text: verdict and tables). The page needs no network: every image is inlined as a base64 data URI
(large images downscaled), there is no script; links point to local files in the workspace (the GLB
mesh, the full-size mosaic). Sections:

1. verdict: where ours wins and loses (from the eval stage's ``tables.json``);
2. the same frames side by side: raw, every baseline, ours, the oracle and the in-air truth
   (paper Fig. 5); the scene mask and the overlay SfM proposes to mask, drawn over a frame;
3. the tables (paper Tables I-III, fidelity, depth, speed), best value in bold;
4. per-patch board error as bar charts, per-point consistency as histograms;
5. depth: monocular vs stereo error maps (the eval stage's ``depth/``);
6. the textured mesh: a rendered view (the orthophoto draped on the mesh's height field, drawn with
   matplotlib; vertical exaggeration stated) with a link to the GLB, and the mosaic;
7. the site water (the water stage's estimate with its intervals, residual plot) and the diagnosis: the
   model ledger plot and verdict (the diagnose stage's folder);
8. each stage's configuration and result (timings).

A section whose stage did not run says "not run" (and which command makes it); a section that
fails to draw says so and the page is still written.
"""

from __future__ import annotations

import base64
import html
import io
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from watergan.errors import UserInputError
from watergan.io import atomic_write_json, atomic_write_text, frame_file
from watergan.water_record import WaterRecord, read_water

from .report_found import NotRun, eval_tables, found_lines, load_json, stage_result
from .workspace import Workspace

#: Longest side of an inlined photograph / mosaic, pixels.
THUMB_PX = 320
MOSAIC_PX = 1000


# ----------------------------------------------------------------------------------------- helpers


def _esc(text) -> str:
    return html.escape(str(text))


def _resize(rgb: np.ndarray, max_side: int) -> np.ndarray:
    import cv2

    h, w = rgb.shape[:2]
    scale = max_side / max(h, w)
    if scale >= 1:
        return rgb
    return cv2.resize(rgb, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)


def read_display(path: Path) -> np.ndarray:
    """An image file as 8-bit RGB for display (16-bit scaled down, grey expanded)."""
    import cv2

    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise UserInputError(f"cannot read image {path}")
    if raw.dtype == np.uint16:
        raw = (raw.astype(np.float64) / 257.0).round().astype(np.uint8)
    if raw.ndim == 2:
        raw = np.repeat(raw[..., None], 3, axis=2)
    return np.ascontiguousarray(raw[..., 2::-1] if raw.shape[2] >= 3 else raw)


def data_uri(rgb: np.ndarray, fmt: str = "jpeg", max_side: int | None = THUMB_PX) -> str:
    """An 8-bit RGB array as a data URI (JPEG quality 88 or PNG), downscaled to ``max_side``."""
    import cv2

    if max_side:
        rgb = _resize(rgb, max_side)
    ext, params = (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 88]) if fmt == "jpeg" else (".png", [])
    ok, data = cv2.imencode(ext, np.ascontiguousarray(rgb[..., ::-1]), params)
    if not ok:
        raise OSError("could not encode an image for the report")
    mime = "image/jpeg" if fmt == "jpeg" else "image/png"
    return f"data:{mime};base64,{base64.b64encode(data.tobytes()).decode('ascii')}"


def figure_uri(fig) -> str:
    """A matplotlib figure as a PNG data URI (the figure is closed)."""
    import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return f"data:image/png;base64,{base64.b64encode(buffer.getvalue()).decode('ascii')}"


def _img(uri: str, alt: str, cls: str = "") -> str:
    return f"<img src='{uri}' alt='{_esc(alt)}'{f' class={cls!r}' if cls else ''}>"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _link(ws, out: Path, path: str | Path, text: str) -> str:
    target = ws.path(path) if not Path(path).is_absolute() else Path(path)
    rel = os.path.relpath(target, out)
    return f"<a href='{_esc(Path(rel).as_posix())}'>{_esc(text)}</a>"


# ---------------------------------------------------------------------------------------- sections


def section_found(ws, out: Path) -> tuple[str, dict]:
    lines, command = found_lines(ws)
    if not lines:
        raise NotRun("not run: no water, diagnosis or evaluation yet")
    items = "".join(f"<li>{_esc(line)}</li>" for line in lines)
    body = f"<ul>{items}</ul>" + (f"<p><b>Next:</b> <code>{_esc(command)}</code></p>" if command else "")
    return body, {"found": lines, "next": command}


def section_verdict(ws, out: Path) -> tuple[str, dict]:
    data = eval_tables(ws)
    lines = data.get("verdict", [])
    items = "".join(f"<li class='{'lose' if ' loses to ' in line else ''}'>{_esc(line)}</li>" for line in lines)
    methods = ", ".join(data["labels"].get(m, m) for m in data["methods"])
    body = (f"<p>Methods measured on the same SfM points and board: {_esc(methods)}; range for the range-based "
            f"baselines from <b>{_esc(data['range_source'])}</b>.</p><ul class='verdict'>{items}</ul>")
    return body, {"verdict": lines, "methods": data["methods"]}


def section_frames(ws, out: Path) -> tuple[str, dict]:
    """Raw, every baseline, ours, oracle and in-air truth on the same frames."""
    try:
        data = eval_tables(ws)
    except NotRun:
        data = None
    if data is not None:
        columns = [*data["methods"], *data.get("reference", [])]
        folders = {m: ws.path(p) if not Path(p).is_absolute() else Path(p) for m, p in data["folders"].items()}
        labels = data["labels"]
        frames = data.get("example_frames") or []
    else:
        survey = ws.stage_dir("survey") / "images"
        if not survey.is_dir():
            raise NotRun(f"not run: no survey images in {ws.relative(survey)} and no evaluation")
        names = sorted(p.name for p in survey.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".tif"))
        columns, folders, labels = ["raw"], {"raw": survey}, {"raw": "raw"}
        frames = [names[i] for i in sorted({0, len(names) // 2, len(names) - 1})] if names else []
    if not frames:
        raise NotRun("no frames to show")
    head = "".join(f"<th>{_esc(labels.get(m, m))}</th>" for m in columns)
    rows = []
    for name in frames:
        cells = []
        for m in columns:
            path = frame_file(folders[m], name)
            cells.append(f"<td>{_img(data_uri(read_display(path)), f'{m} {name}')}</td>" if path.is_file()
                         else "<td class='missing'>missing</td>")
        rows.append(f"<tr><th>{_esc(name)}</th>{''.join(cells)}</tr>")
    note = "" if data is not None else "<p class='missing'>Evaluation not run: only the raw frames are shown.</p>"
    body = (f"{note}<div class='scroll'><table class='grid'><tr><th>frame</th>{head}</tr>{''.join(rows)}</table></div>"
            f"<p class='note'>Frames downscaled to {THUMB_PX} px, in survey order; one of them is the frame with "
            f"the most board patches.</p>")
    return body, {"frames": frames, "columns": columns}


def section_mask(ws, out: Path) -> tuple[str, dict]:
    """The scene mask (the survey's mask.png and camera.json's mask_rects_px, in the workspace's frames) shaded red
    and the overlay SfM proposes to mask (:func:`pipeline.overlay.still_features`) outlined in yellow, over the
    survey's middle frame: a mask or a proposal on the scene is seen at once."""
    import cv2

    from watergan.io import read_scene_mask

    survey, sfm = ws.result("survey"), ws.result("sfm")
    mask = read_scene_mask(ws.path(survey.scene_mask)) if survey is not None and survey.scene_mask else None
    found = sfm.still_features if sfm is not None else {}
    boxes = (found.get("boxes_px") or [found["box_px"]]) if found else []
    if mask is None and not boxes:
        raise NotRun("no scene mask (mask.png, camera.json's mask_rects_px) and no overlay found by SfM")
    images = ws.folder("survey") / "images"
    names = sorted(p.name for p in images.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".tif", ".tiff")
                   ) if images.is_dir() else []
    if not names:
        raise NotRun("no survey frames to draw the mask over")
    name = names[len(names) // 2]
    rgb = read_display(images / name).astype(np.float32)
    if mask is not None and mask.shape == rgb.shape[:2]:
        rgb[~mask] = 0.45 * rgb[~mask] + 0.55 * np.array([255.0, 0.0, 0.0])
    rgb = np.ascontiguousarray(rgb.clip(0, 255).astype(np.uint8))
    for x0, y0, x1, y1 in boxes:
        cv2.rectangle(rgb, (x0, y0), (x1 - 1, y1 - 1), (255, 220, 0), max(1, round(max(rgb.shape[:2]) / 300)))
    masked = 100 * float((~mask).mean()) if mask is not None else 0.0
    note = (f"<p class='note'>{_esc(name)}: red, the pixels the scene mask leaves out ({masked:.1f} % of the frame: "
            f"never corrected, matched or measured)" + (f"; yellow, the overlay SfM proposes to mask "
                                                       f"(mask_rects_px {boxes})" if boxes else "") + ".</p>")
    return (_img(data_uri(rgb, "jpeg", MOSAIC_PX), f"scene mask over {name}", "wide") + note,
            {"frame": name, "masked_pct": round(masked, 2), "overlay_px": boxes})


def section_tables(ws, out: Path) -> tuple[str, dict]:
    from eval.tables import table_html

    data = eval_tables(ws)
    return "".join(table_html(t) for t in data["tables"]), {"tables": [t["id"] for t in data["tables"]]}


def section_board_chart(ws, out: Path) -> tuple[str, dict]:
    data = eval_tables(ws)
    table = next(t for t in data["tables"] if t["id"] == "table1")
    if table["status"] != "ok":
        raise NotRun(table["status"])
    plt = _plt()
    patches = [r for r in table["rows"] if not r["label"].startswith("mean")]
    columns = table["columns"]
    fig, ax = plt.subplots(figsize=(max(8.0, 0.45 * len(patches) * max(1, len(columns)) / 3), 3.8))
    width = 0.8 / len(columns)
    x = np.arange(len(patches))
    cmap = plt.get_cmap("tab10")
    for j, m in enumerate(columns):
        values = [np.nan if r["values"][j] is None else r["values"][j] for r in patches]
        ax.bar(x + (j - (len(columns) - 1) / 2) * width, values, width, label=table["labels"].get(m, m),
               color=cmap(j % 10), edgecolor="black" if m == "ours" else "none", linewidth=0.6)
    ax.set_xticks(x, [r["label"] for r in patches], rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("|n(measured) - n(true)|")
    ax.set_title("Per-patch colour-board error (lower is better)", fontsize=10)
    ax.legend(fontsize=7, ncol=min(5, len(columns)))
    return _img(figure_uri(fig), "per-patch board error", "wide"), {"patches": len(patches)}


def section_consistency(ws, out: Path) -> tuple[str, dict]:
    points = stage_result(ws, "eval").consistency_points
    path = ws.path(points) if points else None
    if path is None or not path.is_file():
        raise NotRun("not run: no consistency_points.npz (run `watergan evaluate --workspace WS`)")
    data = eval_tables(ws)
    with np.load(path) as npz:
        variances = {k: npz[k] for k in npz.files}
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.2), sharey=True)
    positive = np.concatenate([v[v > 0] for v in variances.values()]) if variances else np.array([1e-6])
    lo, hi = np.percentile(positive, [0.5, 99.5]) if positive.size else (1e-8, 1e-2)
    bins = np.geomspace(max(lo, 1e-12), max(hi, lo * 10), 40)
    cmap = plt.get_cmap("tab10")
    order = [m for m in [*data["methods"], *data.get("reference", [])] if m in variances]
    for ch, ax in enumerate(axes):
        for j, m in enumerate(order):
            v = np.clip(variances[m][:, ch], bins[0], bins[-1])
            ax.hist(v, bins=bins, histtype="step", color=cmap(j % 10), linewidth=2.0 if m == "ours" else 1.0,
                    linestyle="--" if m in data.get("reference", []) else "-", label=data["labels"].get(m, m))
        ax.set_xscale("log")
        ax.set_title(f"{'RGB'[ch]} channel", fontsize=9)
        ax.set_xlabel("variance of normalised colour across views")
    axes[0].set_ylabel("SfM points")
    axes[-1].legend(fontsize=7)
    n_points = len(next(iter(variances.values()))) if variances else 0
    note = (f"<p class='note'>Per-point variance of c / (R + G + B) across views, the same {n_points} points "
            f"for every method (Table II holds their means). Lower is more consistent; a constant image scores "
            f"zero, so read this beside the board error.</p>")
    return _img(figure_uri(fig), "consistency histograms", "wide") + note, {"points": n_points}


def section_depth(ws, out: Path) -> tuple[str, dict]:
    from eval.tables import depth_table, table_html
    from pipeline.site_depth import site_depth_metrics

    r = stage_result(ws, "eval")
    if not r.depth:
        raise NotRun("not measured: no restorer depth or no dense depth (the eval stage's depth comparison)")
    folder = ws.path(r.depth)
    site = site_depth_metrics(ws)
    table = depth_table(folder, site)
    if table["status"] != "ok":
        raise NotRun(table["status"])
    rows, n_maps = _error_map_row(folder, "restorer's depth net")
    if site is not None and site.is_file():
        rows += _error_map_row(site.parent, "site depth net (held-out)")[0]
    note = ("<p class='note'>|depth - stereo depth| of each net (the restorer's aligned as the table says, the site "
            "depth net's metric on frames it never trained on) and of the flat seafloor at the navigation's altitude "
            "and attitude, side by side on the same frames; colour map magma from 0 to the 95th percentile of the "
            "net's error; black: no value.</p>")
    return table_html(table) + rows + note, {"error_maps": n_maps}


def _error_map_row(folder: Path, label: str) -> tuple[str, int]:
    """Three frames' error maps of a depth comparison's net (``errors/``) and flat seafloor (``errors_floor/``), as
    a row of figures, and how many maps of the net the folder holds."""
    maps = sorted((folder / "errors").glob("*.png"))
    picks = [maps[i] for i in sorted({0, len(maps) // 2, len(maps) - 1})] if maps else []
    images = ""
    for p in picks:
        floor = folder / "errors_floor" / p.name
        images += f"<figure>{_img(data_uri(read_display(p)), f'{label} error {p.stem}')}" \
                  f"<figcaption>{_esc(p.stem)}: {_esc(label)}</figcaption></figure>"
        if floor.is_file():
            images += f"<figure>{_img(data_uri(read_display(floor)), f'flat seafloor error {p.stem}')}" \
                      f"<figcaption>{_esc(p.stem)}: flat seafloor</figcaption></figure>"
    return f"<div class='row'>{images}</div>", len(maps)


def render_mesh_view(mosaic_rgb: np.ndarray, world: list[float], vertices: np.ndarray, max_px: int = 110,
                     exaggeration: float = 2.0):
    """A perspective view of the orthophoto draped on the mesh's height field (matplotlib 3D).
    ``world``: the world file's (texel, 0, 0, -texel, x of the upper-left texel centre, its y)."""
    import cv2
    import matplotlib.tri as mtri
    from matplotlib.colors import LightSource

    plt = _plt()
    h, w = mosaic_rgb.shape[:2]
    step = max(1, int(np.ceil(max(h, w) / max_px)))
    rows, cols = h // step, w // step
    # block means of the covered texels (black = not covered); block (j, i) is centred on texel
    # ((i + 0.5) step - 0.5, (j + 0.5) step - 0.5)
    covered = (mosaic_rgb.sum(-1) > 0).astype(np.float32)
    area = (cols, rows)
    cover = cv2.resize(covered[:rows * step, :cols * step], area, interpolation=cv2.INTER_AREA)
    total = cv2.resize(mosaic_rgb[:rows * step, :cols * step].astype(np.float32), area, interpolation=cv2.INTER_AREA)
    colours = np.clip(total / np.maximum(cover, 1e-6)[..., None] / 255.0, 0, 1)
    texel, x0, y0 = float(world[0]), float(world[4]), float(world[5])
    centres_i, centres_j = (np.arange(cols) + 0.5) * step - 0.5, (np.arange(rows) + 0.5) * step - 0.5
    xs, ys = x0 + centres_i * texel, y0 - centres_j * texel
    gx, gy = np.meshgrid(xs, ys)
    verts = np.asarray(vertices, float)
    if len(verts) > 60000:
        verts = verts[np.random.default_rng(0).choice(len(verts), 60000, replace=False)]
    _, first = np.unique(verts[:, :2], axis=0, return_index=True)
    verts = verts[np.sort(first)]
    if len(verts) < 3:
        raise NotRun("the mesh has fewer than 3 distinct vertices: nothing to draw")
    # heights linearly interpolated on a Delaunay triangulation of the vertices' x, y (fast point location)
    interp = mtri.LinearTriInterpolator(mtri.Triangulation(verts[:, 0], verts[:, 1]), verts[:, 2])
    z = np.ma.filled(interp(gx, gy).astype(float), np.nan)
    seen = np.isfinite(z) & (cover > 0.5)
    if seen.sum() < 4:
        raise NotRun("the mesh and the mosaic do not overlap: nothing to draw")
    z = np.where(seen, z, np.nan)
    filled = np.where(seen, z, np.nanmedian(z))
    shaded = LightSource(azdeg=315, altdeg=45).shade_rgb(colours, filled * exaggeration, fraction=0.6,
                                                         blend_mode="soft")
    rgba = np.concatenate([shaded, seen[..., None].astype(float)], -1)
    fig = plt.figure(figsize=(10, 6.5))
    fig.subplots_adjust(left=0, right=1, bottom=0, top=1)
    ax = fig.add_subplot(projection="3d")
    ax.plot_surface(gx, gy, np.where(seen, z * exaggeration, np.nan), facecolors=rgba, rstride=1, cstride=1,
                    linewidth=0, antialiased=False, shade=False)
    ax.view_init(elev=38, azim=-65)
    span = max(np.ptp(xs), np.ptp(ys), 1e-6)
    ax.set_box_aspect((np.ptp(xs) / span, np.ptp(ys) / span, 0.3), zoom=1.25)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel(f"z x{exaggeration:g}")
    return fig


def section_mesh(ws, out: Path) -> tuple[str, dict]:
    import trimesh

    r = stage_result(ws, "mesh")
    mosaic = read_display(ws.path(r.mosaic_png))
    world = [float(v) for v in ws.path(r.world_file).read_text().split()]
    mesh = trimesh.load(ws.path(r.ply), process=False, force="mesh")
    fig = render_mesh_view(mosaic, world, np.asarray(mesh.vertices))
    links = " · ".join(_link(ws, out, getattr(r, k), text) for k, text in (
        ("glb", "textured mesh (GLB)"), ("obj", "OBJ"), ("ply", "PLY with vertex colours")))
    body = (f"<p>{links} — {r.n_vertices} vertices, {r.n_faces} faces ({_esc(r.mesh_kind)}), "
            f"{1000 * r.texel_m:.1f} mm per texel.</p>{_img(figure_uri(fig), 'rendered mesh view', 'wide')}"
            f"<p class='note'>The orthophoto draped on the mesh's height field (heights interpolated from the "
            f"mesh vertices), hill-shaded, vertical exaggeration x2; open the GLB in any glTF viewer for the "
            f"textured mesh itself.</p>")
    return body, {"glb": r.glb, "n_faces": r.n_faces}


def section_mosaic(ws, out: Path) -> tuple[str, dict]:
    r = stage_result(ws, "mesh")
    mosaic = read_display(ws.path(r.mosaic_png))
    body = (f"<p>{_link(ws, out, r.mosaic_png, 'full-size mosaic (PNG)')} · "
            f"{_link(ws, out, r.world_file, 'world file')}"
            + (f" · {_link(ws, out, r.mosaic_tif, 'GeoTIFF')} · {_link(ws, out, r.dem_tif, 'DEM (GeoTIFF)')}"
               if r.mosaic_tif else "")
            + f" — {mosaic.shape[1]} x {mosaic.shape[0]} texels, "
            f"{1000 * r.texel_m:.1f} mm per texel, {100 * r.mosaic_coverage:.1f} % covered"
            + (f"; in {r.crs} (rotation {r.georef_rotation_deg:+.2f} deg, scale {r.georef_scale:.4f}, RMS "
               f"{r.georef_rms_m:.3f} m)" if getattr(r, "crs", "") else "") + ".</p>"
            f"{_img(data_uri(mosaic, 'jpeg', MOSAIC_PX), 'mosaic', 'wide')}")
    return body, {"mosaic_png": r.mosaic_png, "coverage": r.mosaic_coverage}


def alternatives_table(record: WaterRecord) -> str:
    """HTML: each alternative the intervals took in, in its own words, with its held-out test and the parameters
    whose interval it widened."""
    rows = []
    for a in record.alternatives:
        test = ("" if a.heldout_change_pct is None else
                f"{a.heldout_change_pct:+.1f} % [{a.ci95_pct[0]:+.1f}, {a.ci95_pct[1]:+.1f}]"
                + (" preferred" if a.preferred else " rejected" if a.rejected else ""))
        moved = [key for key, p in record.params.items()
                 if (w := p.widening(a.key)) is not None and any(np.ravel(w.widened))]
        rows.append(f"<tr><th>{_esc(a.words)}</th><td>{_esc(test)}</td><td>{_esc(', '.join(moved) or '-')}</td>"
                    f"<td>{a.seconds:.0f} s</td></tr>")
    if not rows:
        return ""
    return ("<h3>Alternatives the intervals take in</h3><table><tr><th>alternative</th><th>held-out change (95 %)"
            "</th><th>widened</th><th>time</th></tr>" + "".join(rows) + "</table>")


def section_water(ws: Workspace, out: Path) -> tuple[str, dict]:
    """The site water the water stage estimated: its summary line, each parameter with its 95 % interval,
    the plots water.json names; and where each pixel's range came from (the range stage)."""
    r = stage_result(ws, "water")
    water = read_water(ws.path(r.water_json))
    from watergan.formation import builtin_effects

    nuisance = {name for name, cls in builtin_effects().items() if cls.nuisance}
    rows = "".join(f"<tr><th>{_esc(key)}</th><td>{_esc(p.value)}</td>"
                   f"<td>{_esc([p.low, p.high] if p.low is not None else 'held')}</td>"
                   f"<td>{_esc(p.units)}</td></tr>" for key, p in water.params.items()
                   if key.split(".")[0] not in nuisance)
    plots = ((ws.path(r.water_json).parent / name, alt) for name, alt in water.plots.items())
    figure = "".join(_img(data_uri(read_display(plot), "png", None), alt, "wide") for plot, alt in plots
                     if plot.is_file())
    warn = (f"<p class='error'>At a bound of their range: {_esc(', '.join(r.at_bounds))}. The stack does not fit "
            f"this survey there (an effect is missing or has another form): read the residuals and the "
            f"diagnosis.</p>" if r.at_bounds else "")
    ranges = ws.result("range")
    ranged = (f"Each pixel's range: from the dense stage, from the fused mesh for {100 * ranges.mesh_fraction:.1f} % "
              f"of the pixels; {100 * ranges.range_missing:.1f} % had none (the physics correction ranges them from "
              f"their neighbours or at the survey's far range)." if ranges is not None else "")
    body = (f"<p>{_esc(r.summary)}</p>{warn}<table><tr><th>parameter</th><th>estimate</th><th>95 % interval</th>"
            f"<th>units</th></tr>{rows}</table>{alternatives_table(water)}<p class='note'>"
            f"{'A colour board pinned the gain. ' if r.board else ''}{ranged}</p>{figure}")
    return body, {"summary": r.summary}


def section_diagnosis(ws, out: Path) -> tuple[str, dict]:
    diagnosed = stage_result(ws, "diagnose")
    folder = Path(diagnosed.out_dir)
    ledger = ws.path(diagnosed.ledger)
    if not ledger.is_file() and not (folder / "ledger.png").is_file():
        raise NotRun("not run: no model ledger (run `watergan diagnose WS`)")
    parts, info = [], {}
    if ledger.is_file():
        from eval.ledger import ledger_table, plot_ledger, read_ledger

        records = read_ledger(ledger)
        plot = out / "ledger.png"
        plot_ledger(records, plot)
        parts.append(_img(data_uri(read_display(plot), "png", None), "model ledger", "wide"))
        parts.append(f"<pre>{_esc(ledger_table(records))}</pre>")
        info["ledger_entries"] = len(records)
    else:
        parts.append(_img(data_uri(read_display(folder / "ledger.png"), "png", None), "model ledger", "wide"))
    verdict = folder / "verdict.txt"
    if verdict.is_file():
        parts.insert(0, f"<p class='verdict'><b>Diagnosis:</b> {_esc(verdict.read_text().strip())}</p>")
        info["verdict"] = verdict.read_text().strip()
    if diagnosed.measurements:
        parts.insert(1 if verdict.is_file() else 0, f"<p class='note'>Measurements: {_esc(diagnosed.measurements)}</p>")
        info["measurements"] = diagnosed.measurements
    return "".join(parts), info


def objects_html(table: dict) -> str:
    """The HTML table of :func:`eval.objects.spread_table`: per object, each method's chromaticity spread and (in
    brackets) its ratio to raw's, and the median over objects."""
    methods = table["methods"]
    head = "".join(f"<th>{_esc(m)}</th>" for m in methods)

    def cell(row: dict, m: str) -> str:
        value = row["spread"].get(m)
        ratio = row["over_raw"].get(m)
        return "<td>–</td>" if value is None else \
            f"<td>{value:.4f}" + ("" if m == "raw" or ratio is None else f" ({ratio:.2f}x)") + "</td>"

    body = ""
    for row in table["rows"]:
        span = "–" if row["range_m"] is None else f"{row['range_m'][0]:.2f}–{row['range_m'][1]:.2f}"
        body += (f"<tr><th>{_esc(row['name'])}</th><td>{_esc(row['kind'])}</td><td>{row['frames']}</td>"
                 f"<td>{span}</td>{''.join(cell(row, m) for m in methods)}</tr>")
    median = "".join("<td>–</td>" if table["median"][m] is None else f"<td>{table['median'][m]:.4f}</td>"
                     for m in methods)
    return (f"<table><tr><th>object</th><th>kind</th><th>frames</th><th>range (m)</th>{head}</tr>{body}"
            f"<tr><th>median over objects</th><td></td><td></td><td></td>{median}</tr></table>")


def section_objects(ws, out: Path) -> tuple[str, dict]:
    """The survey folder's labelled objects (``objects.json``, :mod:`eval.objects`): per object the chromaticity
    spread across its frames in the raw, physics and restorer frames, and their chromaticity against range."""
    from eval.objects import (
        LazyFrames,
        chromaticity_figure,
        load_object_labels,
        measure_objects,
        object_pixels,
        range_frames,
        spread_table,
        undistortion_warp,
    )
    from watergan.io import read_image
    from watergan.survey_files import image_files

    survey = stage_result(ws, "survey")
    labels_path = Path(survey.survey_dir) / "objects.json"
    if not labels_path.is_file():
        raise NotRun("not run: the survey folder holds no objects.json (objects of one colour labelled in its "
                     "frames, docs/evaluation.md)")
    images = ws.stage_dir("survey") / "images"
    names = image_files(images)
    labels = load_object_labels(labels_path, names)
    folders = {"raw": images}
    correct = ws.result("correct")
    if correct is not None:
        folders.update({m: ws.path(f) for m, f in (("physics", correct.physics_images), ("restorer", correct.images))
                        if f})
    folders = {m: f for m, f in folders.items() if f.is_dir()}
    ranges = ws.result("range")
    range_maps = range_frames(ws.path(ranges.range_dir), names) if ranges is not None else None
    camera = ws.folder("survey") / "camera.json"
    warp = undistortion_warp(json.loads(camera.read_text())) if camera.is_file() else None
    per_method: dict[str, dict] = {}
    pixels: dict[tuple, dict] = {}
    for method, folder in folders.items():
        frames = LazyFrames(names, lambda name, folder=folder: read_image(frame_file(folder, name)))
        shape = frames[names[0]].shape[:2]  # a folder's frames share one size
        if shape not in pixels:
            pixels[shape] = object_pixels(labels, shape, names, warp)
        per_method[method] = measure_objects(frames, labels, pixels[shape], range_maps)["objects"]
    table = spread_table(per_method)
    figure = out / "objects.png"
    chromaticity_figure(per_method, figure, note=labels.notice)
    note = ("<p class='note'>Each labelled object's chromaticity c = RGB / (R + G + B) of its mean linear colour per "
            "frame; spread: the sum over channels of max - min across its frames (0: its colour kept at every "
            "range; a method that greys every image also scores 0, so read it beside the board and the tables). "
            "Range: the range stage's maps. In brackets: over raw's.</p>")
    body = objects_html(table) + note + _img(data_uri(read_display(figure), "png", None), "objects' chromaticity "
                                                                                          "against range", "wide")
    return body, {"objects": len(table["rows"]), "median_spread": table["median"]}


def section_config(ws, out: Path) -> tuple[str, dict]:
    rows, details, stages = [], [], {}
    for stage, spec in ws.stages.items():
        folder = spec.folder
        if stage == "report":
            continue
        config = load_json(ws.root / folder / "config.json")
        record = load_json(ws.root / folder / "result.json")
        result = (record or {}).get("result", record) or {}
        seconds = result.get("seconds") if isinstance(result, dict) else None
        status = "done" if record is not None else "present" if (ws.root / folder).is_dir() else "not run"
        stages[stage] = {"folder": folder, "status": status, "seconds": seconds}
        secs = "-" if seconds is None else f"{seconds:.1f}"
        rows.append(f"<tr><th>{_esc(folder)}</th><td>{status}</td><td>{secs}</td></tr>")
        if config is not None or record is not None:
            text = json.dumps({"config": (config or {}).get("config"), "result": result}, indent=1)
            if len(text) > 6000:
                text = text[:6000] + "\n... (truncated)"
            details.append(f"<details><summary>{_esc(folder)}</summary><pre>{_esc(text)}</pre></details>")
    body = (f"<table><tr><th>stage</th><th>status</th><th>seconds</th></tr>{''.join(rows)}</table>"
            f"{''.join(details)}")
    return body, {"stages": stages}


SECTIONS = (
    ("found", "What this run found", section_found),
    ("verdict", "Verdict", section_verdict),
    ("frames", "The same frames, every method", section_frames),
    ("mask", "The scene mask over a frame", section_mask),
    ("tables", "Tables", section_tables),
    ("board", "Colour-board error per patch", section_board_chart),
    ("consistency", "Consistency across views", section_consistency),
    ("depth", "Depth: monocular vs stereo", section_depth),
    ("objects", "Objects of one colour", section_objects),
    ("water", "The site's water", section_water),
    ("mesh", "Textured mesh", section_mesh),
    ("mosaic", "Mosaic", section_mosaic),
    ("diagnosis", "Diagnosis: where the model is wrong", section_diagnosis),
    ("config", "Configuration and timings", section_config),
)

STYLE = """
body { font-family: sans-serif; margin: 1.5em auto; max-width: 1400px; padding: 0 1em; color: #222; }
h1 { font-size: 1.6em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: .2em; margin-top: 1.6em; }
table { border-collapse: collapse; margin: .5em 0; font-size: .85em; }
th, td { border: 1px solid #ddd; padding: .25em .5em; text-align: right; }
th { background: #f4f4f4; text-align: left; }
table.grid td { padding: 2px; } table.grid img { display: block; width: 200px; }
.scroll { overflow-x: auto; } img.wide { max-width: 100%; }
.missing { color: #888; font-style: italic; } .error { color: #a00; }
.note { color: #555; font-size: .85em; } li.lose { color: #a00; }
.row { display: flex; gap: 1em; flex-wrap: wrap; } figure { margin: 0; } figcaption { font-size: .8em; }
pre { background: #f7f7f7; padding: .6em; overflow-x: auto; font-size: .8em; }
"""


@dataclass(frozen=True)
class ReportConfig:
    """The report stage has no options: it shows what the workspace holds."""


@dataclass
class ReportResult:
    report: str
    """Workspace-relative path of report.html (report.json and report.md beside it)."""


def run_report(ws: Workspace, cfg: ReportConfig) -> ReportResult:
    """Workspace stage: the report of everything the workspace holds."""
    return ReportResult(report=ws.relative(write_report(ws)))


def write_report(ws: Workspace | str | Path) -> Path:
    """Write ``report.html``, ``report.json`` and ``report.md`` into the report stage's folder of a
    workspace; returns the HTML path."""
    if not isinstance(ws, Workspace):
        root = Path(ws)
        if not root.is_dir():
            raise UserInputError(f"workspace {root} does not exist")
        ws = Workspace(root)
    out = ws.stage_dir("report")
    parts, summary = [], []
    for key, title, fn in SECTIONS:
        try:
            body, info = fn(ws, out)
            status = "ok"
        except NotRun as exc:
            body, info, status = f"<p class='missing'>{_esc(exc)}</p>", {}, "not run"
            info["reason"] = str(exc)
        except Exception as exc:  # a broken input must not take the whole report down: say so in the page
            body, info, status = (f"<p class='error'>could not be shown: {_esc(type(exc).__name__)}: "
                                  f"{_esc(exc)}</p>"), {"error": f"{type(exc).__name__}: {exc}"}, "error"
        parts.append(f"<section id='{key}'><h2>{_esc(title)}</h2>{body}</section>")
        summary.append({"id": key, "title": title, "status": status, **info})
    generated = time.strftime("%Y-%m-%d %H:%M:%S")
    toc = " · ".join(f"<a href='#{k}'>{_esc(t)}</a>" for k, t, _ in SECTIONS)
    page = (f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'><title>watergan report: "
            f"{_esc(ws.root.name)}</title><style>{STYLE}</style></head><body>"
            f"<h1>watergan report — {_esc(ws.root.resolve())}</h1><p class='note'>generated {generated}</p>"
            f"<p>{toc}</p>{''.join(parts)}</body></html>\n")
    html_path = out / "report.html"
    atomic_write_text(html_path, page)
    try:
        tables = eval_tables(ws)
    except NotRun:
        tables = None
    atomic_write_json(out / "report.json", {"workspace": str(ws.root.resolve()), "generated": generated,
                                            "sections": summary, "tables": (tables or {}).get("tables", []),
                                            "verdict": (tables or {}).get("verdict", [])})
    atomic_write_text(out / "report.md", report_markdown(ws, summary, tables))
    return html_path


def report_markdown(ws, summary: list[dict], tables: dict | None) -> str:
    """The report's text as Markdown (no figures): verdict, tables and what each section shows."""
    from eval.tables import table_markdown

    lines = [f"# watergan report — {ws.root.resolve()}", "", "## Verdict", ""]
    lines += [f"- {line}" for line in (tables or {}).get("verdict", [])] or ["not run: no evaluation tables"]
    lines += ["", "## Tables", ""] + [table_markdown(t) for t in (tables or {}).get("tables", [])]
    lines += ["## Sections of report.html", ""]
    lines += [f"- {s['title']}: {s['status']}" + (f" ({s.get('reason') or s.get('error')})" if s["status"] != "ok"
                                                   else "") for s in summary]
    return "\n".join(lines) + "\n"
