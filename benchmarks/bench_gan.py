"""WaterGAN on the simulated demo survey: training speed and how well the water is learned.

    .venv/bin/python benchmarks/bench_gan.py [--survey DIR] [--out DIR] [--budget-min 5] [--iterations N]
                                             [--rgbd-dir DIR] [--site-water WATER_JSON --site-water-mode held|prior]

Simulates the demo preset with no hidden effect (unless ``--survey`` already holds one), trains on
``SURVEY/rgbd`` (in-air RGB-D; ``--rgbd-dir`` for another set, e.g. a generic one) against ``SURVEY/images``
(the underwater frames), starting from the water stage's estimate with ``--site-water``, then:

- attenuation: learned eta_c vs the truth (``truth/effects.json`` "full"): channel ordering and
  relative error per channel (target: same ordering, each within 50 %);
- colour: per-channel mean and std of full-resolution images generated from the survey's own
  in-air frames and depth (``truth/inair_linear``, ``truth/depth``) vs the real underwater frames,
  in the sRGB-encoded 0..1 scale the frames are stored in (8-bit code values / 255; target: within
  0.03); linear values and the 48x64 training data are printed for reference.

Prints PASS/FAIL for each criterion and exits 1 when one fails.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path

import cv2
import numpy as np

from watergan.data import load_underwater, read_image
from watergan.generate import GenerateConfig, generate
from watergan.train import GanConfig, train_gan


def _stats(images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean and std of (N,H,W,3) images."""
    return images.reshape(-1, 3).mean(0), images.reshape(-1, 3).std(0)


def _stored(path: Path) -> np.ndarray:
    """An 8-bit image file's code values / 255 as (H,W,3) RGB float64: the sRGB-encoded 0..1 scale the
    survey frames and the generated images are stored in."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.dtype != np.uint8:
        raise SystemExit(f"{path}: expected an 8-bit image")
    return image[..., 2::-1].astype(np.float64) / 255.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--survey", default="/tmp/gan_demo", help="simulated survey (made when missing)")
    parser.add_argument("--out", default="/tmp/gan_bench", help="work folder (model/ and generated/)")
    parser.add_argument("--budget-min", type=float, default=5.0)
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    defaults = GanConfig(Path(), Path(), Path())
    parser.add_argument("--disc-width", type=int, default=defaults.disc_width)
    parser.add_argument("--instance-noise", type=float, default=defaults.instance_noise_std)
    parser.add_argument("--real-label", type=float, default=defaults.real_label)
    parser.add_argument("--physics-lr", type=float, default=defaults.physics_lr)
    parser.add_argument("--rgbd-dir", default=None, help="in-air RGB-D set (default: SURVEY/rgbd)")
    parser.add_argument("--site-water", default=None, help="a water stage's water.json")
    parser.add_argument("--site-water-mode", default="held", choices=["held", "prior"])
    parser.add_argument("--adversarial-physics", action="store_true",
                        help="the paper's training: the discriminator moves the physical parameters too")
    args = parser.parse_args()
    os.environ.setdefault("MPLCONFIGDIR", str(Path(args.out) / "mpl"))

    survey, out = Path(args.survey), Path(args.out)
    if not (survey / "truth" / "effects.json").is_file():
        from eval.synth import make_config, simulate_survey

        started = time.perf_counter()
        simulate_survey(survey, make_config("demo", hidden=[], seed=args.seed), force=True)
        print(f"simulated the demo survey in {time.perf_counter() - started:.1f} s -> {survey}")
    if out.exists():
        shutil.rmtree(out)

    config = GanConfig(rgbd_dir=Path(args.rgbd_dir) if args.rgbd_dir else survey / "rgbd",
                       underwater_dir=survey / "images", out_dir=out / "model",
                       site_water=Path(args.site_water) if args.site_water else None,
                       site_water_mode=args.site_water_mode,
                       budget_min=args.budget_min, iterations=args.iterations, seed=args.seed,
                       disc_width=args.disc_width, instance_noise_std=args.instance_noise,
                       real_label=args.real_label, physics_lr=args.physics_lr,
                       adversarial_physics=args.adversarial_physics)
    cpu_started = time.process_time()
    result = train_gan(config)
    cpu_s = time.process_time() - cpu_started
    print(f"\ntraining: {result.steps} iterations in {result.seconds:.1f} s = {result.iterations_per_s:.2f} it/s "
          f"(batch {config.batch_size}, {config.gen_steps_per_disc_step} G steps per D step, disc width "
          f"{config.disc_width}, stopped by {result.stopped_by})")
    print(f"  final losses D {result.d_loss:.3f}, G {result.g_loss:.3f}")
    print(f"  CPU time {cpu_s:.0f} s = {cpu_s / max(result.steps, 1):.2f} CPU-s per iteration (all threads; on an "
          f"idle 2-core machine wall time is about half of that)")

    effects = json.loads((survey / "truth" / "effects.json").read_text())
    truth = {e["name"]: e["params"] for e in effects["full"]}
    print(f"hidden effects in the survey: {[e['name'] for e in effects['hidden']] or 'none'}")
    eta_true = np.array(truth["attenuation"]["eta_per_m"])
    eta = np.array(result.params["attenuation.eta_per_m"])
    rel = (eta - eta_true) / eta_true
    same_order = list(np.argsort(eta)) == list(np.argsort(eta_true))
    print("\nattenuation eta (1/m)   R       G       B")
    print(f"  truth               {eta_true[0]:.3f}   {eta_true[1]:.3f}   {eta_true[2]:.3f}")
    print(f"  learned             {eta[0]:.3f}   {eta[1]:.3f}   {eta[2]:.3f}")
    print(f"  relative error      {rel[0]:+.0%}    {rel[1]:+.0%}    {rel[2]:+.0%}")
    print(f"  ordering same as truth: {same_order}; every channel within 50 %: {bool((abs(rel) <= 0.5).all())}")
    for name, value in result.params.items():
        if not name.startswith("attenuation"):
            print(f"  learned {name} = {np.round(value, 4).tolist()}   (truth: {truth.get(name.split('.')[0])})")

    # full resolution, from the survey's own in-air frames
    rgbd = out / "survey_rgbd"
    (rgbd / "rgb").mkdir(parents=True)
    (rgbd / "depth").symlink_to((survey / "truth" / "depth").resolve())
    for f in sorted((survey / "truth" / "inair_linear").glob("*.png")):
        (rgbd / "rgb" / f.name).symlink_to(f.resolve())
    shutil.copy(survey / "camera.json", rgbd / "camera.json")
    started = time.perf_counter()
    gen = generate(GenerateConfig(model_dir=out / "model", rgbd_dir=rgbd, out_dir=out / "generated",
                                  encoding="linear", seed=args.seed, recolour_fraction=0.0,
                                  progress=False))
    print(f"\ngenerated {gen.count} full-resolution images in {time.perf_counter() - started:.1f} s")
    fake = np.stack([read_image(p) for p in sorted((out / "generated" / "underwater").glob("*.png"))])
    real = np.stack([read_image(p) for p in sorted((survey / "images").glob("*.png"))])
    print(f"  generated {fake.shape[2]}x{fake.shape[1]}, real {real.shape[2]}x{real.shape[1]} "
          f"({real.shape[0]} frames)")
    # (b) on the scale the images are stored in: 8-bit sRGB code values / 255 (float64 statistics)
    fake8 = np.stack([_stored(p) for p in sorted((out / "generated" / "underwater").glob("*.png"))])
    real8 = np.stack([_stored(p) for p in sorted((survey / "images").glob("*.png"))])
    (fm, fs), (rm, rs) = _stats(fake8), _stats(real8)
    mean_diff, std_diff = np.abs(fm - rm), np.abs(fs - rs)
    print("  sRGB-encoded 0..1 (stored 8-bit values / 255), R G B:")
    print(f"    mean  generated {np.round(fm, 3).tolist()}  real {np.round(rm, 3).tolist()}  "
          f"|diff| {np.round(mean_diff, 3).tolist()}")
    print(f"    std   generated {np.round(fs, 3).tolist()}  real {np.round(rs, 3).tolist()}  "
          f"|diff| {np.round(std_diff, 3).tolist()}")
    (lfm, lfs), (lrm, lrs) = _stats(fake), _stats(real)
    print(f"  (linear, for reference: mean |diff| {np.round(np.abs(lfm - lrm), 3).tolist()}, "
          f"std |diff| {np.round(np.abs(lfs - lrs), 3).tolist()})")
    train_real = load_underwater(survey / "images").images.numpy()
    gm, trm = np.array(result.colour_mean["generated"]), train_real.mean(axis=(0, 2, 3))
    gs, trs = np.array(result.colour_std["generated"]), np.array(result.colour_std["real"])
    print(f"  (48x64 training data, linear: mean |diff| {np.round(np.abs(gm - trm), 3).tolist()}, "
          f"std |diff| {np.round(np.abs(gs - trs), 3).tolist()})")

    criteria = [
        ("time", f"training within the budget ({args.budget_min:g} min)",
         result.seconds <= 60.0 * args.budget_min + 5.0, f"{result.seconds:.0f} s"),
        ("a", "attenuation: learned eta in the true channel ordering",
         same_order, f"learned {np.round(eta, 3).tolist()}, truth {eta_true.tolist()}"),
        ("a", "attenuation: every eta_c within 50 % of the truth",
         bool((np.abs(rel) <= 0.5).all()), f"relative error {np.round(rel, 2).tolist()}"),
        ("b", "colour: per-channel mean within 0.03 (sRGB-encoded 0..1)",
         bool((mean_diff <= 0.03).all()), f"largest |diff| {mean_diff.max():.3f}"),
        ("b", "colour: per-channel std within 0.03 (sRGB-encoded 0..1)",
         bool((std_diff <= 0.03).all()), f"largest |diff| {std_diff.max():.3f}"),
    ]
    print("\ncriteria")
    for tag, text, ok, detail in criteria:
        print(f"  ({tag}) {'PASS' if ok else 'FAIL'}  {text}: {detail}")
    passed = all(c[2] for c in criteria)
    print(f"overall: {'PASS' if passed else 'FAIL'}")
    return 0 if passed else 1


if __name__ == "__main__":
    raise SystemExit(main())
