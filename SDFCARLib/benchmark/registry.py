"""The tables the benchmark shares with the rest of SDFCARLib: modes and their titles, the metric
table, and the paper's protocols and geometry.

They are not benchmark-specific; they sit together here, in one place, until SDFCARLib/settings.py
(the torch-free home of modes, presets, protocols and the metric registry) takes them over and
this file imports them from there.
"""

from __future__ import annotations

from typing import Dict, List, Tuple

# --- modes ----------------------------------------------------------------------------------------
# The baseline row: the visual hull of the two masks, no optimiser.
HULL = "hull"

# Short row names as in the paper's tables; a mode the optimiser adds later falls back to its title.
MODE_NAMES = {
    HULL: "Visual hull (masks only)",
    "neca": "NeCA",
    "occ-combined": "Occ. Rep. + Combined Loss",
    "sdf-occ": "SDF Rep. + Occ. Loss",
    "sdfcar": "SDF-CAR",
}


def mode_title(mode: str) -> str:
    """A mode's row name in the tables."""
    if mode in MODE_NAMES:
        return MODE_NAMES[mode]
    try:
        from ..optimiser import MODES

        return str(MODES[mode]["title"])
    except Exception:
        return mode


# --- metrics --------------------------------------------------------------------------------------
#: (column, header, scale, decimals, higher is better) — the paper's six metrics, then ours.
TABLE_METRICS: List[Tuple[str, str, float, int, bool]] = [
    ("cldice", "clDice (%)", 100.0, 2, True),
    ("dice", "Dice (%)", 100.0, 2, True),
    ("iou", "IoU (%)", 100.0, 2, True),
    ("re_error", "reError", 1.0, 3, False),
    ("chamfer_l2_mm", "CD-ℓ2 (mm)", 1.0, 2, False),
    ("re_mse", "reMSE (×1e-4)", 1e4, 2, False),
    ("skeleton_dice", "skeleton-Dice (%)", 100.0, 2, True),
    ("wall_s", "wall time (s)", 1.0, 1, False),
]
PAPER_METRICS = ("cldice", "dice", "iou", "re_error", "chamfer_l2_mm", "re_mse")

# The metric columns of results.csv, in order.
METRIC_COLUMNS = ["cldice", "tprec", "tsens", "skeleton_dice", "dice", "iou", "chamfer_l2_mm", "re_error", "re_mse",
                  "reprojection_dice_view1", "reprojection_dice_view2", "voxels_predicted", "voxels_label"]

# --- protocols --------------------------------------------------------------------------------------
#: protocol name → (VIEW_PAIRS key, target kind)
PROTOCOLS: Dict[str, Tuple[str, str]] = {
    "paper": ("paper", "line_integral"),
    "clinical-lao30-rao30": ("lao30-rao30", "mask"),
    "clinical-lao50cra25-rao50cra25": ("lao50cra25-rao50cra25", "mask"),
}
PAPER_VOLUME_SHAPE = (128, 128, 128)
PAPER_SPACING_MM = 0.8
PAPER_DETECTOR_SHAPE = (512, 512)
PAPER_DETECTOR_SPACING_MM = 0.278
