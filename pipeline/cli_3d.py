"""The 3D subcommands of the `watergan` console script (wired in by pipeline.cli):

    watergan sfm --workspace WS [--images DIR] [--matching auto|sequential|exhaustive]
                 [--scale auto|stereo|board|altitude|none] [--board FILE [--board-width-m W --board-height-m H]]
    watergan dense --workspace WS [--images DIR] [--method auto|sgbm|patch_match] [--pairs auto|rig|neighbours]
                   [--no-fuse]
    watergan consistency --workspace WS --folder NAME=DIR [--folder ...] [--patch-px 5] [--truth SURVEY | --board FILE]
    watergan depth-compare --pred DIR [--ref DIR] (--workspace WS | --out DIR) [--with-shift] [--global-alignment]
    watergan texture --workspace WS [--images DIR] [--source auto|dense|sparse] [--mesh-kind auto|2.5d|tsdf]
    watergan mosaic --workspace WS [--images DIR] [--texel-m M]

sfm, dense, texture and mosaic are workspace stages (skipped when done with the same options,
unless --force); consistency and depth-compare are measurements written to ``06_eval``.
"""

from __future__ import annotations

import argparse

from .cliargs import scheduler_parent


def _workspace(args: argparse.Namespace):
    from pipeline.workspace import Workspace

    return Workspace(args.workspace)


def cmd_sfm(args: argparse.Namespace) -> int:
    from pipeline.sfm import SfmConfig, run_sfm

    cfg = SfmConfig(images_dir=args.images or "", matching=args.matching, sequential_overlap=args.sequential_overlap,
                    scale=args.scale, board_json=args.board or "", board_width_m=args.board_width_m,
                    board_height_m=args.board_height_m, fix_intrinsics=not args.refine_intrinsics,
                    init_min_tri_angle_deg=args.init_min_tri_angle_deg, seed=args.seed)
    ws = _workspace(args)
    r = ws.run("sfm", cfg, run_sfm, force=args.force)["result"]
    print(f"sfm: registered {r['n_registered']} of {r['n_images']} images, {r['n_points']} points "
          f"(mean track {r['mean_track_length']:.1f}, reprojection {r['mean_reprojection_error_px']:.2f} px), "
          f"{r['matching']} matching, scale from {r['scale_method']} (x{r['scale_factor']:.4g}, "
          f"spread {100 * r['scale_spread']:.1f} %), {r['seconds']:.1f} s")
    print(f"model:  {ws.path(r['model_dir'])}\ntracks: {ws.path(r['tracks'])}")
    return 0


def cmd_dense(args: argparse.Namespace) -> int:
    from pipeline.dense import DenseConfig, run_dense

    cfg = DenseConfig(images_dir=args.images or "", method=args.method, pairs=args.pairs, fuse=not args.no_fuse,
                      scheduler=args.scheduler)
    ws = _workspace(args)
    r = ws.run("dense", cfg, run_dense, force=args.force)["result"]
    print(f"dense: {len(r['pairs'])} depth maps, mean coverage {100 * r['mean_coverage']:.1f} %, "
          f"{len(r['skipped'])} skipped, {r['n_fused_points']} fused points, {r['seconds']:.1f} s")
    print(f"depth: {ws.path(r['depth_dir'])}")
    if r["mesh_ply"]:
        print(f"fused: {ws.path(r['points_ply'])}, {ws.path(r['mesh_ply'])}")
    return 0


def cmd_consistency(args: argparse.Namespace) -> int:
    from eval.colour import ColourEvalConfig, run_colour_eval

    cfg = ColourEvalConfig(folders=tuple(args.folder), patch_px=args.patch_px, min_views=args.min_views,
                           linear=not args.encoded, board_json=args.board or "", truth_dir=args.truth or "",
                           scheduler=args.scheduler)
    ws = _workspace(args)
    r = run_colour_eval(ws, cfg)
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
    print(f"table: {ws.path(r.table)}")
    return 0


def cmd_depth_compare(args: argparse.Namespace) -> int:
    from eval.depth import DepthCompareConfig, compare_depth_folders, run_depth_compare
    from watergan.errors import UserInputError

    cfg = DepthCompareConfig(pred_dir=args.pred, ref_dir=args.ref or "", with_shift=args.with_shift,
                             per_image=not args.global_alignment)
    if args.workspace:
        r = run_depth_compare(_workspace(args), cfg)
    elif args.out and args.ref:
        r = compare_depth_folders(args.pred, args.ref, args.out, cfg)
    else:
        raise UserInputError("give --workspace WS, or --ref DIR and --out DIR")
    o = r.overall
    print(f"depth ({r.alignment}): {len(r.per_image)} images, RMSE {o.rmse_m:.4f} m "
          f"({100 * o.rmse_over_range:.2f} % of range), AbsRel {o.abs_rel:.4f}, delta<1.25 {o.delta_125:.3f}, "
          f"coverage {100 * o.coverage:.1f} %; {len(r.skipped)} skipped")
    print(f"table: {r.table}")
    return 0


def _mesh(args: argparse.Namespace) -> tuple[object, dict]:
    from pipeline.mesh import MeshConfig, run_mesh

    cfg = MeshConfig(images_dir=args.images or "", source=args.source, texel_m=args.texel_m, mesh_kind=args.mesh_kind)
    ws = _workspace(args)
    return ws, ws.run("mesh", cfg, run_mesh, force=args.force)["result"]


def cmd_texture(args: argparse.Namespace) -> int:
    ws, r = _mesh(args)
    kind = r.get("mesh_kind", "2.5d")
    print(f"mesh ({kind}): {r['n_vertices']} vertices, {r['n_faces']} faces, "
          f"texture {1000 * r['texel_m']:.1f} mm/texel, {r['seconds']:.1f} s")
    for key in ("glb", "obj", "ply"):
        print(f"{key}: {ws.path(r[key])}")
    return 0


def cmd_mosaic(args: argparse.Namespace) -> int:
    ws, r = _mesh(args)
    print(f"mosaic: {1000 * r['texel_m']:.1f} mm per pixel, {100 * r['mosaic_coverage']:.1f} % covered")
    print(f"png: {ws.path(r['mosaic_png'])}\nworld file: {ws.path(r['world_file'])}")
    return 0


def add_commands(sub, parents: list[argparse.ArgumentParser]) -> None:
    """Add the 3D subcommands to an argparse subparsers object; each sets ``func``."""
    ws = argparse.ArgumentParser(add_help=False)
    ws.add_argument("--workspace", required=True, help="workspace folder (its 00_survey/images are the default input)")
    ws.add_argument("--force", action="store_true", help="redo the stage even when done with the same options")
    images = argparse.ArgumentParser(add_help=False)
    images.add_argument("--images", help="image folder (default: the workspace's 00_survey/images)")

    p = sub.add_parser("sfm", parents=[*parents, ws, images], help="structure from motion (pycolmap) on the raw images")
    p.add_argument("--matching", choices=["auto", "sequential", "exhaustive"], default="auto",
                   help="auto: exhaustive up to 40 images, else sequential with quadratic overlap")
    p.add_argument("--sequential-overlap", type=int, default=10, help="neighbours matched per image (sequential)")
    p.add_argument("--scale", choices=["auto", "stereo", "board", "altitude", "none"], default="auto",
                   help="metric scale source (auto: stereo rig, else board (with --board), else navigation "
                        "altitude, else none)")
    p.add_argument("--board", help="board JSON: per image the pixel corners of the board (4 outer corners, or 4 "
                                   "per colour patch) and its true size (width_m/height_m or patch_side_m)")
    p.add_argument("--board-width-m", type=float, default=0.0, help="true board (patch) width, overrides the file")
    p.add_argument("--board-height-m", type=float, default=0.0, help="true board (patch) height, overrides the file")
    p.add_argument("--refine-intrinsics", action="store_true",
                   help="refine camera.json intrinsics in bundle adjustment")
    p.add_argument("--init-min-tri-angle-deg", type=float, default=8.0,
                   help="initial pair's minimum triangulation angle")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_sfm)

    p = sub.add_parser("dense", parents=[*parents, ws, images, scheduler_parent()],
                       help="SGBM/patch-match depth maps and TSDF fusion")
    p.add_argument("--method", choices=["auto", "sgbm", "patch_match"], default="auto",
                   help="auto: pycolmap patch-match when it was built with CUDA, else OpenCV SGBM")
    p.add_argument("--pairs", choices=["auto", "rig", "neighbours"], default="auto",
                   help="stereo rig pairs or SfM neighbours (auto: rig when right/ exists)")
    p.add_argument("--no-fuse", action="store_true", help="depth maps only, no fused cloud/mesh")
    p.set_defaults(func=cmd_dense)

    p = sub.add_parser("consistency", parents=[*parents, scheduler_parent()],
                       help="colour consistency across views (+ board accuracy)")
    p.add_argument("--workspace", required=True, help="workspace with a finished sfm stage")
    p.add_argument("--folder", action="append", required=True, metavar="NAME=DIR",
                   help="image folder to measure (repeatable), same file names as the SfM images")
    p.add_argument("--patch-px", type=int, default=5, help="side of the averaged patch, pixels (odd)")
    p.add_argument("--min-views", type=int, default=3, help="points seen in fewer views are left out")
    p.add_argument("--encoded", action="store_true", help="measure sRGB-encoded values instead of linear RGB")
    board = p.add_mutually_exclusive_group()
    board.add_argument("--truth", help="simulated survey folder: board corners projected with its true poses")
    board.add_argument("--board", help="board JSON with per-image pixel corners and true colours")
    p.set_defaults(func=cmd_consistency)

    p = sub.add_parser("depth-compare", parents=[*parents], help="monocular depth vs stereo/MVS depth")
    p.add_argument("--pred", required=True, help="folder of predicted depth maps (.png mm or .npy m)")
    p.add_argument("--ref", help="folder of reference depth maps (default: the workspace's 05_dense/depth)")
    p.add_argument("--workspace", help="workspace (results in 06_eval/depth)")
    p.add_argument("--out", help="output folder when no workspace is given")
    p.add_argument("--with-shift", action="store_true", help="fit scale and shift (default: scale only)")
    p.add_argument("--global-alignment", action="store_true", help="one alignment for all images (default: per image)")
    p.set_defaults(func=cmd_depth_compare)

    for name, func, text in (("texture", cmd_texture, "mesh (2.5D or TSDF) textured from the images (GLB, OBJ, PLY)"),
                             ("mosaic", cmd_mosaic, "orthophoto mosaic PNG with a world file")):
        p = sub.add_parser(name, parents=[*parents, ws, images], help=text)
        p.add_argument("--source", choices=["auto", "dense", "sparse"], default="auto",
                       help="points to mesh (auto: dense fused points when present)")
        p.add_argument("--texel-m", type=float, default=0.0, help="metres per texel (0: automatic)")
        p.add_argument("--mesh-kind", choices=["auto", "2.5d", "tsdf"], default="auto",
                       help="2.5d height field (planar UVs) or the dense stage's TSDF mesh (xatlas UVs); "
                            "auto: tsdf when the points are not a height field")
        p.set_defaults(func=func)

