"""Polarity of angiography frames: the dark-vessel asymmetry (``masks.thin_structure_contrasts``, dark over bright)
of frames with dark vessels, of the same frames inverted (lowest + highest − value, an inverted display's export)
and of frames without vessels; and whether ``bright_vessels=True`` gives an inverted frame the mask of the original
(Dice between the two).

    python bench/frame_polarity.py --protocol realistic-static-lao30-rao30 --cases 10 --extra --tubes \\
        --real ../shared/data/xa-phantom

Per frame the contrasts are read where ``segment_angiogram`` computes them (on its field, before the ridge filter), so the
values are the pipeline's own. Prints one JSON line per frame and a summary per group (minimum, maximum) with the
levels ``MIN_DARK_VESSEL_ASYMMETRY`` (refused below) and ``DOUBTFUL_DARK_VESSEL_ASYMMETRY`` (a warning below).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

import SDFCARLib.masks as masks  # noqa: E402


class _Measured(Exception):
    pass


def asymmetry(frame, spacing, magnification, settings=None):
    """The pipeline's polarity reading of ``frame`` (``masks.judge_polarity``; the segmentation is stopped right
    after it): the asymmetry at each tail of ``POLARITY_TAILS_PCT`` (None: that tail not judged), the contrasts
    (dark, bright) of the 1 % tail, and the verdict."""
    judge, seen = masks.judge_polarity, []

    def record(*args, **kwargs):
        seen.append(judge(*args, **kwargs))
        raise _Measured

    masks.judge_polarity = record
    try:
        masks.segment_angiogram(np.asarray(frame, float), spacing, magnification, settings)
    except _Measured:
        pass
    finally:
        masks.judge_polarity = judge
    reading = seen[0]
    rounded = [None if a is None else round(a, 3) for a in reading.asymmetries]
    return rounded, [round(c, 4) for c in reading.contrasts[0]], reading.verdict


def _simulated_frames(realistic, label, geometry, seed, options):
    """The frames ``realistic.realistic_input`` simulates for the views of ``geometry`` and the arguments it segments
    each with (no segmentation runs: an empty mask stands in)."""
    from types import SimpleNamespace

    seen = []

    def record(frame, spacing, magnification, settings):
        seen.append((np.asarray(frame, float), spacing, magnification, settings))
        return SimpleNamespace(mask=np.zeros(np.shape(frame), bool), parameters={})

    segment, realistic.segment_angiogram = realistic.segment_angiogram, record
    try:
        realistic.realistic_input(label, geometry, seed, options)
    finally:
        realistic.segment_angiogram = segment
    return seen


def inverted(frame) -> np.ndarray:
    frame = np.asarray(frame, float)
    return frame.min() + frame.max() - frame


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--protocol", default="realistic-static-lao30-rao30", help="a realistic protocol (its frames)")
    parser.add_argument("--cases", type=int, default=5, help="LAD and RCA cases 0..N-1")
    parser.add_argument("--extra", action="store_true", help="also 8 simulated frames without vessels")
    parser.add_argument("--tubes", action="store_true", help="also the frames of bench/qca.py's ten lone stenosed tubes, "
                        "with their random axes and at 5° and 45° elevation (two views each)")
    parser.add_argument("--real", type=Path, default=None, help="folder of the IM2, IM3, IM7 XA runs (four frames each)")
    args = parser.parse_args(argv)
    from SDFCARLib.angiogram import AngiogramSettings, simulate_angiogram
    from SDFCARLib.benchmark.cases import CaseSpec, prepare_case

    print(f"machine: {platform.machine()} {platform.processor() or ''}, {os.cpu_count()} cores, "
          f"python {platform.python_version()}, one thread", flush=True)
    started = time.perf_counter()
    groups = {}

    def row(group, name, frame, spacing, magnification, settings=None, check_inversion=False):
        dark, dark_contrasts, dark_verdict = asymmetry(frame, spacing, magnification, settings)
        inv, inv_contrasts, inv_verdict = asymmetry(inverted(frame), spacing, magnification, settings)
        # per tail of POLARITY_TAILS_PCT; None: not judged (the thin structures of both sides under MIN_POLARITY_CONTRAST)
        entry = {"group": group, "name": name, "dark": dark, "dark_verdict": dark_verdict, "inverted": inv,
                 "inverted_verdict": inv_verdict, "thin_contrasts": dark_contrasts, "inverted_thin_contrasts": inv_contrasts}
        if check_inversion:
            from dataclasses import replace

            base = settings or masks.AngioMaskSettings()
            original = masks.segment_angiogram(np.asarray(frame, float), spacing, magnification, base).mask
            told = masks.segment_angiogram(inverted(frame), spacing, magnification, replace(base, bright_vessels=True)).mask
            entry["bright_vessels_mask_dice"] = round(float(2 * (original & told).sum() / (original.sum() + told.sum())), 4)
        groups.setdefault(group, []).append(entry)
        print(json.dumps(entry), flush=True)

    display = "display" in args.protocol
    settings = masks.mask_settings_for_intensity("DISP" if display else None)
    for suite in ("lad", "rca"):
        for seed in range(args.cases):
            case = prepare_case(CaseSpec(suite=suite, name=f"{suite}{seed}", tree=suite, seed=seed, index=seed),
                                args.protocol)
            for v, (frame, view) in enumerate(zip(case.frames, case.geometry.views), start=1):
                row(args.protocol, f"{suite}{seed} view {v}", frame, view.pixel_spacing_mm, view.magnification, settings,
                    check_inversion=seed == 0)
            if seed < 3:  # the same tree behind a collimator (12 % of each side), as an inverted export shows it white
                from SDFCARLib.phantoms import simulate_views
                from SDFCARLib.settings import MASK_THRESHOLD_MM

                line_integrals, _ = simulate_views(case.label, case.geometry.volume, case.geometry.views, MASK_THRESHOLD_MM)
                for v, (integral, view) in enumerate(zip(line_integrals, case.geometry.views), start=1):
                    frame, _ = simulate_angiogram(integral, view.pixel_spacing_mm, seed,
                                                  AngiogramSettings(collimator_fraction=0.12))
                    row("behind a collimator", f"{suite}{seed} view {v}", frame, view.pixel_spacing_mm,
                        view.magnification, settings)
    if args.extra:
        for seed in range(8):
            frame, _ = simulate_angiogram(np.zeros((512, 512)), 0.278, seed,
                                          AngiogramSettings(collimator_fraction=0.04 * (seed % 2)))
            row("without vessels", f"seed {seed}", frame, 0.278, 1000 / 757)
    if args.tubes:  # lone stenosed tubes (bench/qca.py's recon suite), each frame as the realistic protocol simulates it
        sys.path.insert(0, str(REPO / "bench"))
        import qca
        import SDFCARLib.realistic as realistic
        from SDFCARLib.analysis.phantoms import stenosed_tube
        from SDFCARLib.geometry import Geometry
        from SDFCARLib.settings import REALISTIC_PROTOCOLS

        options = realistic.RealisticOptions(**REALISTIC_PROTOCOLS["realistic-static-lao30-rao30"])
        for elevation in (None, 5.0, 45.0):  # the suite's random axes; along / across LAO 30 / RAO 30's epipolar planes
            for n, (name, kw) in enumerate(qca.RECON_TUBES):
                direction = (qca.tube_direction(n) if elevation is None else
                             np.array([np.cos(np.radians(elevation)), 0.0, np.sin(np.radians(elevation))]))
                tree = stenosed_tube(length_mm=40.0, direction=direction, **kw).tree
                grid = qca.grid_around(tree, 0.2)
                label = qca.voxelize_exact(tree, grid)
                # the pair's frames as the protocol draws them (one noise stream over both views)
                frames = _simulated_frames(realistic, label, Geometry(grid, qca.VIEWS[:2]), n, options)
                for v, (frame, spacing, magnification, view_settings) in enumerate(frames, start=1):
                    row("lone tubes" + ("" if elevation is None else f", axis at {elevation:g}° elevation"),
                        f"{name} view {v}", frame, spacing, magnification, view_settings)
    if args.real:
        from SDFCARLib.dicom import choose_frame, load_xa, view_from_dicom

        for name in ("IM2", "IM3", "IM7"):
            run = load_xa(args.real / name)
            n = run.frames.shape[0]
            for index in sorted({choose_frame(run).index, 0, n // 2, n - 1}):
                view, _ = view_from_dicom(run, index)
                row("real XA", f"{name} frame {index}", run.frames[index], view.pixel_spacing_mm, view.sid_mm / view.sod_mm)
    print(f"\nper tail {masks.POLARITY_TAILS_PCT} %: refused below {masks.MIN_DARK_VESSEL_ASYMMETRY}, warned below "
          f"{masks.DOUBTFUL_DARK_VESSEL_ASYMMETRY}, unless a tail reaches {masks.CLEAR_DARK_VESSEL_ASYMMETRY}")

    def span(values):
        judged = [v for v in values if v is not None]
        unjudged = len(values) - len(judged)
        text = f"{min(judged):.3f}–{max(judged):.3f}" if judged else "—"
        return text + (f" ({unjudged} not judged)" if unjudged else "")

    for group, rows in groups.items():
        tails = "; ".join(f"{tail:g} % tail: dark {span([r['dark'][k] for r in rows])}, inverted "
                          f"{span([r['inverted'][k] for r in rows])}" for k, tail in enumerate(masks.POLARITY_TAILS_PCT))
        count = lambda key, verdict: sum(r[key] == verdict for r in rows)  # noqa: E731
        print(f"{group}: {len(rows)} frames; {tails}; inverted refused {count('inverted_verdict', 'bright')}/{len(rows)} "
              f"(warned {count('inverted_verdict', 'doubtful')}), dark ones refused {count('dark_verdict', 'bright')} "
              f"(warned {count('dark_verdict', 'doubtful')})")
    print(f"{time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
