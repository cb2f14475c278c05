"""Vessel masks of angiography frames: the first helper (``masks.vesselness_mask``) against the
pipeline (``masks.segment_angiogram``), on simulated angiograms with a known silhouette and on the
real XA runs of the static phantom.

    python bench/masks.py --cases 3 --real ../shared/data/xa-phantom --out bench/masks_results.md

Simulated: ``--cases`` RCA and as many LAD procedural trees (seeds 1…N), two views each (LAO 30 /
RAO 30, 512² detector at 0.278 mm, SID/SOD 1000/757), the frame from ``angiogram.simulate_angiogram``
with its defaults (12 bits, SNR 25, 0.3 mm blur, smooth tissue, ribs, diaphragm) and, in view 2, a
collimator over 5 % of each side. Truth: the silhouette ``line integral > 0.2 mm`` (every branch of
these trees is at least 1 mm in diameter). Real: the frame ``dicom.choose_frame`` picks in each run,
the pixel spacing and SID/SOD of its tags. Per frame: Dice and clDice against the truth, 8-connected
components, mask pixels in the border the pipeline detects (collimator + image edge), and the time
in CPU seconds of one thread (the machine is shared). Figures go to ``--figures``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Tuple

os.environ.setdefault("OMP_NUM_THREADS", "1")  # time per frame on one core
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
from skimage.measure import label as connected_components  # noqa: E402

from SDFCARLib.angiogram import AngiogramSettings, simulate_angiogram  # noqa: E402
from SDFCARLib.geometry import standard_geometry  # noqa: E402
from SDFCARLib.masks import AngioMaskSettings, MaskError, segment_angiogram  # noqa: E402
from SDFCARLib.metrics import cldice, mask_dice  # noqa: E402
from SDFCARLib.phantoms import lad_tree, make_case, rca_tree  # noqa: E402

METHODS = {
    "old helper (vesselness_mask, frangi)": None,
    "pipeline, sato (default)": AngioMaskSettings(),
    "pipeline, frangi": AngioMaskSettings(method="frangi"),
    "pipeline, meijering": AngioMaskSettings(method="meijering"),
}


# --- the baseline: the project's first vesselness helper, removed from the product --------------------
def _normalise(frame: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(frame, [1.0, 99.0])
    if not hi > lo:
        raise MaskError("the frame is flat (no contrast between its 1st and 99th percentiles): nothing to segment")
    return np.clip((frame - lo) / (hi - lo), 0.0, 1.0)


def vesselness_mask(
    frame: Any,
    sigmas: Sequence[float] = (1.0, 2.0, 3.0, 4.0),
    method: str = "frangi",
    black_ridges: bool = True,
    threshold: Optional[float] = None,
    min_component_px: int = 30,
) -> Tuple[np.ndarray, Dict[str, Any]]:
    """Vessel mask of one frame by a ridge filter, threshold and small-component removal.

    Returns ``(mask, parameters)``; ``parameters`` holds every value used (the Otsu threshold
    when ``threshold`` is None) and the fraction of the image marked vessel.
    """
    from skimage.filters import frangi, sato, threshold_otsu
    from skimage.morphology import remove_small_objects

    image = np.asarray(frame, dtype=np.float64)
    if image.ndim != 2:
        raise MaskError(f"vesselness works on one 2-D frame, got shape {image.shape}; pick a frame first")
    if not np.all(np.isfinite(image)):
        raise MaskError("the frame contains NaN or infinite values")
    sigmas = tuple(float(s) for s in sigmas)
    if not sigmas or any(s <= 0 for s in sigmas):
        raise MaskError(f"sigmas must be positive scales in pixels (about the vessel radius), got {sigmas}")
    if method not in ("frangi", "sato"):
        raise MaskError(f"method must be 'frangi' or 'sato', got {method!r}")
    if int(min_component_px) < 0:
        raise MaskError(f"min_component_px must be 0 or more, got {min_component_px}")
    scaled = _normalise(image)
    if method == "frangi":
        response = frangi(scaled, sigmas=sigmas, black_ridges=black_ridges)
    else:
        response = sato(scaled, sigmas=sigmas, black_ridges=black_ridges)
    response = np.nan_to_num(response, nan=0.0)
    if threshold is None:
        # Otsu on the pixels that respond at all: the flat background would otherwise dominate.
        active = response[response > 1e-3 * float(response.max())] if response.max() > 0 else response
        if active.size < 2 or float(active.max()) == float(active.min()):
            raise MaskError("the ridge filter found no vessel-like structure; check black_ridges and sigmas")
        if method == "frangi":
            # Frangi's response spans decades; on a linear scale Otsu keeps only the vessel cores.
            value = float(np.exp(threshold_otsu(np.log(active))))
            threshold_source = "Otsu on the logarithm of the non-negligible response"
        else:
            value, threshold_source = float(threshold_otsu(active)), "Otsu on the non-negligible response"
    else:
        value, threshold_source = float(threshold), "user"
    mask = response > value
    if min_component_px > 0:
        mask = remove_small_objects(mask, max_size=int(min_component_px) - 1, connectivity=2) if _has_max_size() \
            else remove_small_objects(mask, min_size=int(min_component_px), connectivity=2)
    parameters = {
        "method": method,
        "sigmas": list(sigmas),
        "black_ridges": bool(black_ridges),
        "threshold": value,
        "threshold_source": threshold_source,
        "response_max": float(response.max()),
        "min_component_px": int(min_component_px),
        "vessel_fraction": float(mask.mean()),
    }
    return mask, parameters


def _has_max_size() -> bool:
    """scikit-image ≥ 0.26 names the size limit ``max_size`` (objects up to it are removed)."""
    import inspect

    from skimage.morphology import remove_small_objects

    return "max_size" in inspect.signature(remove_small_objects).parameters



def _run(method, frame, spacing, magnification):
    """(mask, border or None, CPU seconds of this process: the machine is shared, wall time is not
    the method's)."""
    started = time.process_time()
    if method is None:
        mask, _ = vesselness_mask(frame)
        return mask, None, time.process_time() - started
    result = segment_angiogram(frame, spacing, magnification, method)
    return result.mask, result.border, time.process_time() - started


def _panel(frame, mask, border):
    """Half-size picture: the mask filled in red, the detected border tinted blue (outlines vanish
    when the picture is shrunk)."""
    from SDFCARLib.masks import display_frame

    grey = display_frame(frame).astype(np.float64)
    rgb = np.dstack([grey, grey, grey])
    if border is not None:
        rgb[border] = 0.6 * rgb[border] + 0.4 * np.array([40.0, 110.0, 255.0])
    rgb[mask] = 0.35 * rgb[mask] + 0.65 * np.array([255.0, 20.0, 20.0])
    rows, cols = (s // 2 * 2 for s in rgb.shape[:2])
    half = rgb[:rows, :cols].reshape(rows // 2, 2, cols // 2, 2, 3).mean(axis=(1, 3))
    return np.rint(half).astype(np.uint8)


def _save(path, rgb):
    from PIL import Image

    Image.fromarray(rgb).quantize(colors=64).save(path, optimize=True)


def _machine() -> str:
    import subprocess

    try:
        model = [line.split(":", 1)[1].strip() for line in subprocess.run(["lscpu"], capture_output=True, text=True).stdout
                 .splitlines() if line.startswith("Model name")][0]
    except (OSError, IndexError):
        model = platform.processor() or platform.machine()
    return f"{model}, {os.cpu_count()} cores (shared with other jobs)"


def _median(values):
    return statistics.median(values) if values else float("nan")


def simulated(n_cases: int, figures: Path, snr: float, mu: float):
    geometry = standard_geometry("lao30-rao30")
    view_spacing = geometry.views[0].pixel_spacing_mm
    magnification = geometry.views[0].sid_mm / geometry.views[0].sod_mm
    rows = {name: [] for name in METHODS}
    example = example_truth = None
    for suite, tree in (("RCA", rca_tree), ("LAD", lad_tree)):
        for seed in range(1, n_cases + 1):
            case = make_case(tree(seed), geometry)
            for v in range(2):
                settings = AngiogramSettings(collimator_fraction=0.05 if v == 1 else 0.0, snr=snr,
                                             mu_per_mm=mu)
                frame, _ = simulate_angiogram(case.line_integrals[v], view_spacing, 100 * seed + v, settings)
                truth = case.masks[v]
                border = segment_angiogram(frame, view_spacing, magnification).border
                for name, method in METHODS.items():
                    try:
                        mask, _, seconds = _run(method, frame, view_spacing, magnification)
                    except MaskError as exc:
                        print(f"{suite}-{seed} view {v + 1} {name}: {exc}", file=sys.stderr)
                        mask, seconds = np.zeros_like(truth), float("nan")
                    rows[name].append({"dice": mask_dice(mask, truth), "cldice": cldice(mask, truth),
                                       "components": int(connected_components(mask, connectivity=2).max()),
                                       "border_px": int((mask & border).sum()), "seconds": seconds})
                if example is None and v == 1:
                    example_truth = truth
                    example = (frame, {name: _run(m, frame, view_spacing, magnification) for name, m in
                                       list(METHODS.items())[:2]}, border)
                print(f"{suite}-{seed} view {v + 1}: " + ", ".join(
                    f"{name.split(' (')[0].split(',')[0]} Dice {rows[name][-1]['dice']:.3f}" for name in list(METHODS)[:2]),
                    file=sys.stderr)
    if example is not None and (snr, mu) == (AngiogramSettings().snr, AngiogramSettings().mu_per_mm):
        frame, results, border = example
        truth_panel = _panel(frame, example_truth, None)
        panels = [truth_panel] + [_panel(frame, mask, border) for mask, _, _ in results.values()]
        _save(figures / "masks_simulated.png", np.concatenate(panels, axis=1))
    return rows


def vessel_free(n_frames: int):
    """Frames of background, ribs, diaphragm and noise only (every second one with a collimator):
    (frames refused with 'no vessel found', lengths in mm of what was kept in the others)."""
    refused, kept = 0, []
    for seed in range(n_frames):
        settings = AngiogramSettings(collimator_fraction=0.04 * (seed % 2))
        frame, _ = simulate_angiogram(np.zeros((512, 512)), 0.278, seed, settings)
        try:
            kept.append(segment_angiogram(frame, 0.278, 1000 / 757).parameters["component_lengths_mm"])
        except MaskError:
            refused += 1
    return refused, kept


def real(folder: Path, figures: Path):
    from SDFCARLib.dicom import choose_frame, load_xa, view_from_dicom

    rows, panels = [], {name: [] for name in list(METHODS)[:2]}
    for name in ("IM2", "IM3", "IM7"):
        run = load_xa(folder / name)
        choice = choose_frame(run)
        frame = run.frames[choice.index]
        view, _ = view_from_dicom(run, choice.index)
        magnification = view.sid_mm / view.sod_mm
        border = segment_angiogram(frame, view.pixel_spacing_mm, magnification).border
        for method_name, method in list(METHODS.items())[:2]:
            mask, _, seconds = _run(method, frame, view.pixel_spacing_mm, magnification)
            rows.append({"run": name, "frame": choice.index, "method": method_name,
                         "components": int(connected_components(mask, connectivity=2).max()),
                         "border_px": int((mask & border).sum()), "fraction": float(mask.mean()), "seconds": seconds})
            panels[method_name].append(_panel(frame, mask, border))
    _save(figures / "masks_real.png", np.concatenate([np.concatenate(p, axis=1) for p in panels.values()], axis=0))
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=3, help="trees per suite (RCA and LAD), two views each")
    parser.add_argument("--snr", type=float, default=AngiogramSettings().snr,
                        help="background signal-to-noise ratio of the simulated frames (default: the simulator's)")
    parser.add_argument("--mu", type=float, default=AngiogramSettings().mu_per_mm,
                        help="attenuation of the contrast-filled vessels, per mm (default: the simulator's)")
    parser.add_argument("--vessel-free", type=int, default=0, help="also segment this many vessel-free frames")
    parser.add_argument("--real", type=Path, default=None, help="folder with the IM2, IM3, IM7 XA runs")
    parser.add_argument("--figures", type=Path, default=Path("bench/figures"))
    parser.add_argument("--out", type=Path, default=None, help="also write the tables to this Markdown file")
    args = parser.parse_args(argv)
    args.figures.mkdir(parents=True, exist_ok=True)
    lines = [f"Machine: {_machine()}, Python {platform.python_version()}, "
             f"OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}", ""]
    if args.vessel_free:
        refused, kept = vessel_free(args.vessel_free)
        lines += [f"Vessel-free frames: {refused} of {args.vessel_free} refused ('no vessel found'); kept in the "
                  f"others (mm): {kept}", ""]
    sim = simulated(args.cases, args.figures, args.snr, args.mu) if args.cases else {}
    if sim:
        lines += [f"Simulated angiograms, SNR {args.snr:g}, μ {args.mu:g}/mm: {2 * args.cases} trees × 2 views = "
                  f"{4 * args.cases} frames (512²); median over frames, [min–max]", "",
                  "| method | Dice | clDice | components / image | border px (total) | CPU s / frame |",
                  "|---|---:|---:|---:|---:|---:|"]
    for name, values in sim.items():
        def col(key, fmt="{:.3f}"):
            v = [r[key] for r in values]
            return f"{fmt.format(_median(v))} [{fmt.format(min(v))}–{fmt.format(max(v))}]"
        lines.append(f"| {name} | {col('dice')} | {col('cldice')} | {col('components', '{:.0f}')} | "
                     f"{sum(r['border_px'] for r in values)} | {col('seconds', '{:.2f}')} |")
    if args.real is not None:
        lines += ["", "Real XA runs of the static phantom (the frame `choose_frame` picks):", "",
                  "| run | frame | method | components | border px | vessel % | CPU s / frame |",
                  "|---|---:|---|---:|---:|---:|---:|"]
        for r in real(args.real, args.figures):
            lines.append(f"| {r['run']} | {r['frame']} | {r['method']} | {r['components']} | {r['border_px']} | "
                         f"{100 * r['fraction']:.1f} | {r['seconds']:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
