"""The README's 3D-QCA pictures: the diameter profiles and the best-view map of ``lad_tree(0)`` with a 50 % lesion
over 10 mm on the LAD, voxelised exactly at 0.3 mm, clean LAO 30 / RAO 30 masks.

    python bench/qca_figures.py [--out Resources/Screenshots]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from SDFCARLib.analysis.outputs import plot_profiles, plot_view_map  # noqa: E402
from SDFCARLib.analysis.phantoms import grid_around, render_mask, stenosed_tree, voxelize_exact  # noqa: E402
from SDFCARLib.analysis.pipeline import analyse_volume  # noqa: E402
from SDFCARLib.geometry import standard_geometry  # noqa: E402
from SDFCARLib.phantoms import lad_tree  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "Resources" / "Screenshots")
    args = ap.parse_args(argv)
    phantom = stenosed_tree(lad_tree(0), "LM-LAD", 50, 10.0)
    grid = grid_around(phantom.tree, 0.3)
    label = voxelize_exact(phantom.tree, grid).astype(np.float32)
    views = list(standard_geometry("lao30-rao30").views)
    result = analyse_volume(label, grid, views=views, masks=[render_mask(phantom.tree, v) for v in views],
                            ostium_mm=phantom.tree.branches[0].points[0])
    for profile in result.profiles:
        for lesion in profile.lesions:
            print(f"branch {profile.branch.branch_id}: DS {lesion.diameter_stenosis_pct:.1f} %, length {lesion.length_mm:.2f} mm")
    args.out.mkdir(parents=True, exist_ok=True)
    plot_profiles(args.out / "qca-diameter-profiles.png", result, max_branches=2)
    plot_view_map(args.out / "qca-view-map.png", result)
    print(f"wrote qca-diameter-profiles.png and qca-view-map.png to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
