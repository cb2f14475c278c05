"""Which benchmark cases the pose check before the fit calls aligned: per case, the frames' check
(``optimiser.check_poses`` with ``fast``'s settings, as a run makes it) and what it found per view.

    .venv/bin/python bench/motion_gate.py --suite lad rca --case 0 1 2 3 4 \
        --protocol realistic-lao30-rao30 realistic-static-lao30-rao30

``motion_found`` (``Calibration.motion_found``): True a motion was found and applied, False every view was
searched and moved less than noise allows, None it could not tell. ``prune_last_only_without_motion``
prunes last only on False. Seconds per case: the case's simulation and the check, no fit. Prints the machine.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from SDFCARLib.benchmark import BenchmarkConfig, GridOptions, build_cases, prepare_case  # noqa: E402
from SDFCARLib.optimiser import check_poses, motion_found_by, read_frame_evidence  # noqa: E402
from SDFCARLib.settings import REALISTIC_PROTOCOLS, make_settings  # noqa: E402


def outcome(entry: dict) -> str:
    if entry.get("skipped"):
        return "not searched"
    if entry.get("motion_found") is True:
        return f"applied ({entry.get('consistency_gain')}×)"
    if entry.get("motion_found") is False:
        return f"noise ({entry.get('consistency_gain')}×)"
    return f"left as given ({entry.get('consistency_gain')}×, {str(entry.get('why_left_as_given', ''))[:40]})"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", nargs="+", default=["rca"])
    parser.add_argument("--case", type=int, nargs="+", default=[0])
    parser.add_argument("--protocol", nargs="+", default=["realistic-static-lao30-rao30"], choices=sorted(REALISTIC_PROTOCOLS))
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, {args.threads} thread(s); paper grid",
          flush=True)
    grid = GridOptions()
    for protocol in args.protocol:
        counts = {True: 0, False: 0, None: 0}
        for suite in args.suite:
            config = BenchmarkConfig(suite, Path("unused"), cases=max(args.case) + 1, grid=grid, protocol=protocol)
            specs = build_cases(config)
            for index in args.case:
                t0 = time.perf_counter()
                spec = specs[index]
                case = prepare_case(spec, protocol, grid)
                settings = make_settings("fast", seed=spec.seed)
                evidence = read_frame_evidence(case.frames, case.targets, case.geometry, settings, case.target_kind,
                                               case.frame_intensity)
                calibrations, _ = check_poses(case.geometry, case.targets, settings, case.target_kind, case.frames, evidence)
                found = motion_found_by(calibrations)
                counts[found] += 1
                views = [entry for c in calibrations for entry in c.views]
                print(f"{protocol} {spec.name:7s} motion_found {str(found):5s}  "
                      + "; ".join(f"view {e['view']}: {outcome(e)}" for e in views)
                      + f"  {time.perf_counter() - t0:.0f} s", flush=True)
        print(f"# {protocol}: motion found {counts[True]}, none beyond noise {counts[False]}, not known {counts[None]}",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
