"""The calibration's score along one searched motion: is the re-fitted loss lowest at the true pose?

    .venv/bin/python bench/calibration_scan.py --case 0 --motion rotation_in_plane --true 2 \
        --masks clean segmented --candidates -2 0 1 2 3 4

View 2 (RAO 30) of a procedural case is moved by ``--true`` (mm or degrees) along one of the motions
``calibration.search_axes`` defines (shift, rotation_in_plane, rotation_tilt; rotations about the
region's centre); its masks are simulated clean (the true silhouettes) or segmented by SDFCAR's own
pipeline from simulated angiograms (the realistic protocol without other motion). Each candidate is
scored exactly as ``calibrate`` scores it (``optimiser.fitted_loss``: a ``fast`` field re-fitted for
``calibration_steps`` steps, mean loss of the last steps). Grid 80³ at 1.3 mm, 192² at 0.8 mm.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from SDFCARLib.benchmark.cases import GridOptions, protocol_geometry  # noqa: E402
from SDFCARLib.calibration import moved, pose_score, search_axes  # noqa: E402
from SDFCARLib.geometry import Geometry  # noqa: E402
from SDFCARLib.phantoms import lad_tree, rca_tree, simulate_views, voxelize  # noqa: E402
from SDFCARLib.realistic import RealisticOptions, realistic_input  # noqa: E402
from SDFCARLib.settings import make_settings  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", choices=("rca", "lad"), default="rca")
    parser.add_argument("--case", type=int, default=0, help="case seed")
    parser.add_argument("--motion", choices=("shift", "rotation_in_plane", "rotation_tilt"), default="rotation_in_plane")
    parser.add_argument("--true", type=float, default=2.0, help="the simulated motion (mm for the shift, else degrees)")
    parser.add_argument("--masks", nargs="+", choices=("clean", "segmented"), default=["clean", "segmented"])
    parser.add_argument("--candidates", type=float, nargs="+", default=[-2.0, 0.0, 1.0, 2.0, 3.0, 4.0])
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    geometry = protocol_geometry("clinical-lao30-rao30", args.suite, GridOptions((80, 80, 80), 1.3, (192, 192), 0.8))
    reference, view = geometry.views
    axis = search_axes(reference, view)[args.motion]
    centre = np.asarray(geometry.volume.center_mm, float)
    zero = np.zeros(3)

    def at(value: float):
        return moved(view, value * axis if args.motion != "shift" else zero, value * axis if args.motion == "shift" else zero, centre)

    label = voxelize((rca_tree if args.suite == "rca" else lad_tree)(args.case), geometry.volume)
    truth = Geometry(geometry.volume, (reference, at(args.true)))
    settings = make_settings("fast", seed=args.case, calibrate=True)
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
          f"{args.threads} thread(s); {args.suite.upper()}-{args.case}, view 2 moved {args.true:+g} along {args.motion}",
          flush=True)
    for kind in args.masks:
        if kind == "clean":
            _, masks = simulate_views(label, geometry.volume, truth.views)
        else:
            masks = realistic_input(label, truth, args.case, RealisticOptions(max_shift_mm=0.0, max_rotation_deg=0.0)).masks
        for value in args.candidates:
            t0 = time.perf_counter()
            loss = pose_score(Geometry(geometry.volume, (reference, at(value))), masks, settings, "mask")
            print(f"{kind:9s} candidate {value:+6.2f}: loss {loss:.6f}  ({time.perf_counter() - t0:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
