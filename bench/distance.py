"""L_geo's distance transform: kornia's full cascade against the truncated one, side by side.

    python bench/distance.py --sizes 64,128,256 --out bench/runs/distance

For each image size, both transforms run forward + backward on the same batch (two views × vessel
and background sources = 4 images, a random silhouette), each in its own process so that its peak
memory (maximum resident set size, less the process's own before the transform) is its own. The
truncation is the loss's: 5 mm at ``--pixel-mm`` per pixel. Prints a Markdown table and writes
OUT/distance.json with the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def worker(spec: dict) -> dict:
    import torch

    from kornia.contrib import distance_transform

    from SDFCARLib.losses import cascaded_distance

    torch.set_num_threads(spec["threads"])
    generator = torch.Generator().manual_seed(0)
    n = spec["size"]
    images = torch.rand(4, 1, n, n, generator=generator)
    images = (images > 0.98).float() * torch.rand(4, 1, n, n, generator=generator)  # sparse soft sources
    max_distance_px = spec["truncation_mm"] / spec["pixel_mm"]
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    times = []
    for _ in range(spec["repeats"]):
        x = images.clone().requires_grad_(True)
        start = time.perf_counter()
        if spec["method"] == "kornia":
            distance = distance_transform(x, kernel_size=3)
        else:
            distance = cascaded_distance(x, 3, max_distance_px=max_distance_px)
        distance.clamp(max=max_distance_px).sum().backward()
        times.append(time.perf_counter() - start)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
    return {"size": n, "method": spec["method"], "seconds": min(times), "peak_mib": peak / 1024}


def machine(threads: int) -> dict:
    import torch

    info = {"platform": platform.platform(), "cores": os.cpu_count(), "torch": torch.__version__, "threads": threads}
    try:
        info["cpu"] = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return info


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="64,128,256", help="image sizes (kornia needs ~22 GB at 512)")
    parser.add_argument("--pixel-mm", type=float, default=0.212, help="pixel at the isocenter (0.278 mm / 1.31)")
    parser.add_argument("--truncation-mm", type=float, default=5.0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="bench/runs/distance")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return 0
    rows = []
    for size in (int(s) for s in args.sizes.split(",")):
        pair = {}
        for method in ("kornia", "truncated"):
            spec = {"size": size, "method": method, "threads": args.threads, "repeats": args.repeats,
                    "pixel_mm": args.pixel_mm, "truncation_mm": args.truncation_mm}
            done = subprocess.run([sys.executable, __file__, "--worker", json.dumps(spec)], capture_output=True, text=True)
            if done.returncode != 0:
                pair[method] = {"size": size, "method": method, "error": done.stderr.strip().splitlines()[-1:]}
            else:
                pair[method] = json.loads(done.stdout.strip().splitlines()[-1])
        rows.append(pair)
    lines = [f"Machine: {machine(args.threads)}; truncation {args.truncation_mm} mm at {args.pixel_mm} mm/pixel; "
             f"4 images, forward + backward, best of {args.repeats}.", "",
             "| size | kornia s | truncated s | time ratio | kornia peak MiB | truncated peak MiB | memory ratio |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for pair in rows:
        k, t = pair["kornia"], pair["truncated"]
        if "error" in k or "error" in t:
            lines.append(f"| {k['size']} | {k.get('error', '')} | {t.get('error', '')} | | | | |")
            continue
        lines.append(f"| {k['size']}² | {k['seconds']:.3f} | {t['seconds']:.3f} | {k['seconds'] / t['seconds']:.1f}× | "
                     f"{k['peak_mib']:.0f} | {t['peak_mib']:.0f} | {k['peak_mib'] / max(t['peak_mib'], 1):.1f}× |")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "distance.json").write_text(json.dumps({"machine": machine(args.threads), "rows": rows}, indent=2))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
