"""What the epipolar check says before a run (``consistency.view_agreement``, ``agreement_warnings``), per case.

    .venv/bin/python bench/view_agreement.py --protocol realistic-static-collimated-lao30-rao30 --suite rca --cases 10
    .venv/bin/python bench/view_agreement.py --protocol realistic-static-lao50cra25-rao50cra25 --suite lad --cases 10 \\
        --masks '{"collimator_fraction": 0.15}' --fault 2 secondary_deg -25

Per case and view: the consistency (centreline with a partner in the other view), the share seen by that view only
(stretches without a partner that continue a vessel into another view's unseen part: collimator, clipped, off the
detector) and the views hiding it; with the frames' unseen parts read as a run reads them (``masks.unseen_pixels``).
``--fault VIEW FIELD VALUE`` gives one view a wrong value (e.g. a flipped secondary angle) after the simulation, to
see whether a wrong geometry still gets the geometry checks named. Then the tally over the cases: how many get the
bare geometry warning, the one-view message with the geometry checks, and the one-view message alone (a case counts
under each its views' messages fall in). No fit runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from SDFCARLib.benchmark import BenchmarkConfig, GridOptions, build_cases, prepare_case  # noqa: E402
from SDFCARLib.benchmark.report import machine_info  # noqa: E402
from SDFCARLib.consistency import GEOMETRY_CHECKS, agreement_warnings, view_agreement  # noqa: E402
from SDFCARLib.geometry import Geometry  # noqa: E402
from SDFCARLib.masks import unseen_pixels  # noqa: E402
from SDFCARLib.settings import PROTOCOLS  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--protocol", required=True, choices=list(PROTOCOLS))
    parser.add_argument("--suite", required=True, choices=("lad", "rca"))
    parser.add_argument("--cases", type=int, default=10)
    parser.add_argument("--masks", default="{}", help="JSON: realistic.RealisticOptions fields over the protocol's")
    parser.add_argument("--fault", nargs=3, metavar=("VIEW", "FIELD", "VALUE"),
                        help="give view VIEW (from 1) the value VALUE of CArmView field FIELD after the simulation")
    args = parser.parse_args()
    overrides = json.loads(args.masks)
    print(f"machine: {machine_info()}; "
          f"{args.protocol} {args.suite} cases 0–{args.cases - 1}, masks {overrides or 'as the protocol'}, "
          f"fault {args.fault or 'none'}", flush=True)
    tally = {"geometry": 0, "one view + geometry checks": 0, "one view alone": 0, "nothing": 0}
    specs = build_cases(BenchmarkConfig(args.suite, Path("unused"), cases=args.cases, grid=GridOptions(),
                                        protocol=args.protocol))
    for spec in specs[:args.cases]:
        case = prepare_case(spec, args.protocol, GridOptions(), overrides or None)
        views = list(case.geometry.views)
        unseen = [unseen_pixels(f, v.pixel_spacing_mm, v.magnification) for f, v in zip(case.frames, views)]
        if args.fault:
            n, field, value = int(args.fault[0]), args.fault[1], float(args.fault[2])
            views[n - 1] = dataclasses.replace(views[n - 1], **{field: value})
        t0 = time.perf_counter()
        agreements = view_agreement(Geometry(case.geometry.volume, tuple(views)),
                                    [np.asarray(m, bool) for m in case.masks], unseen)
        seconds = time.perf_counter() - t0
        warnings = agreement_warnings(agreements)
        kinds = {("one view + geometry checks" if "cannot show them" in w else
                  "one view alone" if "cannot show it" in w else "geometry") for w in warnings
                 if GEOMETRY_CHECKS in w or "cannot show" in w}
        for kind in kinds or {"nothing"}:  # a case counts in every kind one of its views' messages is
            tally[kind] += 1
        kind = ", ".join(sorted(kinds)) or "nothing"
        per_view = "  ".join(f"view {n}: consistency {a.consistency:.3f}, one view only {a.one_view_share:.3f}"
                             f"{' (hidden by view ' + ', '.join(map(str, a.hidden_by)) + ')' if a.hidden_by else ''}"
                             for n, a in enumerate(agreements, start=1))
        print(f"{spec.name}: {per_view}; {kind}; {seconds:.1f} s", flush=True)
    print("tally: " + ", ".join(f"{k} {v}" for k, v in tally.items()))


if __name__ == "__main__":
    main()
