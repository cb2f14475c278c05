"""Mask oracles on realistic cases: `fast` given the segmented masks, the true silhouettes, or the segmented
masks less their extra pixels / plus their missed ones, with or without the frames (paper grid, one thread).

    .venv/bin/python bench/mask_oracles.py lad 0,1 default,truemasks,noextra,nomissed     # suite, cases, variants

Variants: default (the segmented masks and frames, as the benchmark gives them), truemasks (the true
silhouettes, same frames), noframes, truenoframes, noextra (segmented ∩ true), nomissed (segmented ∪ true),
refined_SIGMA_T (pixels whose path length, smoothed by SIGMA px, is below T mm removed). The true silhouettes
are for these oracles only: no method may read them (bench/RESULTS.md §56b, §57a).
"""
import sys, time
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import numpy as np, torch
torch.set_num_threads(1)
from SDFCARLib.benchmark import BenchmarkConfig, GridOptions, build_cases, prepare_case
from SDFCARLib.metrics import evaluate
from SDFCARLib.optimiser import reconstruct
from SDFCARLib.settings import make_settings, REALISTIC_PROTOCOLS
from SDFCARLib.realistic import RealisticOptions, realistic_input
from SDFCARLib.evidence import view_evidence
from scipy import ndimage
from skimage.morphology import skeletonize

suite = sys.argv[1]
cases = [int(c) for c in sys.argv[2].split(",")]
which = sys.argv[3].split(",")  # the variants of the docstring
protocol = "realistic-static-lao30-rao30"
grid = GridOptions()
config = BenchmarkConfig(suite, Path("unused"), cases=max(cases) + 1, grid=grid, protocol=protocol)
specs = build_cases(config)
for index in cases:
    spec = specs[index]
    case = prepare_case(spec, protocol, grid)
    real = realistic_input(case.label, case.geometry, spec.seed, RealisticOptions(**REALISTIC_PROTOCOLS[protocol]))
    assert all((a == b).all() for a, b in zip(real.masks, case.masks)), "masks differ"
    true = [np.asarray(t, bool) for t in real.true_masks]
    seg = [np.asarray(m, bool) for m in case.masks]
    px = [(int(t.sum()), int((t & ~s).sum()), int((s & ~t).sum())) for t, s in zip(true, seg)]
    print(f"{spec.name} true/missed/extra px per view {px}", flush=True)
    def refine(sigma, t):
        out = []
        for m, f, v in zip(seg, case.frames, case.geometry.views):
            e = ndimage.gaussian_filter(view_evidence(f, m, v).line_integral_mm, sigma)
            out.append((m & (e >= t)) | skeletonize(m))
        return out
    for name in which:
        if name.startswith("refined"):
            _, s_, t_ = name.split("_")
            r_ = refine(float(s_), float(t_))
            print(f"{spec.name} {name} mask px {[int(a.sum()) for a in r_]} extra {[int((a & ~t).sum()) for a, t in zip(r_, true)]} missed {[int((t & ~a).sum()) for a, t in zip(r_, true)]}", flush=True)
    variants = {"default": (seg, case.frames), "truemasks": (true, case.frames), "noframes": (seg, None),
                "truenoframes": (true, None), "noextra": ([s & t for s, t in zip(seg, true)], case.frames), "nomissed": ([s | t for s, t in zip(seg, true)], case.frames)}
    for name in which:
        if name.startswith("refined"):
            _, s_, t_ = name.split("_")
            variants[name] = (refine(float(s_), float(t_)), case.frames)
        masks, frames = variants[name]
        t0 = time.perf_counter()
        r = reconstruct(case.geometry, [m.astype(np.float32) for m in masks], make_settings("fast", seed=spec.seed),
                        "mask", frames=frames)
        m = evaluate(r.segmentation, case.label, case.geometry.volume, case.geometry.views, seg)
        cal = r.report.get("frame_calibration") or r.report.get("calibration")
        print(f"{spec.name} {name:12s} clDice {m['cldice']:.3f} Tprec {m['tprec']:.3f} Tsens {m['tsens']:.3f} "
              f"Dice {m['dice']:.3f} pieces {m.get('components')} {time.perf_counter() - t0:.0f} s", flush=True)
