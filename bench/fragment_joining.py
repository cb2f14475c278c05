"""Joining fragments before or after the unconfirmed ones are dropped, side by side from one optimised field.

``fast`` reconnects fragments through bright, short stretches of the field (``connectivity.py``, 4 mm /
geometric-mean occupancy 0.1) and then drops the detached fragments that some view does not confirm
(``pruning.unconfirmed_fragments``). Section 5 of RESULTS.md found looser joining glued ghosts to the
tree; the confirmation step came later (section 13). This script asks whether dropping first and then
joining what is left more loosely brings a tree that is one piece back as fewer pieces without losing
clDice.

Per case: one ``fast`` reconstruction with both steps off (pruning as the preset has it), then each
variant of ``VARIANTS`` applied to the same occupancy and scored with ``metrics.evaluate``. The
"fast" variant is exactly what ``optimiser.finish`` does (``--check`` reconstructs once more with the
preset as it is and prints both scores). Protocols: ``clean`` (clinical-lao30-rao30, binary masks
projected from the truth) or ``realistic`` (realistic-static-lao30-rao30: masks segmented from
simulated angiograms, the frames given as evidence); coarse grid 80³ at 1.3 mm, 192² at 0.8 mm.

    .venv/bin/python bench/fragment_joining.py --suite rca --input realistic --cases 10 --csv bench/runs/joining/rca-real.csv
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from bench.realistic_cases import COARSE_GRID, add_grid_arguments  # noqa: E402
from SDFCARLib.benchmark.cases import CaseSpec, GridOptions, default_centreline, prepare_case, protocol_geometry  # noqa: E402
from SDFCARLib.connectivity import ReconnectSettings, reconnect_fragments  # noqa: E402
from SDFCARLib.metrics import evaluate  # noqa: E402
from SDFCARLib.optimiser import reconstruct  # noqa: E402
from SDFCARLib.phantoms import lad_tree, rca_tree, voxelize  # noqa: E402
from SDFCARLib.pruning import removal_zone, unconfirmed_fragments  # noqa: E402
from SDFCARLib.realistic import RealisticOptions, realistic_input  # noqa: E402
from SDFCARLib.settings import REALISTIC_PROTOCOLS, make_settings  # noqa: E402

#: name: (drop the unconfirmed fragments first?, reconnect max gap mm, reconnect min geometric-mean occupancy)
VARIANTS = {
    "fast": (False, 4.0, 0.1),
    "drop, join 4/0.1": (True, 4.0, 0.1),
    "drop, join 6/any": (True, 6.0, 1e-6),
    "drop, join 8/0.002": (True, 8.0, 0.002),
    "drop, join 8/any": (True, 8.0, 1e-6),
    "drop, join 12/any": (True, 12.0, 1e-6),
}
KEYS = ("cldice", "tprec", "tsens", "dice", "chamfer_l2_mm", "components", "largest_component_fraction")


def drop_unconfirmed(segmentation, occupancy, masks, geometry, threshold):
    removed, _ = unconfirmed_fragments(segmentation, masks, geometry)
    occupancy = occupancy.copy()
    if removed.any():
        occupancy[removal_zone(segmentation, segmentation & ~removed, geometry.volume.spacing_mm)] = 0.0
    return occupancy >= threshold, occupancy


def apply(variant, segmentation, occupancy, support, masks, geometry, threshold):
    drop_first, gap_mm, min_occupancy = VARIANTS[variant]
    if drop_first:
        segmentation, occupancy = drop_unconfirmed(segmentation, occupancy, masks, geometry, threshold)
    segmentation, occupancy, _, info = reconnect_fragments(segmentation, occupancy, geometry.volume.spacing_mm, support,
                                                           ReconnectSettings(gap_mm, min_occupancy, threshold))
    if not drop_first:
        segmentation, occupancy = drop_unconfirmed(segmentation, occupancy, masks, geometry, threshold)
    return segmentation, info


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", choices=("rca", "lad", "721a"), default="rca",
                        help="procedural trees, or the clinical 721A centreline (clean masks, the protocol's own grid)")
    parser.add_argument("--input", choices=("clean", "realistic"), default="realistic")
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--cases", type=int, default=4)
    parser.add_argument("--check", action="store_true", help="also run fast as it is on each case and print both scores")
    parser.add_argument("--csv", type=Path)
    add_grid_arguments(parser)
    args = parser.parse_args()
    import os
    import platform

    import torch

    torch.set_num_threads(args.threads)
    if args.suite == "721a" and args.input != "clean":
        parser.error("the 721A case has clean masks only (--input clean)")
    protocol = "clinical-lao30-rao30" if args.input == "clean" else "realistic-static-lao30-rao30"
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"{args.threads} thread(s); {args.suite} {protocol}, cases {args.first}..{args.first + args.cases - 1}, "
          f"{'paper grid' if args.paper_grid or args.suite == '721a' else 'grid80'}", flush=True)
    grid = None if args.paper_grid else COARSE_GRID
    rows = []
    writer = None
    if args.csv:
        args.csv.parent.mkdir(parents=True, exist_ok=True)
        handle = open(args.csv, "w", newline="")
        writer = csv.DictWriter(handle, ["case", "variant", *KEYS, "components_label", "joined", "seconds"],
                                extrasaction="ignore")
        writer.writeheader()
    for seed in range(args.first, args.first + args.cases):
        name = f"{args.suite.upper()}-{seed}"
        spec = (CaseSpec("721a", "721A", "721a", seed, 0, source=str(default_centreline())) if args.suite == "721a"
                else CaseSpec(args.suite, name, args.suite, seed, seed - args.first))
        if args.input == "clean":  # 721A: on the protocol's own grid, as section 13 ran it
            case = prepare_case(spec, protocol, GridOptions() if grid is None or args.suite == "721a" else grid)
            geometry, masks, targets, kind, label, frames = (case.geometry, case.masks, case.targets, case.target_kind,
                                                             case.label, None)
        else:
            geometry = protocol_geometry(protocol, args.suite, grid)
            label = voxelize((rca_tree if args.suite == "rca" else lad_tree)(seed), geometry.volume)
            realistic = realistic_input(label, geometry, seed, RealisticOptions(**REALISTIC_PROTOCOLS[protocol]))
            masks = targets = realistic.masks
            kind, frames = "mask", realistic.frames
        settings = make_settings("fast", seed=seed, reconnect=False, drop_unconfirmed_fragments=False)
        t0 = time.perf_counter()
        result = reconstruct(geometry, targets, settings, kind, frames=frames)
        print(f"{name}: optimised in {time.perf_counter() - t0:.0f} s", flush=True)
        threshold = settings.region.threshold
        for variant in VARIANTS:
            t1 = time.perf_counter()
            # result.geometry: the poses as corrected by the calibration from the frames, as finish sees them
            segmentation, info = apply(variant, result.segmentation, result.occupancy, result.support, masks,
                                       result.geometry, threshold)
            m = evaluate(segmentation, label, geometry.volume, geometry.views, masks)
            row = {"case": name, "variant": variant, **m, "joined": info["joined"], "seconds": time.perf_counter() - t1}
            rows.append(row)
            if writer:
                writer.writerow(row)
                handle.flush()
            print(f"{name} {variant:20s} clDice {m['cldice']:.3f} Tprec {m['tprec']:.3f} Tsens {m['tsens']:.3f} "
                  f"Dice {m['dice']:.3f} pieces {m['components']}/{m['components_label']} "
                  f"largest {m['largest_component_fraction']:.2f} joined {info['joined']}", flush=True)
        if args.check:
            plain = reconstruct(geometry, targets, make_settings("fast", seed=seed), kind, frames=frames)
            m = evaluate(plain.segmentation, label, geometry.volume, geometry.views, masks)
            print(f"{name} check: fast as it is clDice {m['cldice']:.4f} pieces {m['components']}; the 'fast' variant "
                  f"{rows[-len(VARIANTS)]['cldice']:.4f} pieces {rows[-len(VARIANTS)]['components']}", flush=True)
    print(f"# means over {args.cases} cases (clDice, Tprec, Tsens, Dice, largest in %; Chamfer mm; pieces); "
          f"paired against 'fast'")
    base = np.array([r["cldice"] for r in rows if r["variant"] == "fast"])
    for variant in VARIANTS:
        chosen = [r for r in rows if r["variant"] == variant]
        delta = np.array([r["cldice"] for r in chosen]) - base
        truth = np.mean([r["components_label"] for r in chosen])
        print(f"{variant:20s} " + "  ".join(
            f"{k} {np.mean([r[k] for r in chosen]) * (1 if k in ('chamfer_l2_mm', 'components') else 100):.2f}" for k in KEYS)
              + f"  (truth {truth:.1f} pieces)  ΔclDice {delta.mean() * 100:+.2f}, worse in {(delta < -1e-9).sum()}/{delta.size}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
