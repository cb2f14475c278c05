"""The README's picture of the bundled sample case, redrawn from a ``make demo`` output folder.

    .venv/bin/python bench/demo_figure.py demo-output Resources/Screenshots/demo-result.png

The two masks, the reconstructed surface seen from the front, and the maximum-intensity overlay with
the ground truth (``figures.save_result_figure``), with the run's clDice and Dice in the title.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from SDFCARLib.figures import save_result_figure  # noqa: E402
from SDFCARLib.io import align_to_grid, read_label, read_surface_vtk  # noqa: E402
from SDFCARLib.metrics import cldice, dice  # noqa: E402
from SDFCARLib.sample_data import load_sample_case  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("demo_output", type=Path, help="the folder `make demo` wrote (segmentation.seg.nrrd, surface.vtk)")
    parser.add_argument("picture", type=Path, help="PNG to write")
    args = parser.parse_args()
    for name in ("segmentation.seg.nrrd", "surface.vtk"):
        if not (args.demo_output / name).is_file():
            parser.error(f"{args.demo_output / name} is missing: run `make demo` (or `python -m SDFCARLib demo --out …`) first")
    case = load_sample_case()
    grid = case.geometry.volume
    segmentation = align_to_grid(*read_label(args.demo_output / "segmentation.seg.nrrd"), grid, what="demo result")
    vertices, faces = read_surface_vtk(args.demo_output / "surface.vtk")
    view_names = [f"mask, {'LAO' if v.primary_deg >= 0 else 'RAO'} {abs(v.primary_deg):g}" for v in case.geometry.views]
    save_result_figure(args.picture, case.masks, vertices, faces, segmentation, case.label,
                       view_names + ["SDF-CAR surface (front)",
                                     f"vs ground truth: clDice {cldice(segmentation, case.label):.3f}, "
                                     f"Dice {dice(segmentation, case.label):.3f}"])
    print(f"wrote {args.picture}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
