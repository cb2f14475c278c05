"""Mask oracles on realistic cases: `fast` given the segmented masks, the true silhouettes, or the segmented
masks less their extra pixels / plus their missed ones, with or without the frames (paper grid, one thread).

    .venv/bin/python bench/mask_oracles.py lad 0,1 default,truemasks,noextra,nomissed     # suite, cases, variants
    .venv/bin/python bench/mask_oracles.py lad 0,1 truemasks '{"frame_excess_factor": 1.5}'   # settings on `fast`

Variants: default (the segmented masks and frames, as the benchmark gives them), truemasks (the true
silhouettes, same frames), noframes, truenoframes, noextra (segmented ∩ true), nomissed (segmented ∪ true),
refined_SIGMA_T (the frame trim of ``evidence.border_trimmed_mask``: pixels whose path length, smoothed by
SIGMA px, is below T mm removed). The true silhouettes are for these oracles only: no method may read them
(bench/RESULTS.md §56b, §57a).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from SDFCARLib.benchmark import BenchmarkConfig, GridOptions, build_cases, prepare_case  # noqa: E402
from SDFCARLib.evidence import border_trimmed_mask, view_evidence  # noqa: E402
from SDFCARLib.metrics import evaluate  # noqa: E402
from SDFCARLib.optimiser import reconstruct  # noqa: E402
from SDFCARLib.realistic import RealisticOptions, realistic_input  # noqa: E402
from SDFCARLib.settings import REALISTIC_PROTOCOLS, make_settings  # noqa: E402

PROTOCOL = "realistic-static-lao30-rao30"


def variant_masks(name, case, segmented, true):
    """(masks, frames) of one variant of the module docstring."""
    fixed = {"default": (segmented, case.frames), "truemasks": (true, case.frames), "noframes": (segmented, None),
             "truenoframes": (true, None), "noextra": ([s & t for s, t in zip(segmented, true)], case.frames),
             "nomissed": ([s | t for s, t in zip(segmented, true)], case.frames)}
    if name in fixed:
        return fixed[name]
    if name.startswith("refined_"):
        _, sigma_px, min_path_mm = name.split("_")
        trimmed = [border_trimmed_mask(m, view_evidence(f, m, v).line_integral_mm, float(min_path_mm), float(sigma_px))
                   for m, f, v in zip(segmented, case.frames, case.geometry.views)]
        return trimmed, case.frames
    raise SystemExit(f"unknown variant {name!r}: see the docstring")


def main() -> None:
    suite, cases, names = sys.argv[1], [int(c) for c in sys.argv[2].split(",")], sys.argv[3].split(",")
    overrides = json.loads(sys.argv[4]) if len(sys.argv) > 4 else {}
    torch.set_num_threads(1)
    grid = GridOptions()
    specs = build_cases(BenchmarkConfig(suite, Path("unused"), cases=max(cases) + 1, grid=grid, protocol=PROTOCOL))
    for index in cases:
        spec = specs[index]
        case = prepare_case(spec, PROTOCOL, grid)
        real = realistic_input(case.label, case.geometry, spec.seed, RealisticOptions(**REALISTIC_PROTOCOLS[PROTOCOL]))
        assert all((a == b).all() for a, b in zip(real.masks, case.masks)), "the benchmark's masks are not these"
        true = [np.asarray(t, bool) for t in real.true_masks]
        segmented = [np.asarray(m, bool) for m in case.masks]
        pixels = [(int(t.sum()), int((t & ~s).sum()), int((s & ~t).sum())) for t, s in zip(true, segmented)]
        print(f"{spec.name} true/missed/extra px per view {pixels}", flush=True)
        for name in names:
            masks, frames = variant_masks(name, case, segmented, true)
            print(f"{spec.name} {name} extra {[int((a & ~t).sum()) for a, t in zip(masks, true)]} "
                  f"missed {[int((t & ~a).sum()) for a, t in zip(masks, true)]}", flush=True)
            t0 = time.perf_counter()
            result = reconstruct(case.geometry, [m.astype(np.float32) for m in masks],
                                 make_settings("fast", seed=spec.seed, **overrides), "mask", frames=frames)
            m = evaluate(result.segmentation, case.label, case.geometry.volume, case.geometry.views, segmented)
            print(f"{spec.name} {name:12s} clDice {m['cldice']:.3f} Tprec {m['tprec']:.3f} Tsens {m['tsens']:.3f} "
                  f"Dice {m['dice']:.3f} pieces {m.get('components')} {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
