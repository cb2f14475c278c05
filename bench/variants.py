"""Settings variants side by side on benchmark cases: the same prepared input, the default first.

    .venv/bin/python bench/variants.py --suite rca --case 0 1 2 3 --protocol realistic-static-lao30-rao30 \
        --grid80 '{"prune": false}' '{"dt_downsample": 4}'

Each variant is a JSON object of setting overrides (``settings.py`` keys) on the ``fast`` preset;
the first row is always the unchanged preset. ``--finish-only``: each case's field is fitted once (the
preset) and finished once per variant, so variants of the finishing rules (``FINISH_ONLY_KEYS``) differ only
in the rule, at one fit's cost. ``--save DIR`` keeps each run's report.json, occupancy, result,
truth and masks for offline study. The realistic protocols' angiograms are given as the
benchmark gives them (``frames``: evidence and motion read off them). Prints clDice, Dice, components (result / truth),
support voxels and wall time per variant (with the scoring; the reconstruction's own and its phases in
brackets), and the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from SDFCARLib.benchmark import BenchmarkConfig, GridOptions, build_cases, prepare_case  # noqa: E402
from SDFCARLib.metrics import evaluate  # noqa: E402
from SDFCARLib.optimiser import fit_field, reconstruct  # noqa: E402
from SDFCARLib.settings import PROTOCOLS, REALISTIC_PROTOCOLS, make_settings  # noqa: E402


def save_run(folder: Path, stem: str, case, result) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(folder / f"{stem}.npz", occupancy=result.occupancy.astype(np.float16),
                        segmentation=result.segmentation.astype(bool), label=case.label.astype(bool),
                        masks=np.stack([np.asarray(m, bool) for m in case.masks]))
    case.geometry.save(folder / f"{stem}.json")
    # what each step removed, joined and found (width_exclusion, pruning, …), to read the run's why
    (folder / f"{stem}-report.json").write_text(json.dumps(result.report, indent=1, default=str))


# settings only ``finish`` reads in ``fast`` (pruning reaches the fit only with exclusion_takes_finishing_removals)
FINISH_ONLY_KEYS = ("prune", "prune_tolerance", "prune_keep_connected", "drop_unconfirmed_fragments", "reconnect",
                    "reconnect_max_gap_mm", "reconnect_min_occupancy", "reconnect_every_component", "grow_threshold", "final_reconnect_max_gap_mm",
                    "min_fragment_volume_mm3", "fill_unexplained", "prune_last",
                    "prune_last_only_without_motion", "prune_split_pieces",
                    "prune_last_min_views_any_motion")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", default="rca")
    parser.add_argument("--case", type=int, nargs="+", default=[0], help="case indices of the suite (their seeds)")
    parser.add_argument("--protocol", default="realistic-static-lao30-rao30", choices=sorted(PROTOCOLS))
    parser.add_argument("--grid80", action="store_true", help="80³ at 1.3 mm, 192² at 0.8 mm (section 1's coarse grid)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--save", type=Path, default=None,
                        help="folder: one .npz per case and variant (occupancy, result, truth label, masks), its geometry .json and its report, to study offline")
    parser.add_argument("--skip-default", action="store_true",
                        help="run only the variants (the preset's own runs already saved; deterministic on one thread)")
    parser.add_argument("--masks", type=json.loads, default=None,
                        help='JSON object of realistic.RealisticOptions overrides for every run, e.g. \'{"mask_edge_fraction": 0.2}\' '
                             '(the masks segmented otherwise; realistic protocols only)')
    parser.add_argument("--finish-only", action="store_true",
                        help="fit each case once and finish it once per variant (variants of FINISH_ONLY_KEYS only)")
    parser.add_argument("--frame-intensity", default=None, metavar="LIN|DISP|none",
                        help="every view's frames handed over with this Pixel Intensity Relationship instead of the "
                             "protocol's (none: not known, as arrays from Python or a PNG in Slicer)")
    parser.add_argument("--frames-8bit", action="store_true",
                        help="every view's frames handed over as 8-bit grey levels, linearly (0 … its largest value → "
                             "0 … 255, rounded), as a linear frame exported to PNG; the masks are the protocol's")
    parser.add_argument("variants", nargs="*", help="JSON objects of setting overrides")
    args = parser.parse_args()
    if args.masks and args.protocol not in REALISTIC_PROTOCOLS:
        parser.error(f"--masks changes masks segmented from simulated angiograms; {args.protocol} projects its masks "
                     f"from the truth: give a realistic protocol ({', '.join(sorted(REALISTIC_PROTOCOLS))})")
    torch.set_num_threads(args.threads)
    grid = GridOptions((80, 80, 80), 1.3, (192, 192), 0.8) if args.grid80 else GridOptions()
    config = BenchmarkConfig(args.suite, Path("unused"), cases=max(args.case) + 1, grid=grid, protocol=args.protocol)
    variants = [{}] + [json.loads(text) for text in args.variants]
    if args.finish_only:
        others = sorted({key for v in variants for key in v if key not in FINISH_ONLY_KEYS})
        if others or args.skip_default:
            parser.error(f"--finish-only finishes one fit per case: {', '.join(others) or '--skip-default'} would need "
                         f"fits of their own; give only {', '.join(FINISH_ONLY_KEYS)}")
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"{args.threads} thread(s); {args.suite} cases {args.case}, {args.protocol}, "
          f"{'grid80' if args.grid80 else 'paper grid'}{'; masks ' + json.dumps(args.masks) if args.masks else ''}"
          f"{'; frame intensity ' + args.frame_intensity if args.frame_intensity else ''}"
          f"{'; frames as 8-bit' if args.frames_8bit else ''}", flush=True)
    scores: dict = {json.dumps(v): [] for v in variants}
    for index in args.case:
        spec = build_cases(config)[index]
        case = prepare_case(spec, args.protocol, grid, realistic_overrides=args.masks)
        if args.frame_intensity is not None and case.frames is not None:
            case.frame_intensity = (None if args.frame_intensity.lower() == "none"
                                    else [args.frame_intensity.upper()] * len(case.frames))
        if args.frames_8bit and case.frames is not None:
            case.frames = [np.round(np.asarray(f, np.float64) * (255.0 / float(np.max(f)))).astype(np.uint8)
                           for f in case.frames]
        fitted = (fit_field(case.geometry, case.targets, make_settings("fast", seed=spec.seed), case.target_kind,
                            frames=case.frames, frame_intensity=case.frame_intensity) if args.finish_only else None)
        for number, variant in enumerate(variants):
            if number == 0 and args.skip_default:
                continue
            t0 = time.perf_counter()
            # the fit's seed is the case's unless the variant sets it (another draw of the same case)
            settings = make_settings("fast", **{"seed": spec.seed, **variant})
            result = (fitted.finished(settings) if fitted is not None
                      else reconstruct(case.geometry, case.targets, settings, case.target_kind, frames=case.frames,
                                       frame_intensity=case.frame_intensity))
            m = evaluate(result.segmentation, case.label, case.geometry.volume, case.geometry.views, case.masks)
            if args.save is not None:
                save_run(args.save, f"{spec.name}-v{number}", case, result)
            timings = result.report["timings_s"]
            scores[json.dumps(variant)].append((m["cldice"], m["dice"], m.get("components")))
            print(f"{spec.name:7s} {json.dumps(variant):40s} clDice {m['cldice']:.3f}  Dice {m['dice']:.3f}  components "
                  f"{m.get('components')}/{m.get('components_label')}  support {result.report['support_voxels']}  "
                  f"motion found {result.report['motion_found']}  "
                  f"{time.perf_counter() - t0:.0f} s (reconstruction {timings['total']:.0f}: setup {timings['setup']:.0f}, optimise {timings['optimise']:.0f}, "
                  f"{1000 * timings['per_step']:.0f} ms/step, output {timings['output']:.0f}; {result.report['device']})",
                  flush=True)
    if len(args.case) > 1 and not args.skip_default:
        default = np.array(scores[json.dumps({})])
        for key, rows in scores.items():
            rows = np.array(rows)
            wins = int(np.sum(rows[:, 0] > default[:, 0]))
            print(f"mean    {key:40s} clDice {rows[:, 0].mean():.3f}  Dice {rows[:, 1].mean():.3f}  components "
                  f"{rows[:, 2].mean():.1f}  better clDice than default on {wins}/{len(rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
