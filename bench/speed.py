"""Speed and time-to-accuracy of the presets and variants, side by side in one run.

    python bench/speed.py --cases 721a,lad-0,rca-0 --protocol clinical --out bench/runs/speed

Every (case, variant) runs in its own process, one after another, so its peak memory (maximum
resident set size) is its own and the machine's noise hits all variants alike. Each reconstruction
records the segmentation's clDice/Dice every ``--snapshot-every`` steps (snapshot time excluded),
from which the time to reach given clDice levels is read. Variants with ``"timing_only"`` run a
few steps only (the paper preset takes minutes per step on a CPU): their per-step time, setup
time and memory are measured, their 5000-step time is extrapolated and labelled as such.
The machine is recorded in the output. Results: OUT/speed.json and OUT/speed.md.
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

#: name -> (preset, overrides, timing_only)
VARIANTS = {
    "paper": ("paper", {}, True),
    "paper+hull": ("paper", {"support": "hull"}, True),
    "fast": ("fast", {}, False),
    "fast dt8": ("fast", {"dt_downsample": 8}, False),
    "fast dt4": ("fast", {"dt_downsample": 4}, False),
    "fast dt1": ("fast", {"dt_downsample": 1}, False),
    "fast w32": ("fast", {"width": 32}, False),
    "fast w128": ("fast", {"width": 128}, False),
    "fast 800 steps": ("fast", {"steps": 800}, False),
    "fast sdf-occ": ("fast", {"mode": "sdf-occ"}, False),
}
THRESHOLDS = (0.5, 0.6, 0.7, 0.75, 0.8)


def machine() -> dict:
    info = {"platform": platform.platform(), "python": platform.python_version(), "cores": os.cpu_count()}
    try:
        info["cpu"] = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
        info["memory_gib"] = round(int(next(l.split()[1] for l in open("/proc/meminfo") if l.startswith("MemTotal"))) / 2**20, 1)
    except (OSError, StopIteration):
        pass
    import torch

    info["torch"] = torch.__version__
    info["torch_threads"] = torch.get_num_threads()
    info["gpu"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return info


def make_case(name: str, protocol: str):
    from SDFCARLib.geometry import CArmView, Geometry, VIEW_PAIRS, VolumeGrid
    from SDFCARLib.phantoms import lad_tree, load_centreline_vtk, make_case as simulate, rca_tree

    grid = VolumeGrid((128, 128, 128), (0.8, 0.8, 0.8))
    if name == "721a":
        tree = load_centreline_vtk(REPO.parent / "shared" / "data" / "721A_Centreline.vtk").centered()
    else:
        kind, seed = name.split("-")
        tree = {"lad": lad_tree, "rca": rca_tree}[kind](int(seed))
    pair = "paper" if protocol == "paper" else "lao30-rao30"
    views = [CArmView(a, b, sid, sod, (0.278, 0.278), (512, 512)) for a, b, sid, sod in VIEW_PAIRS[pair]]
    if name == "721a" and protocol != "paper":  # the protocol of the hull baseline
        views = [CArmView(a, b, 1000.0, 757.0, (0.35, 0.35), (512, 512)) for a, b, _, _ in VIEW_PAIRS[pair]]
    return simulate(tree, Geometry(grid, views))


def worker(spec: dict) -> dict:
    import torch

    from SDFCARLib import metrics
    from SDFCARLib.optimiser import reconstruct
    from SDFCARLib.settings import make_settings

    torch.set_num_threads(spec["threads"])
    case = make_case(spec["case"], spec["protocol"])
    targets, kind = (case.line_integrals, "line_integral") if spec["protocol"] == "paper" else (case.masks, "mask")
    overrides = dict(spec["overrides"])
    if spec["timing_only"]:
        overrides["steps"] = spec["timing_steps"]
    settings = make_settings(spec["preset"], seed=0, **overrides)
    curve = []

    def snapshot(step, occupancy):
        seg = occupancy >= settings.region.threshold
        m = metrics.volume_metrics(seg, case.label, case.geometry.volume.spacing_mm)
        curve.append({"step": step, "cldice": m["cldice"], "dice": m["dice"]})

    t0 = time.perf_counter()
    result = reconstruct(case.geometry, targets, settings, target_kind=kind, snapshot=None if spec["timing_only"] else snapshot,
                         snapshot_every=spec["snapshot_every"])
    wall = time.perf_counter() - t0
    timings = result.report["timings_s"]
    out = {"case": spec["case"], "variant": spec["variant"], "timings": timings, "wall_s": wall,
           "support_voxels": result.report["support_voxels"], "steps_run": settings.optimisation.steps,
           "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}
    if spec["timing_only"]:
        full_steps = spec["full_steps"]
        out["extrapolated_total_s"] = timings["setup"] + timings["per_step"] * full_steps
    else:
        m = metrics.volume_metrics(result.segmentation, case.label, case.geometry.volume.spacing_mm)
        out["final"] = {k: m[k] for k in ("cldice", "dice", "iou", "chamfer_l2_mm", "skeleton_dice")}
        per_step = timings["per_step"]
        out["curve"] = curve
        out["time_to"] = {}
        for level in THRESHOLDS:
            hit = next((c["step"] for c in curve if c["cldice"] >= level), None)
            out["time_to"][str(level)] = None if hit is None else timings["setup"] + per_step * hit
    return out


def fmt(value, digits=1):
    return "–" if value is None else f"{value:.{digits}f}"


def write_report(results: list, info: dict, args, out: Path) -> str:
    lines = [f"# Speed: {args.protocol} protocol, cases {args.cases}", "",
             f"Machine: {info.get('cpu')} ({info.get('cores')} cores, {info.get('memory_gib')} GiB), "
             f"torch {info['torch']} with {args.threads} threads, GPU: {info['gpu'] or 'none'}; {time.strftime('%Y-%m-%d')}.",
             f"Command: `python bench/speed.py {' '.join(sys.argv[1:])}`", "",
             "| case | variant | support voxels | setup s | ms/step | steps | total s | × paper per step | peak RSS GiB | "
             "clDice | Dice | CD mm | s to clDice " + " / ".join(str(t) for t in THRESHOLDS) + " |",
             "|" + "---|" * 13]
    paper_step = {r["case"]: r["timings"]["per_step"] for r in results if r["variant"] == "paper" and "timings" in r}
    for r in results:
        if "error" in r:
            lines.append(f"| {r['case']} | {r['variant']} | error: {r['error'][:80]} |" + " |" * 10)
            continue
        t = r["timings"]
        total = r.get("extrapolated_total_s")
        total_text = f"{total:.0f} (extrapolated, {r['steps_run']} steps run)" if total is not None else fmt(t["total"])
        steps = r["steps_run"] if total is None else 5000
        ratio = paper_step.get(r["case"], 0) / t["per_step"] if paper_step.get(r["case"]) else None
        final = r.get("final", {})
        times = " / ".join(fmt(v, 0) for v in r.get("time_to", {}).values()) if r.get("time_to") else "not run"
        lines.append(f"| {r['case']} | {r['variant']} | {r['support_voxels']} | {t['setup']:.1f} | {t['per_step'] * 1000:.0f} | "
                     f"{steps} | {total_text} | {fmt(ratio)} | {r['peak_rss_gib']:.2f} | {fmt(final.get('cldice'), 3)} | "
                     f"{fmt(final.get('dice'), 3)} | {fmt(final.get('chamfer_l2_mm'), 2)} | {times} |")
    text = "\n".join(lines) + "\n"
    (out / "speed.md").write_text(text)
    return text


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", default="721a,lad-0,rca-0")
    parser.add_argument("--protocol", choices=("clinical", "paper"), default="clinical")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--snapshot-every", type=int, default=50)
    parser.add_argument("--timing-steps", type=int, default=2, help="steps run by timing-only variants")
    parser.add_argument("--out", default=str(REPO / "bench" / "runs" / "speed"))
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print("RESULT " + json.dumps(worker(json.loads(args.worker))), flush=True)
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    info = machine()
    results = []
    for case in args.cases.split(","):
        for name in args.variants.split(","):
            preset, overrides, timing_only = VARIANTS[name]
            spec = {"case": case, "variant": name, "preset": preset, "overrides": overrides, "timing_only": timing_only,
                    "protocol": args.protocol, "threads": args.threads, "snapshot_every": args.snapshot_every,
                    "timing_steps": args.timing_steps, "full_steps": 5000}
            proc = subprocess.run([sys.executable, __file__, "--worker", json.dumps(spec)], capture_output=True, text=True)
            line = next((l for l in proc.stdout.splitlines() if l.startswith("RESULT ")), None)
            result = json.loads(line[7:]) if line else {"case": case, "variant": name, "error": (proc.stderr or "no output").strip().splitlines()[-1]}
            results.append(result)
            print(json.dumps({k: v for k, v in result.items() if k != "curve"}), flush=True)
            (out / "speed.json").write_text(json.dumps({"machine": info, "results": results}, indent=1))
    print(write_report(results, info, args, out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
