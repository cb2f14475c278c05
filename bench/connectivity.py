"""Reconnection of fragments side by side with the plain result, from the same optimised field.

For each case of a procedural suite: the benchmark's case (``benchmark.cases.prepare_case``), one
``fast`` reconstruction with the preset as it is (reconnect off), scored; then the same field
with ``connectivity.reconnect_fragments`` applied (the step ``optimiser.finish`` runs when
``reconnect`` is on) at the default thresholds and at looser ones (``VARIANTS``), scored with the
same metrics. The optimisation is shared, so the difference is
the reconnection alone. Writes one CSV row per case × variant.

    .venv/bin/python bench/connectivity.py --suite rca --cases 5 --csv bench/runs/conn/rca.csv
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's SDFCARLib

from SDFCARLib.benchmark.cases import CaseSpec, GridOptions, prepare_case
from SDFCARLib.connectivity import ReconnectSettings, reconnect_fragments
from SDFCARLib.metrics import evaluate
from SDFCARLib.optimiser import reconstruct
from SDFCARLib.settings import make_settings

#: (reconnect_max_gap_mm, reconnect_min_occupancy): the settings' defaults first, then looser ones
VARIANTS = [(4.0, 0.1), (6.0, 0.02), (8.0, 0.002)]
COLUMNS = ["suite", "case", "variant", "cldice", "tprec", "tsens", "dice", "chamfer_l2_mm", "components",
           "largest_component_fraction", "components_label", "joined", "gap_mm", "wall_s"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", choices=("rca", "lad"), required=True)
    parser.add_argument("--cases", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--protocol", default="clinical-lao30-rao30")
    parser.add_argument("--volume-shape", type=int, default=80)
    parser.add_argument("--spacing-mm", type=float, default=1.28)
    parser.add_argument("--detector-shape", type=int, default=192)
    parser.add_argument("--detector-spacing-mm", type=float, default=0.742)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--csv", type=Path, required=True)
    parser.add_argument("--save", action="store_true", help="keep each case's occupancy, segmentation and label (npz)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    grid = GridOptions((args.volume_shape,) * 3, args.spacing_mm, (args.detector_shape,) * 2, args.detector_spacing_mm)
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    with open(args.csv, "w", newline="") as handle:
        writer = csv.DictWriter(handle, COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for index in range(args.cases):
            seed = args.seed + index
            spec = CaseSpec(args.suite, f"{args.suite.upper()}-{seed}", args.suite, seed, index)
            case = prepare_case(spec, args.protocol, grid)
            settings = make_settings("fast", seed=seed, device="cpu")
            result = reconstruct(case.geometry, case.targets, settings, case.target_kind)
            base = {"suite": args.suite, "case": spec.name}
            grid_, views = case.geometry.volume, case.geometry.views
            writer.writerow({**base, "variant": "fast", **evaluate(result.segmentation, case.label, grid_, views, case.masks),
                             "wall_s": result.report["timings_s"]["total"]})
            if args.save:
                np.savez_compressed(args.csv.parent / f"{spec.name}.npz", occupancy=result.occupancy,
                                    segmentation=result.segmentation, label=case.label,
                                    support=result.support if result.support is not None else np.ones(grid_.shape, bool))
            for max_gap_mm, min_occupancy in VARIANTS:
                t0 = time.perf_counter()
                joined, _, _, info = reconnect_fragments(
                    result.segmentation, result.occupancy, grid_.spacing_mm, result.support,
                    ReconnectSettings(max_gap_mm, min_occupancy, settings.region.threshold))
                extra = time.perf_counter() - t0
                writer.writerow({**base, "variant": f"fast+reconnect {max_gap_mm:g} mm / {min_occupancy:g}",
                                 **evaluate(joined, case.label, grid_, views, case.masks),
                                 "joined": info["joined"], "gap_mm": " ".join(f"{g:.1f}" for g in info["gap_mm"]),
                                 "wall_s": result.report["timings_s"]["total"] + extra})
            handle.flush()
            print(spec.name, "done", flush=True)


if __name__ == "__main__":
    main()
