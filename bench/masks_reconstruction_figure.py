"""Picture of a reconstruction from two real runs with ``segment`` masks: for each view the mask and
the reprojection of the reconstructed tree over it (white both, red mask only, blue reprojection
only), and the surface.

    python bench/masks_reconstruction_figure.py RESULT_DIR GEOM.json MASK1.png MASK2.png OUT.png
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from SDFCARLib.geometry import Geometry  # noqa: E402
from SDFCARLib.io import read_image, read_label, read_surface_vtk  # noqa: E402
from SDFCARLib.metrics import mask_dice  # noqa: E402
from SDFCARLib.projector import project_volume  # noqa: E402


def main(result: str, geometry_path: str, mask1: str, mask2: str, out: str) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    geometry = Geometry.load(geometry_path)
    segmentation, _ = read_label(Path(result) / "segmentation.seg.nrrd", grid=geometry.volume)
    fig = plt.figure(figsize=(12, 4.2), dpi=100)
    for n, (view, path) in enumerate(zip(geometry.views, (mask1, mask2))):
        mask = read_image(path) > 0
        projected = project_volume(segmentation.astype(np.float32), view, geometry.volume) > 0.2
        rgb = np.zeros(mask.shape + (3,))
        rgb[mask & projected] = 1.0
        rgb[mask & ~projected] = (1.0, 0.2, 0.2)
        rgb[~mask & projected] = (0.3, 0.5, 1.0)
        ax = fig.add_subplot(1, 3, n + 1)
        ax.imshow(rgb, interpolation="nearest")
        ax.set_title(f"view {n + 1}: reprojection Dice {mask_dice(projected, mask):.3f}")
        ax.axis("off")
    vertices, faces = read_surface_vtk(Path(result) / "surface.vtk")
    ax = fig.add_subplot(1, 3, 3, projection="3d")
    ras = vertices * np.array([-1.0, -1.0, 1.0])
    triangles = ras[faces]
    ax.add_collection3d(Poly3DCollection(triangles, facecolors=(0.85, 0.3, 0.25), edgecolor="none"))
    lo, hi = ras.min(axis=0), ras.max(axis=0)
    centre, half = (lo + hi) / 2, float((hi - lo).max()) / 2
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.view_init(elev=10, azim=90)
    ax.set_title("reconstructed surface (front)")
    ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(out)
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:6]))
