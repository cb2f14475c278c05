"""LOG-encoded frames side by side with the same frames stored linearly, on realistic benchmark cases.

    .venv/bin/python bench/log_frames.py --suite lad --case 0 1 2 3 4

Per case the realistic protocol's simulated angiograms (linear counts, as a LIN run stores them) are encoded as a
LOG run would store them — 12 bits over ln I from 0 to ln 65536 (a 16-bit detector's range), higher values less
intensity (Pixel Intensity Relationship Sign −1) — and three fits of `fast` are run with the same masks and seed:

    LIN        the linear frames (what a LIN run gives);
    LOG read   the LOG frames brought back to a linear scale by ``dicom.intensity.linearised``, as ``load_xa`` and the
               Slicer module now read them;
    LOG as-is  the LOG frames handed over with their relationship, as every run tagged LOG was read until now: no
               path lengths (``evidence.unreadable_intensity``), the masks alone fitted.

Prints per case clDice, Dice and pieces of each, the largest difference of the path lengths read off the LOG frames
from the LIN frames' (inside the masks, relative to the LIN path length's 99th percentile), and the machine.
"""

from __future__ import annotations

import argparse
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
from SDFCARLib.dicom.intensity import IntensityTags, linearised  # noqa: E402
from SDFCARLib.metrics import evaluate  # noqa: E402
from SDFCARLib.optimiser import read_frame_evidence, reconstruct  # noqa: E402
from SDFCARLib.settings import make_settings  # noqa: E402

BITS = 12
LOG_RANGE = np.log(65536.0)


def log_encoded(counts: np.ndarray) -> np.ndarray:
    """Stored values of a LOG run: 12 bits over ln I in [0, ln 65536], sign −1 (higher values, less intensity)."""
    log = np.log(np.clip(np.asarray(counts, np.float64), 1.0, 65535.0))
    return np.round((2**BITS - 1) * (1.0 - log / LOG_RANGE)).astype(np.uint16)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", default="lad")
    parser.add_argument("--case", type=int, nargs="+", default=[0])
    parser.add_argument("--protocol", default="realistic-static-lao30-rao30")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    grid = GridOptions()
    config = BenchmarkConfig(args.suite, Path("unused"), cases=max(args.case) + 1, grid=grid, protocol=args.protocol)
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"{args.threads} thread(s); {args.suite} cases {args.case}, {args.protocol}", flush=True)
    tags = IntensityTags("LOG", -1, "MONOCHROME2", BITS)
    rows = []
    for index in args.case:
        spec = build_cases(config)[index]
        case = prepare_case(spec, args.protocol, grid)
        settings = make_settings("fast", seed=spec.seed)
        stored = [log_encoded(frame) for frame in case.frames]
        read = [linearised(values, tags)[0] for values in stored]
        # the path lengths each way, before any fit
        lin_ev = read_frame_evidence(case.frames, case.targets, case.geometry, settings, case.target_kind)
        log_ev = read_frame_evidence(read, case.targets, case.geometry, settings, case.target_kind, ["LIN"] * len(read))
        worst = max(float(np.max(np.abs(a - b)[m > 0]) / np.percentile(a[m > 0], 99))
                    for a, b, m in zip(lin_ev.images, log_ev.images, case.masks))
        scores = []
        for label, frames, intensity in (("LIN", case.frames, None), ("LOG read", read, ["LIN"] * len(read)),
                                         ("LOG as-is", stored, ["LOG"] * len(read))):
            t0 = time.perf_counter()
            result = reconstruct(case.geometry, case.targets, settings, case.target_kind, frames=frames,
                                 frame_intensity=intensity)
            m = evaluate(result.segmentation, case.label, case.geometry.volume, case.geometry.views, case.masks)
            scores.append((m["cldice"], m["dice"], m.get("components")))
            print(f"{spec.name:7s} {label:10s} clDice {m['cldice']:.3f}  Dice {m['dice']:.3f}  pieces {m.get('components')}"
                  f"  path lengths used {result.report['frame_evidence'].get('used')}  {time.perf_counter() - t0:.0f} s",
                  flush=True)
        print(f"{spec.name:7s} path lengths off the LOG frames differ from the LIN frames' by at most {100 * worst:.2f} % "
              f"(of the LIN path length's 99th percentile, inside the masks)", flush=True)
        rows.append(scores)
    table = np.array([[s[:2] for s in case] for case in rows])  # (cases, 3, 2)
    for k, label in enumerate(("LIN", "LOG read", "LOG as-is")):
        print(f"mean    {label:10s} clDice {table[:, k, 0].mean():.4f}  Dice {table[:, k, 1].mean():.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
