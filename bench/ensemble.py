"""Several fits of one case averaged (``ensemble_fits``) against each fit alone, side by side in one run.

    .venv/bin/python bench/ensemble.py --suite rca --case 0 1 --fits 3 --protocol realistic-static-lao30-rao30 --threads 1

Each case is fitted ``--fits`` times on one problem (the case's seed, then seed + 1, …; ``fast`` otherwise),
and finished ``fast``'s way from: each fit alone ("draw k": draw 0 is ``fast`` as it is), the mean occupancy
of the first two fits and of all of them, and the draw whose result reprojects best onto the masks (highest
mean reprojection Dice, what ``ensemble_combine`` "best_reprojection" keeps) of the first two and of all.
So the ensemble and the choice are compared with the very fits they are made from, and the draws give the
spread of one case between seeds. Prints clDice, Dice, topology precision / sensitivity,
components and times per row, and means over the cases; ``--jsonl FILE`` appends one JSON line per row.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from SDFCARLib.benchmark import BenchmarkConfig, GridOptions, build_cases, prepare_case  # noqa: E402
from SDFCARLib.metrics import evaluate  # noqa: E402
from SDFCARLib.optimiser import fit_field, finish, volumes_of_occupancy  # noqa: E402
from SDFCARLib.settings import PROTOCOLS, make_settings  # noqa: E402


def rows_of(fitted, settings):
    """(name, volumes, settings) to finish: each fit alone, the means of the first two and of all, and with
    three or more fits their median and their mean finished without growing (a ghost of one fit in three
    has mean occupancy 1/3, above `fast`'s grow threshold 0.3)."""
    members = fitted.members
    rows = [(f"draw {k}", members[k], settings) for k in range(len(members))]
    if len(members) > 2:
        rows.append(("mean of 2", volumes_of_occupancy((members[0][0] + members[1][0]) / 2, settings), settings))
    rows.append((f"mean of {len(members)}", fitted.volumes, settings))
    if len(members) > 2:
        rows.append((f"median of {len(members)}",
                     volumes_of_occupancy(np.median(np.stack([m[0] for m in members]), axis=0), settings), settings))
        rows.append((f"mean of {len(members)}, no growing", fitted.volumes,
                     dataclasses.replace(settings, region=dataclasses.replace(settings.region, grow_threshold=0.0))))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", default="rca")
    parser.add_argument("--case", type=int, nargs="+", default=[0])
    parser.add_argument("--protocol", default="realistic-static-lao30-rao30", choices=sorted(PROTOCOLS))
    parser.add_argument("--grid80", action="store_true", help="80³ at 1.3 mm, 192² at 0.8 mm")
    parser.add_argument("--fits", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--set", action="append", default=[], metavar="JSON", help="setting overrides on `fast`")
    parser.add_argument("--jsonl", type=Path, default=None)
    args = parser.parse_args()
    if args.fits < 2:
        parser.error("--fits must be at least 2 (one fit is `fast` itself)")
    torch.set_num_threads(args.threads)
    grid = GridOptions((80, 80, 80), 1.3, (192, 192), 0.8) if args.grid80 else GridOptions()
    config = BenchmarkConfig(args.suite, Path("unused"), cases=max(args.case) + 1, grid=grid, protocol=args.protocol)
    overrides = {}
    for text in args.set:
        overrides.update(json.loads(text))
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"{args.threads} thread(s); {args.suite} cases {args.case}, {args.protocol}, "
          f"{'grid80' if args.grid80 else 'paper grid'}, {args.fits} fits, overrides {overrides}", flush=True)
    table: dict = {}
    for index in args.case:
        spec = build_cases(config)[index]
        t0 = time.perf_counter()
        case = prepare_case(spec, args.protocol, grid)
        prepare_s = time.perf_counter() - t0
        settings = make_settings("fast", **{"seed": spec.seed, **overrides, "ensemble_fits": args.fits})
        t0 = time.perf_counter()
        fitted = fit_field(case.geometry, case.targets, settings, case.target_kind, frames=case.frames, keep_members=True)
        fit_s = time.perf_counter() - t0
        finished_draws = []
        for name, volumes, row_settings in rows_of(fitted, settings):
            t0 = time.perf_counter()
            result = finish(dataclasses.replace(fitted.problem, settings=row_settings), fitted.model, fitted.history,
                            fitted.optimise_s, fitted.t_start, volumes=(volumes[0].copy(), volumes[1].copy()))
            finish_s = time.perf_counter() - t0
            if name.startswith("draw"):
                finished_draws.append(result)
            m = evaluate(result.segmentation, case.label, case.geometry.volume, case.geometry.views, case.masks)
            row = {"case": spec.name, "row": name, "cldice": m["cldice"], "dice": m["dice"],
                   "tprec": m["tprec"], "tsens": m["tsens"],
                   "components": m.get("components"), "components_truth": m.get("components_label"),
                   "reprojection_dice": result.report["reprojection_dice"], "prepare_s": round(prepare_s, 1), "fits_s": round(fit_s, 1), "finish_s": round(finish_s, 1),
                   "device": result.report["device"]}
            table.setdefault(name, []).append(row)
            print(f"{spec.name:7s} {name:26s} clDice {row['cldice']:.3f}  Dice {row['dice']:.3f}  Tprec "
                  f"{row['tprec']:.3f}  Tsens {row['tsens']:.3f}  components {row['components']}/"
                  f"{row['components_truth']}  (prepare {prepare_s:.0f} s, {args.fits} fits {fit_s:.0f} s, finish "
                  f"{finish_s:.0f} s; {row['device']})", flush=True)
            if args.jsonl is not None:
                with open(args.jsonl, "a") as out:
                    out.write(json.dumps(row) + "\n")
        for among in sorted({2, args.fits}):  # the chosen draw's row again, under the choice's name
            scores = [float(np.mean(r.report["reprojection_dice"])) for r in finished_draws[:among]]
            chosen = int(np.argmax(scores))
            row = {**table[f"draw {chosen}"][-1], "row": f"best of {among} by reprojection", "chosen_draw": chosen}
            table.setdefault(row["row"], []).append(row)
            print(f"{spec.name:7s} {row['row']:26s} clDice {row['cldice']:.3f}  Dice {row['dice']:.3f}  components "
                  f"{row['components']}/{row['components_truth']}  (draw {chosen}; mean reprojection Dice of the draws "
                  f"{', '.join(f'{x:.4f}' for x in scores)})", flush=True)
            if args.jsonl is not None:
                with open(args.jsonl, "a") as out:
                    out.write(json.dumps(row) + "\n")
    if len(args.case) > 1:
        draws = np.array([[r["cldice"] for r in rows] for name, rows in table.items() if name.startswith("draw")])
        for name, rows in table.items():
            cl = np.array([r["cldice"] for r in rows])
            print(f"mean    {name:26s} clDice {cl.mean():.4f}  Dice {np.mean([r['dice'] for r in rows]):.4f}  components "
                  f"{np.mean([r['components'] for r in rows]):.1f}  better clDice than draw 0 on "
                  f"{int(np.sum(cl > draws[0]))}/{len(cl)}, than the mean of the draws on {int(np.sum(cl > draws.mean(0)))}/{len(cl)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
