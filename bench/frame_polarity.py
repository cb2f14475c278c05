"""Polarity of angiography frames: the dark-vessel asymmetry (``masks.thin_structure_contrasts``, dark over bright)
of frames with dark vessels, of the same frames inverted (lowest + highest − value, an inverted display's export)
and of frames without vessels; and whether ``bright_vessels=True`` gives an inverted frame the mask of the original
(Dice between the two).

    python bench/frame_polarity.py --protocol realistic-static-lao30-rao30 --cases 10 --extra \\
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
    """The pipeline's (dark, bright) thin-structure contrasts of ``frame`` and their ratio, the asymmetry (the
    segmentation is stopped right after they are measured)."""
    measure, seen = masks.thin_structure_contrasts, []

    def record(*args, **kwargs):
        seen.append(measure(*args, **kwargs))
        raise _Measured

    masks.thin_structure_contrasts = record
    try:
        masks.segment_angiogram(np.asarray(frame, float), spacing, magnification, settings)
    except _Measured:
        pass
    finally:
        masks.thin_structure_contrasts = measure
    dark, bright = seen[0]
    judged = max(dark, bright) >= masks.MIN_POLARITY_CONTRAST
    return (dark / bright if bright > 0 else float("inf")) if judged else None, round(dark, 4), round(bright, 4)


def inverted(frame) -> np.ndarray:
    frame = np.asarray(frame, float)
    return frame.min() + frame.max() - frame


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--protocol", default="realistic-static-lao30-rao30", help="a realistic protocol (its frames)")
    parser.add_argument("--cases", type=int, default=5, help="LAD and RCA cases 0..N-1")
    parser.add_argument("--extra", action="store_true", help="also 8 simulated frames without vessels")
    parser.add_argument("--real", type=Path, default=None, help="folder of the IM2, IM3, IM7 XA runs (four frames each)")
    args = parser.parse_args(argv)
    from SDFCARLib.angiogram import AngiogramSettings, simulate_angiogram
    from SDFCARLib.benchmark.cases import CaseSpec, prepare_case

    print(f"machine: {platform.machine()} {platform.processor() or ''}, {os.cpu_count()} cores, "
          f"python {platform.python_version()}, one thread", flush=True)
    started = time.perf_counter()
    groups = {}

    def row(group, name, frame, spacing, magnification, settings=None, check_inversion=False):
        dark, dark_thin, bright_thin = asymmetry(frame, spacing, magnification, settings)
        inv, inv_dark_thin, inv_bright_thin = asymmetry(inverted(frame), spacing, magnification, settings)
        # None: not judged (the thin structures of both sides under MIN_POLARITY_CONTRAST)
        entry = {"group": group, "name": name, "dark": None if dark is None else round(dark, 3),
                 "inverted": None if inv is None else round(inv, 3), "thin_contrasts": [dark_thin, bright_thin],
                 "inverted_thin_contrasts": [inv_dark_thin, inv_bright_thin]}
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
    if args.real:
        from SDFCARLib.dicom import choose_frame, load_xa, view_from_dicom

        for name in ("IM2", "IM3", "IM7"):
            run = load_xa(args.real / name)
            n = run.frames.shape[0]
            for index in sorted({choose_frame(run).index, 0, n // 2, n - 1}):
                view, _ = view_from_dicom(run, index)
                row("real XA", f"{name} frame {index}", run.frames[index], view.pixel_spacing_mm, view.sid_mm / view.sod_mm)
    print(f"\nrefused below {masks.MIN_DARK_VESSEL_ASYMMETRY}, warned below {masks.DOUBTFUL_DARK_VESSEL_ASYMMETRY}")
    def span(values):
        judged = [v for v in values if v is not None]
        unjudged = len(values) - len(judged)
        text = f"{min(judged):.3f}–{max(judged):.3f}" if judged else "—"
        return text + (f" ({unjudged} not judged)" if unjudged else "")

    for group, rows in groups.items():
        dark, inv = [r["dark"] for r in rows], [r["inverted"] for r in rows]
        refused = lambda values: sum(v is not None and v < masks.MIN_DARK_VESSEL_ASYMMETRY for v in values)  # noqa: E731
        warned = lambda values: sum(v is not None and v < masks.DOUBTFUL_DARK_VESSEL_ASYMMETRY for v in values)  # noqa: E731
        print(f"{group}: {len(rows)} frames, dark {span(dark)}, inverted {span(inv)}; inverted refused "
              f"{refused(inv)}/{len(rows)} (warned {warned(inv)}), dark ones refused {refused(dark)} (warned {warned(dark)})")
    print(f"{time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
