"""Finishing rules side by side on a pair of real XA runs, as ``reconstruct --dicom A B --auto-masks`` prepares them.

    .venv/bin/python bench/dicom_finishing.py --dicom ../shared/data/xa-phantom/IM3 ../shared/data/xa-phantom/IM7 \
        --threads 1 '{"prune_keep_connected": true}' '{"reconnect_every_component": true}'

The geometry from the runs' tags, the masks from the segment pipeline, the grid placed on them and the frames
with their Pixel Intensity Relationship exactly as the command line does (its own functions); the field is
fitted once (``fast``) and finished once per variant (``bench/variants.py``'s FINISH_ONLY_KEYS), the first
the preset as it is. There is no 3D truth: each row gives what can be measured — the reprojection Dice per
view, the share of each mask left unexplained, the voxels, the pieces and the largest piece's share — and
the finishing time. Prints the machine.

``--save-fit FILE`` keeps the fitted field (a few hundred MB on this pair) and ``--load-fit FILE`` finishes it again
without fitting, so that finishing code can be compared or profiled (``--profile N``) on one fit.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import platform
import pstats
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.variants import FINISH_ONLY_KEYS  # noqa: E402
from SDFCARLib.cli.parser import build_parser  # noqa: E402
from SDFCARLib.cli.reconstruct import _auto_masks, _geometry_for_reconstruct, _place_grid  # noqa: E402
from SDFCARLib.metrics import component_counts  # noqa: E402
from SDFCARLib.optimiser import fit_field  # noqa: E402
from SDFCARLib.settings import make_settings  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dicom", nargs=2, required=True, metavar="RUN", help="two XA DICOM runs")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--mask-edge-fraction", type=float, default=None, metavar="F",
                        help="segment the masks with this AngioMaskSettings.edge_fraction (0: no edge rule) instead of the default")
    parser.add_argument("--display-as-log", action="store_true",
                        help="frames not read as LIN (DISP, a vendor's term) read as a LOG run with the header's sign "
                             "(dicom.intensity.linear_from_log), so their path lengths are fitted")
    parser.add_argument("--save-fit", metavar="FILE", help="keep the fitted field here (torch.save) to finish it again later")
    parser.add_argument("--load-fit", metavar="FILE",
                        help="finish a fit kept by --save-fit instead of fitting (the same runs and options must be given)")
    parser.add_argument("--profile", type=int, default=0, metavar="N",
                        help="profile each variant's finish (cProfile) and print its N most expensive calls by cumulative time")
    parser.add_argument("variants", nargs="*", help="JSON objects of finishing-setting overrides on fast")
    args = parser.parse_args()
    variants = [{}] + [json.loads(text) for text in args.variants]
    others = sorted({key for v in variants for key in v if key not in FINISH_ONLY_KEYS})
    if others:
        parser.error(f"{', '.join(others)} would need fits of their own; give only {', '.join(FINISH_ONLY_KEYS)}")
    torch.set_num_threads(args.threads)
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"{args.threads} thread(s); {' + '.join(Path(r).name for r in args.dicom)}", flush=True)
    cli = build_parser().parse_args(["reconstruct", "--dicom", *args.dicom, "--auto-masks", "--out", "unused",
                                     "--threads", str(args.threads), "--no-progress"])
    geometry, provenance, request = _geometry_for_reconstruct(cli)
    auto, intensity = _auto_masks(cli, geometry, provenance)
    masks = [a.mask for _, _, a in auto]
    frames = [frame for _, frame, _ in auto]
    print(f"# frames' Pixel Intensity Relationship as read: {intensity}", flush=True)
    if args.mask_edge_fraction is not None:
        from SDFCARLib.masks import AngioMaskSettings, segment_angiogram

        masks = [segment_angiogram(f, v.pixel_spacing_mm, v.sid_mm / v.sod_mm,
                                   AngioMaskSettings(edge_fraction=args.mask_edge_fraction)).mask
                 for f, v in zip(frames, geometry.views)]
        print(f"# masks segmented with edge_fraction {args.mask_edge_fraction}", flush=True)
    if args.display_as_log:
        from SDFCARLib.dicom.intensity import intensity_tags_of_file, linear_from_log

        tags = [intensity_tags_of_file(r) for r in args.dicom]
        read = [i == "LIN" for i in intensity or [None] * len(frames)]
        frames = [f if lin else linear_from_log(f, t.larger_means_more_intensity(t.photometric == "MONOCHROME1")[0], t.bits_stored)
                  for f, t, lin in zip(frames, tags, read)]
        intensity = ["LIN"] * len(frames)
        print(f"# frames not LIN read as LOG: {[not r for r in read]}", flush=True)
    geometry, _, source = _place_grid(geometry, masks, request, provenance)
    print(f"# grid {list(geometry.volume.shape)} at {geometry.volume.spacing_mm[0]} mm ({source})", flush=True)
    t0 = time.perf_counter()
    if args.load_fit:
        fitted = torch.load(args.load_fit, weights_only=False)  # our own file, written by --save-fit
        if tuple(fitted.problem.geometry.volume.shape) != tuple(geometry.volume.shape):
            parser.error(f"{args.load_fit} holds a fit on a {list(fitted.problem.geometry.volume.shape)} grid, these runs "
                         f"give {list(geometry.volume.shape)}: give the runs and options it was fitted with")
        print(f"# fit loaded from {args.load_fit}", flush=True)
    else:
        fitted = fit_field(geometry, masks, make_settings("fast", threads=args.threads), "mask",
                           frames=frames, frame_intensity=intensity)
    if args.save_fit:
        torch.save(fitted, args.save_fit)
    print(f"# {'loaded' if args.load_fit else f'fitted in {time.perf_counter() - t0:.0f} s'}; the pose check found motion: {fitted.problem.motion_found} "
          f"({'; '.join(str(e.get('why_left_as_given') or e.get('skipped') or 'applied') for c in fitted.calibrations for e in c.views) or 'no check'})",
          flush=True)
    for variant in variants:
        t1 = time.perf_counter()
        profiler = cProfile.Profile() if args.profile else None
        if profiler:
            profiler.enable()
        result = fitted.finished(make_settings("fast", threads=args.threads, **variant))
        if profiler:
            profiler.disable()
            pstats.Stats(profiler, stream=sys.stdout).sort_stats("cumulative").print_stats(args.profile)
        report = result.report
        pieces = component_counts(result.segmentation)
        unexplained = [q["share_of_mask"]["mask_only"] for q in report["reprojection_qa"]]
        print(f"{json.dumps(variant):42s} reprojection Dice {' / '.join(f'{d:.3f}' for d in report['reprojection_dice'])}  "
              f"unexplained {' / '.join(f'{100 * u:.0f} %' for u in unexplained)}  "
              f"voxels {int(result.segmentation.sum())}  pieces {pieces['components']} "
              f"(largest {100 * pieces['largest_component_fraction']:.0f} %)  finish {time.perf_counter() - t1:.0f} s",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
