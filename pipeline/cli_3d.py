"""The 3D subcommands of the `watergan` console script (wired in by pipeline.cli); options from
:class:`pipeline.sfm.SfmConfig`, :class:`pipeline.dense.DenseConfig`, :class:`pipeline.range.RangeConfig`,
:class:`pipeline.water.WaterStage`, :class:`pipeline.mesh.MeshConfig`,
:class:`eval.colour.ColourEvalConfig` and :class:`eval.depth.DepthCompareConfig` (see ``--help``):

    watergan sfm --workspace WS [--survey DIR] [--matching auto|sequential|exhaustive]
                 [--scale auto|stereo|board|altitude|none] [--board-json FILE [--board-width-m W ...]]
    watergan dense --workspace WS [--method auto|sgbm|patch_match] [--pairs auto|rig|neighbours] [--no-fuse]
    watergan range --workspace WS [--agreement 0.01] [--normal-smooth-px 24]
    watergan water --workspace WS [--effects A,B] [--board-json FILE] [--bootstrap N]
    watergan consistency --workspace WS --out DIR --folders NAME=DIR[,NAME=DIR] [--patch-px 5]
                         [--truth-dir SURVEY | --board-json FILE]
    watergan depth-compare --pred-dir DIR [--ref-dir DIR | --workspace WS] --out DIR [--with-shift] [--no-per-image]
    watergan texture --workspace WS [--images-dir DIR] [--source auto|dense|sparse] [--mesh-kind auto|2.5d|tsdf]
    watergan mosaic --workspace WS [--images-dir DIR] [--texel-m M]

sfm, dense, range, water, texture and mosaic are workspace stages (:func:`pipeline.cli_stage.add_stage_command`:
skipped when done with the same options and upstream results, unless --force; ``--survey DIR``
links a survey first); consistency and depth-compare measure any folders on a workspace's tracks
and dense depth and write into ``--out`` (the workspace's own consistency and depth comparison are
the eval stage's, in its folder).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .cli_stage import add_stage_command
from .cliargs import add_config, config_from_args


def print_sfm(ws, r) -> None:
    print(r.summary())
    print(f"model:  {ws.path(r.model_dir)}\ntracks: {ws.path(r.tracks)}")


def print_dense(ws, r) -> None:
    print(f"dense: {len(r.pairs)} depth maps, mean coverage {100 * r.mean_coverage:.1f} %, "
          f"{len(r.skipped)} skipped, {r.n_fused_points} fused points, {r.seconds:.1f} s")
    print(f"depth: {ws.path(r.depth_dir)}")
    if r.mesh_ply:
        print(f"fused: {ws.path(r.points_ply)}, {ws.path(r.mesh_ply)}")


def print_range(ws, r) -> None:
    print(f"range: {r.n_frames} range maps, from the fused mesh for {100 * r.mesh_fraction:.1f} % of the pixels, "
          f"none for {100 * r.range_missing:.1f} %; {r.seconds:.1f} s")
    print(f"range:  {ws.path(r.range_dir)}")


def print_water(ws, r) -> None:
    print(r.summary)
    print(f"{'board' if r.board else 'no board (gain held)'}; estimate {r.estimate_seconds:.1f} s, all "
          f"{r.seconds:.1f} s")
    if r.at_bounds:
        print("at a bound (the stack does not fit there; see the residuals and the diagnosis): "
              + ", ".join(r.at_bounds))
    print(f"water:  {ws.path(r.water_json)}")


def cmd_consistency(args: argparse.Namespace) -> int:
    from eval.colour import ColourEvalConfig
    from pipeline.evaluate import run_colour_eval
    from pipeline.workspace import Workspace

    ws = Workspace(args.workspace)
    r = run_colour_eval(ws, config_from_args(ColourEvalConfig, args), Path(args.out))
    c = r.consistency
    print(f"consistency on {c.n_points} points ({c.n_observations} observations, {c.patch_px}x{c.patch_px} "
          f"patches, >= {c.min_views} views, {'linear' if c.linear else 'encoded'} RGB): "
          f"mean variance of c/(R+G+B) across views")
    for name, score in c.scores.items():
        board = r.board.get(name)
        extra = (f"   board: distance {board.mean_distance:.4f}, CIEDE2000 {board.mean_ciede2000:.2f}"
                 if board else "")
        print(f"  {name:>12}: {score.mean_variance:.3e}  (R {score.variance[0]:.2e} G {score.variance[1]:.2e} "
              f"B {score.variance[2]:.2e}){extra}")
    print(f"table: {r.table}")
    return 0


def cmd_depth_compare(args: argparse.Namespace) -> int:
    from eval.depth import DepthCompareConfig
    from pipeline.evaluate import run_depth_compare
    from pipeline.workspace import Workspace

    cfg = config_from_args(DepthCompareConfig, args)
    r = run_depth_compare(Workspace(args.workspace) if args.workspace else None, cfg, Path(args.out))
    o = r.overall
    print(f"depth ({r.alignment}): {len(r.per_image)} images, RMSE {o.rmse_m:.4f} m "
          f"({100 * o.rmse_over_range:.2f} % of range), AbsRel {o.abs_rel:.4f}, delta<1.25 {o.delta_125:.3f}, "
          f"coverage {100 * o.coverage:.1f} %; {len(r.skipped)} skipped")
    for name, m in r.sources.items():
        relief = f", relief pixels {m.relief.rmse_m:.4f} m" if m.relief is not None else ""
        print(f"  {name} ({m.alignment}): RMSE {m.all.rmse_m:.4f} m{relief}")
    if r.ratio_to:
        print(f"the net's RMSE on relief pixels ({100 * r.relief_fraction:.0f} % of the pixels) is "
              f"{r.relief_rmse_ratio:.2f}x that of the {r.ratio_to}, {r.all_rmse_ratio:.2f}x over all pixels")
    print(f"table: {r.table}")
    return 0


def print_texture(ws, r) -> None:
    print(f"mesh ({r.mesh_kind}): {r.n_vertices} vertices, {r.n_faces} faces, "
          f"texture {1000 * r.texel_m:.1f} mm/texel, {r.seconds:.1f} s")
    for key in ("glb", "obj", "ply"):
        print(f"{key}: {ws.path(getattr(r, key))}")


def print_mosaic(ws, r) -> None:
    print(f"mosaic: {1000 * r.texel_m:.1f} mm per pixel, {100 * r.mosaic_coverage:.1f} % covered")
    print(f"png: {ws.path(r.mosaic_png)}\nworld file: {ws.path(r.world_file)}")
    if r.mosaic_tif:
        print(f"GeoTIFF: {ws.path(r.mosaic_tif)}\nDEM: {ws.path(r.dem_tif)}")
    print(georeference_line(r))


def georeference_line(r) -> str:
    """Where the mesh stage's mosaic and DEM are placed: the CRS and the fit, or the local frame; and any warning."""
    line = (f"georeferenced in {r.crs}: rotation {r.georef_rotation_deg:+.2f} deg, scale {r.georef_scale:.4f}, "
            f"RMS residual {r.georef_rms_m:.3f} m over {r.georef_frames} frames" if getattr(r, "crs", "")
            else "frame: the survey's local metric frame (no crs in survey.json)")
    return line + (f"\nwarning: {r.georef_warning}" if getattr(r, "georef_warning", "") else "")


def add_commands(sub, parents: list[argparse.ArgumentParser]) -> None:
    """Add the 3D subcommands to an argparse subparsers object; each sets ``func``."""
    from eval.colour import ColourEvalConfig
    from eval.depth import DepthCompareConfig

    add_stage_command(sub, parents, "sfm", print_sfm)
    add_stage_command(sub, parents, "dense", print_dense)
    add_stage_command(sub, parents, "range", print_range)
    add_stage_command(sub, parents, "water", print_water)

    p = sub.add_parser("consistency", parents=parents, help="colour consistency across views (+ board accuracy)")
    p.add_argument("--workspace", required=True, help="workspace with a finished sfm stage (its tracks)")
    p.add_argument("--out", required=True, help="output folder (colour.json)")
    add_config(p, ColourEvalConfig)
    p.set_defaults(func=cmd_consistency)

    p = sub.add_parser("depth-compare", parents=parents, help="monocular depth vs stereo/MVS depth")
    p.add_argument("--workspace", help="workspace whose dense depth maps are the reference (without --ref-dir)")
    p.add_argument("--out", required=True, help="output folder (metrics.json, errors/)")
    add_config(p, DepthCompareConfig)
    p.set_defaults(func=cmd_depth_compare)

    add_stage_command(sub, parents, "mesh", print_texture, help_text="mesh (2.5D or TSDF) textured from the images "
                      "(GLB, OBJ, PLY)")
    add_stage_command(sub, parents, "mesh", print_mosaic, "mosaic", "orthophoto mosaic PNG with a world file")
