"""The frames' motion search per case, and what the motion found does on the planes no collimator cuts.

    .venv/bin/python bench/untruncated_gain.py --protocol realistic-static-collimated-lao30-rao30 --suite lad --cases 10
    .venv/bin/python bench/untruncated_gain.py --protocol realistic-lao30-rao30 --suite rca --cases 10 \\
        --masks '{"collimator_fraction": 0.15}'

Per case and view: the search as a run makes it (``calibrate_from_frames``: every epipolar plane compared), its
consistency gain, the gain of the same motion on the planes no vessel running into a view's unseen part lies on
(``line_integral_consistency.untruncated_gain``, the frames' unseen parts read as a run reads them), how many such
planes there are, and what the run does with it: applied, or left as given and why (gate, range end, the untruncated
check). The truth's motion of each view is printed beside it. With three views or more the joint search runs, which
is not checked. No fit runs (seconds a case after the simulation; up to a minute with three views).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from SDFCARLib.benchmark.report import machine_info  # noqa: E402
from SDFCARLib.calibration import calibrate_from_frames  # noqa: E402
from SDFCARLib.optimiser import frames_unseen, read_frame_evidence, unknown_pixels  # noqa: E402
from SDFCARLib.settings import make_settings  # noqa: E402
from suite_cases import add_case_arguments, prepared_cases  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_case_arguments(parser)
    args = parser.parse_args()
    overrides = json.loads(args.masks)
    print(f"machine: {machine_info()}; {args.protocol} {args.suite} cases 0–{args.cases - 1}, "
          f"masks {overrides or 'as the protocol'}", flush=True)
    changed = cases = 0
    for spec, case in prepared_cases(args):
        cases += 1
        geometry = case.geometry
        settings = make_settings("fast", seed=spec.seed)
        evidence = read_frame_evidence(case.frames, case.targets, geometry, settings, case.target_kind,
                                       case.frame_intensity)
        unseen = unknown_pixels(case.frames, case.targets, geometry, case.target_kind,
                                frames_unseen(case.frames, geometry, case.target_kind))[0]
        t0 = time.perf_counter()
        checked = calibrate_from_frames(geometry, evidence.images, None,
                                        settings.calibration.calibration_min_consistency_gain, None,
                                        confirm_unseen=unseen,
                                        min_untruncated_gain=settings.calibration.calibration_min_untruncated_gain)
        seconds = time.perf_counter() - t0
        motion = case.info.get("realistic", {}).get("motion") or []
        per_view = []
        for entry in checked.views:  # views 2, 3, … (with three or more: the joint search, not checked)
            k = entry["view"] - 1
            applied = checked.geometry.views[k] != geometry.views[k]
            untruncated = entry.get("untruncated_consistency_gain")
            stopped = "hides what the field of view cuts" in str(entry.get("why_left_as_given", ""))
            changed += stopped
            truth = motion[k] if len(motion) > k else None
            truth_text = ("none" if truth is None else
                          f"{np.linalg.norm(truth['rotation_deg']):.2f}° / {np.linalg.norm(truth['translation_mm']):.2f} mm")
            per_view.append(
                f"view {k + 1}: gain {entry.get('consistency_gain')}, on the untruncated planes "
                f"{'—' if untruncated is None else untruncated} ({entry.get('untruncated_planes', '—')} planes); "
                f"{'applied' if applied else 'left as given: ' + str(entry.get('why_left_as_given', ''))[:60]}"
                f"{' (the check)' if stopped else ''}; truth motion {truth_text}")
        print(f"{spec.name}: {'  '.join(per_view)}; {seconds:.0f} s", flush=True)
    print(f"views left as given by the untruncated check: {changed} (of {cases} cases)")


if __name__ == "__main__":
    main()
