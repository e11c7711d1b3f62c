"""Restorer speed: frames per second correcting 640x480 images (depth + colour nets, pad/un-pad included),
on the CPU with 2 threads and on CUDA when present, with peak memory.

    .venv/bin/python benchmarks/bench_restorer.py [--widths cpu|paper] [--batch 4] [--repeats 5]

Peak memory: the process's maximum resident set (``resource.getrusage``, CPU) and
``torch.cuda.max_memory_allocated`` (CUDA). Untrained weights: the speed does not depend on them.
"""

from __future__ import annotations

import argparse
import resource
import time

import torch

from watergan.nets.restorer import WIDTH_PRESETS, Restorer, restore


def frames_per_s(model: Restorer, device: torch.device, batch: int, repeats: int) -> float:
    """Best of ``repeats`` timed batches (after one warm-up): batch / seconds."""
    x = torch.rand(batch, 3, 480, 640, device=device)
    best = float("inf")
    with torch.no_grad():
        for i in range(repeats + 1):
            if device.type == "cuda":
                torch.cuda.synchronize()
            began = time.perf_counter()
            restore(model, x)
            if device.type == "cuda":
                torch.cuda.synchronize()
            if i:
                best = min(best, time.perf_counter() - began)
    return batch / best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--widths", choices=sorted(WIDTH_PRESETS), default="cpu")
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(2)
    model = Restorer(WIDTH_PRESETS[args.widths]).eval()
    params = sum(p.numel() for p in model.parameters())
    fps = frames_per_s(model, torch.device("cpu"), args.batch, args.repeats)
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"cpu (2 threads), widths {args.widths} ({params} parameters), batch {args.batch}: "
          f"{fps:.1f} frames/s at 640x480; peak RSS {peak_mib:.0f} MiB")
    if torch.cuda.is_available():
        device = torch.device("cuda")
        model = model.to(device)
        torch.cuda.reset_peak_memory_stats()
        fps = frames_per_s(model, device, args.batch, args.repeats)
        peak = torch.cuda.max_memory_allocated() / 2**20
        print(f"cuda ({torch.cuda.get_device_name()}), widths {args.widths}, batch {args.batch}: "
              f"{fps:.1f} frames/s at 640x480; peak allocated {peak:.0f} MiB")


if __name__ == "__main__":
    main()
