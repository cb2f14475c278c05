"""Unconfirmed fragments dropped or kept, side by side from the same optimised field.

For each case: the benchmark's case (``benchmark.cases.prepare_case``), one ``fast``
reconstruction with ``drop_unconfirmed_fragments`` off (pruning and reconnection as the preset
has them), scored; then the same result with the detached fragments that some view does not
confirm removed — exactly what ``optimiser.finish`` does when the setting is on — scored with the
same metrics. The strict visual hull is scored too, for reference. One CSV row per case × variant;
the means and the paired differences are printed at the end.

    .venv/bin/python bench/fragments.py --suite rca --protocol realistic-static-lao30-rao30 --cases 4 \\
        --csv bench/runs/fragments/rca-realistic.csv
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's SDFCARLib

from SDFCARLib.benchmark.cases import CaseSpec, GridOptions, default_centreline, prepare_case  # noqa: E402
from SDFCARLib.hull import visual_hull  # noqa: E402
from SDFCARLib.metrics import evaluate  # noqa: E402
from SDFCARLib.optimiser import reconstruct, vessel_pixels  # noqa: E402
from SDFCARLib.pruning import removal_zone, unconfirmed_fragments  # noqa: E402
from SDFCARLib.settings import PROTOCOLS, make_settings  # noqa: E402

COLUMNS = ["suite", "protocol", "case", "variant", "cldice", "tprec", "tsens", "dice", "chamfer_l2_mm", "components",
           "largest_component_fraction", "components_label", "removed_fragments", "removed_voxels", "seconds"]
METRICS = ("cldice", "tprec", "tsens", "dice", "chamfer_l2_mm", "components", "largest_component_fraction")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", choices=("rca", "lad", "721a"), required=True)
    parser.add_argument("--protocol", default="realistic-static-lao30-rao30", choices=sorted(PROTOCOLS))
    parser.add_argument("--cases", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--volume-shape", type=int, default=80)
    parser.add_argument("--spacing-mm", type=float, default=1.3)
    parser.add_argument("--detector-shape", type=int, default=192)
    parser.add_argument("--detector-spacing-mm", type=float, default=0.8)
    parser.add_argument("--protocol-grid", action="store_true", help="the protocol's own grid and detector (ignores the four above)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--csv", type=Path, required=True)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    grid = (GridOptions() if args.protocol_grid else
            GridOptions((args.volume_shape,) * 3, args.spacing_mm, (args.detector_shape,) * 2, args.detector_spacing_mm))
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"{args.threads} thread(s); {args.suite} {args.protocol}, grid {'of the protocol' if args.protocol_grid else grid}",
          flush=True)
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    with open(args.csv, "w", newline="") as handle:
        writer = csv.DictWriter(handle, COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for index in range(args.cases):
            seed = args.seed + index
            spec = (CaseSpec("721a", "721A", "721a", seed, index, source=str(default_centreline())) if args.suite == "721a"
                    else CaseSpec(args.suite, f"{args.suite.upper()}-{seed}", args.suite, seed, index))
            case = prepare_case(spec, args.protocol, grid)
            g, views = case.geometry.volume, case.geometry.views
            base = {"suite": args.suite, "protocol": args.protocol, "case": spec.name}
            score = lambda volume: evaluate(volume, case.label, g, views, case.masks)  # noqa: E731
            hull = visual_hull(case.masks, views, g)
            rows.append({**base, "variant": "hull", **score(hull)})
            settings = make_settings("fast", seed=seed, device="cpu", drop_unconfirmed_fragments=False)
            result = reconstruct(case.geometry, case.targets, settings, case.target_kind)
            rows.append({**base, "variant": "kept", **score(result.segmentation),
                         "seconds": result.report["timings_s"]["total"]})
            # What optimiser.finish does with drop_unconfirmed_fragments on, from the same result.
            t0 = time.perf_counter()
            removed, info = unconfirmed_fragments(result.segmentation, vessel_pixels(case.targets, case.target_kind),
                                                  case.geometry)
            occupancy = result.occupancy.copy()
            occupancy[removal_zone(result.segmentation, result.segmentation & ~removed, g.spacing_mm)] = 0.0
            dropped = occupancy >= settings.region.threshold
            rows.append({**base, "variant": "dropped", **score(dropped), "removed_fragments": info["removed_fragments"],
                         "removed_voxels": info["removed_voxels"], "seconds": time.perf_counter() - t0})
            for row in rows[-3:]:
                writer.writerow(row)
            handle.flush()
            print(spec.name, " | ".join(f"{r['variant']} clDice {r['cldice']:.3f} Dice {r['dice']:.3f} "
                                        f"components {r['components']}/{r['components_label']}" for r in rows[-3:]), flush=True)
    print("\nmeans over", args.cases, "cases")
    for variant in ("hull", "kept", "dropped"):
        chosen = [r for r in rows if r["variant"] == variant]
        print(f"{variant:8s} " + "  ".join(f"{k} {np.mean([float(r[k]) for r in chosen]):.3f}" for k in METRICS))
    kept = [r["cldice"] for r in rows if r["variant"] == "kept"]
    dropped = [r["cldice"] for r in rows if r["variant"] == "dropped"]
    delta = np.subtract(dropped, kept)
    print(f"clDice dropped − kept: mean {delta.mean() * 100:+.2f} points, worse in {(delta < 0).sum()} of {delta.size}")


if __name__ == "__main__":
    main()
