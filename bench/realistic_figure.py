"""The README's realistic case: simulated angiograms, the masks segmented from them, the result.

    .venv/bin/python bench/realistic_figure.py --suite rca --case 0 --out Resources/Screenshots/realistic-case.png

One benchmark case of a ``realistic-…`` protocol (grid 80³ at 1.3 mm, 192² at 0.8 mm unless --paper-grid):
per view the angiogram, its segmented mask against the true silhouette, and the reprojection of the
``fast`` reconstruction against that mask; then the result against the voxelised truth as maximum
intensity projections along A–P and L–R. Prints clDice, Dice and components.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from SDFCARLib.benchmark import BenchmarkConfig, GridOptions, build_cases  # noqa: E402
from SDFCARLib.benchmark.cases import protocol_geometry  # noqa: E402
from SDFCARLib.metrics import evaluate  # noqa: E402
from SDFCARLib.optimiser import reconstruct  # noqa: E402
from SDFCARLib.phantoms import lad_tree, rca_tree, voxelize  # noqa: E402
from SDFCARLib.qa import AGREE_RGB, MASK_ONLY_RGB, RESULT_ONLY_RGB, qa_overlay_rgb  # noqa: E402
from SDFCARLib.realistic import RealisticOptions, realistic_input  # noqa: E402
from SDFCARLib.settings import REALISTIC_PROTOCOLS, make_settings  # noqa: E402


def three_way(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """RGB: both (green), only a (vermillion: extra), only b (blue: missed), the QA overlay colours."""
    image = np.zeros(a.shape + (3,), dtype=np.uint8)
    image[a & b] = AGREE_RGB
    image[a & ~b] = RESULT_ONLY_RGB
    image[b & ~a] = MASK_ONLY_RGB
    return image


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", default="rca", choices=("rca", "lad"))
    parser.add_argument("--case", type=int, default=0)
    parser.add_argument("--protocol", default="realistic-static-lao30-rao30", choices=sorted(REALISTIC_PROTOCOLS))
    parser.add_argument("--paper-grid", action="store_true")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    grid = None if args.paper_grid else GridOptions((80, 80, 80), 1.3, (192, 192), 0.8)
    config = BenchmarkConfig(args.suite, Path("unused"), cases=args.case + 1, grid=grid or GridOptions(),
                             protocol=args.protocol)
    spec = build_cases(config)[args.case]
    geometry = protocol_geometry(args.protocol, args.suite, grid)
    label = voxelize((rca_tree if args.suite == "rca" else lad_tree)(spec.seed), geometry.volume)
    case = realistic_input(label, geometry, spec.seed, RealisticOptions(**REALISTIC_PROTOCOLS[args.protocol]))
    targets = [m.astype(np.float32) for m in case.masks]
    result = reconstruct(geometry, targets, make_settings("fast", seed=spec.seed), "mask", frames=case.frames)
    m = evaluate(result.segmentation, label, geometry.volume, geometry.views, case.true_masks)
    summary = (f"{spec.name}, {args.protocol}: clDice {m['cldice']:.3f}, Dice {m['dice']:.3f}, "
               f"{m.get('components')} components (truth {m.get('components_label')})")
    print(summary)

    views = len(geometry.views)
    fig, axes = plt.subplots(views + 1, 3, figsize=(11, 3.7 * (views + 1)))
    for n, (view, frame, mask, truth, (projected, _)) in enumerate(
            zip(geometry.views, case.frames, case.masks, case.true_masks, result.qa_masks)):
        row = axes[n]
        row[0].imshow(frame, cmap="gray")
        row[0].set_title(f"view {n + 1} ({view.describe()}): simulated angiogram", fontsize=9)
        row[1].imshow(three_way(mask, truth))
        row[1].set_title("segmented mask vs true silhouette", fontsize=9)
        overlay = qa_overlay_rgb(frame, projected, mask)
        row[2].imshow(overlay[: projected.shape[0], : projected.shape[1]])
        row[2].set_title("result reprojected vs segmented mask", fontsize=9)
    seg, truth3d = result.segmentation, label.astype(bool)
    last = axes[views]
    for ax, axis, name in ((last[0], 1, "A–P"), (last[1], 0, "L–R")):
        ax.imshow(np.rot90(three_way(seg.any(axis=axis), truth3d.any(axis=axis))))
        ax.set_title(f"result vs truth, projection {name}", fontsize=9)
    last[2].axis("off")
    last[2].legend(handles=[Patch(color=np.array(AGREE_RGB) / 255, label="both"),
                            Patch(color=np.array(RESULT_ONLY_RGB) / 255, label="extra: only the first of the pair"),
                            Patch(color=np.array(MASK_ONLY_RGB) / 255, label="missed: only the second")],
                   loc="center", fontsize=10, title=summary.replace(": ", "\n").replace(", ", "\n"))
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=80)
    return 0


if __name__ == "__main__":
    sys.exit(main())
