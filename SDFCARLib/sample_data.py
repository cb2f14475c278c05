"""The bundled two-view sample case, and how it is made.

The case is simulated, so its ground truth is known: the procedural left-coronary tree
``phantoms.lad_tree(seed=7)`` voxelised on a 128³ grid at 0.8 mm, seen in an LAO 30 / RAO 30 pair
(SID 1000 mm, SOD 757 mm) on a 512² detector at 0.278 mm; each view's mask is the label's line
integral > 0.2 mm (``phantoms.make_case``).

Files in ``SDFCARLib/data/sample_case/``: ``geometry.json``, ``view1_mask.png``,
``view2_mask.png`` (uint8 0/255), ``ground_truth.seg.nrrd`` and ``README.md``.
``python -m SDFCARLib.sample_data --out DIR`` writes them again; the files are deterministic, so
a test compares the bundled ones with a fresh regeneration.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

import numpy as np

from .geometry import Geometry, standard_geometry
from .io import align_to_grid, read_label, read_mask, write_json, write_mask_png, write_segmentation_nrrd
from .outputs import staged_directory
from .settings import PAPER_DETECTOR_SHAPE, PAPER_DETECTOR_SPACING_MM, PAPER_SPACING_MM, PAPER_VOLUME_SHAPE

PathLike = Union[str, Path]

SAMPLE_DIR = Path(__file__).resolve().parent / "data" / "sample_case"
TREE_SEED = 7
VIEW_PAIR = "lao30-rao30"
VOLUME_SHAPE = PAPER_VOLUME_SHAPE
SPACING_MM = PAPER_SPACING_MM
DETECTOR_SHAPE = PAPER_DETECTOR_SHAPE
DETECTOR_SPACING_MM = PAPER_DETECTOR_SPACING_MM

FILES = {
    "geometry": "geometry.json",
    "mask1": "view1_mask.png",
    "mask2": "view2_mask.png",
    "ground_truth": "ground_truth.seg.nrrd",
    "readme": "README.md",
}

DESCRIPTION = (
    f"SDFCAR sample case: procedural left coronary tree lad_tree(seed={TREE_SEED}), {VIEW_PAIR} views; "
    "made by python -m SDFCARLib.sample_data"
)

README = f"""# SDFCAR sample case

A small simulated two-view coronary angiography case, bundled so that `python -m SDFCARLib demo`
runs without any download. Its ground truth is known, so the demo can report accuracy.

| File | What it is |
| --- | --- |
| `geometry.json` | the GEOM.json: reconstruction grid {VOLUME_SHAPE[0]}×{VOLUME_SHAPE[1]}×{VOLUME_SHAPE[2]} voxels at {SPACING_MM} mm centred on the isocenter, two C-arm views LAO 30 and RAO 30 (SID 1000 mm, SOD 757 mm, detector {DETECTOR_SHAPE[0]}×{DETECTOR_SHAPE[1]} pixels at {DETECTOR_SPACING_MM} mm) |
| `view1_mask.png`, `view2_mask.png` | the vessel masks of the two views (8-bit, 0 = background, 255 = vessel) |
| `ground_truth.seg.nrrd` | the voxelised tree on the reconstruction grid (Slicer segmentation, LPS) |

How it was made (`SDFCARLib/sample_data.py`): the procedural left-coronary tree
`SDFCARLib.phantoms.lad_tree(seed={TREE_SEED})` (LM, LAD with diagonals and a septal branch, LCx
with an obtuse marginal; radii about 2 mm tapering to 0.5–0.7 mm) is voxelised on the grid (a
voxel is vessel when its centre lies inside the tubes), projected into both views with SDFCAR's
cone-beam projector, and each mask is the projected path length > 0.2 mm
(`SDFCARLib.phantoms.make_case`). The geometry is
`SDFCARLib.geometry.standard_geometry("{VIEW_PAIR}", volume_shape={VOLUME_SHAPE}, spacing_mm={SPACING_MM},
detector_shape={DETECTOR_SHAPE}, detector_spacing_mm={DETECTOR_SPACING_MM})`.

Regenerate the files with `python -m SDFCARLib.sample_data --out DIR`; the result is deterministic.
The case is synthetic: no patient data.
"""


@dataclass
class SampleCase:
    """The sample case as arrays: its geometry, one mask per view and the ground-truth label."""

    geometry: Geometry
    masks: List[np.ndarray]  # bool (rows, cols)
    label: np.ndarray  # bool [i, j, k] on geometry.volume
    directory: Optional[Path] = None


def sample_geometry() -> Geometry:
    return standard_geometry(VIEW_PAIR, volume_shape=VOLUME_SHAPE, spacing_mm=SPACING_MM,
                             detector_shape=DETECTOR_SHAPE, detector_spacing_mm=DETECTOR_SPACING_MM)


def make_sample_case() -> SampleCase:
    """Simulate the sample case from scratch (about 20 s on a CPU)."""
    from .phantoms import lad_tree, make_case

    case = make_case(lad_tree(seed=TREE_SEED), sample_geometry(), name="sample_case")
    return SampleCase(case.geometry, [np.asarray(m, bool) for m in case.masks], np.asarray(case.label, bool))


def write_sample_case(out_dir: PathLike, overwrite: bool = False, case: Optional[SampleCase] = None) -> Dict[str, Path]:
    """Write the sample case's files into ``out_dir`` (all or nothing); return their paths."""

    case = case or make_sample_case()
    out_dir = Path(out_dir)
    with staged_directory(out_dir, list(FILES.values()), overwrite) as staging:
        write_json(staging / FILES["geometry"], {"description": DESCRIPTION, **case.geometry.to_dict()})
        for n, mask in enumerate(case.masks, start=1):
            write_mask_png(staging / FILES[f"mask{n}"], mask)
        write_segmentation_nrrd(staging / FILES["ground_truth"], case.label, case.geometry.volume, name="Ground truth",
                                color=(0.2, 0.8, 0.2))
        (staging / FILES["readme"]).write_text(README, encoding="utf-8")
    return {key: out_dir / name for key, name in FILES.items()}


def load_sample_case(directory: Optional[PathLike] = None) -> SampleCase:
    """Read the sample case (default: the copy installed with the package)."""

    directory = Path(directory) if directory is not None else SAMPLE_DIR
    missing = [name for name in FILES.values() if not (directory / name).is_file()]
    if missing:
        raise FileNotFoundError(
            f"the sample case in {directory} is incomplete (missing {', '.join(missing)}); reinstall SDFCARLib or "
            "regenerate it with python -m SDFCARLib.sample_data --out DIR")
    geometry = Geometry.load(directory / FILES["geometry"])
    masks = [read_mask(directory / FILES[f"mask{n}"], view.detector_shape) for n, view in enumerate(geometry.views, start=1)]
    label, label_grid = read_label(directory / FILES["ground_truth"])
    label = align_to_grid(label, label_grid, geometry.volume, what="ground truth")
    return SampleCase(geometry, masks, label, directory)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m SDFCARLib.sample_data", description="Regenerate SDFCAR's bundled sample case.")
    parser.add_argument("--out", required=True, help="folder to write the case into")
    parser.add_argument("--overwrite", action="store_true", help="replace files the folder already holds")
    args = parser.parse_args(argv)
    try:
        files = write_sample_case(args.out, overwrite=args.overwrite)
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for path in files.values():
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
