"""The benchmark's view of the shared registries (``SDFCARLib.settings``): row names of the modes,
the metric columns of its tables, and the paper's protocols and geometry."""

from __future__ import annotations

from typing import List, Tuple

from ..settings import METRICS, MODES, PAPER_METRICS

# The baseline row: the visual hull of the masks, no optimiser.
HULL = "hull"

#: row name of every mode in the tables (the paper's short names)
MODE_NAMES = {HULL: "Visual hull (masks only)", **{key: mode.table_title for key, mode in MODES.items()}}


def mode_title(mode: str) -> str:
    """A mode's row name in the tables (an unknown mode shows as itself)."""
    return MODE_NAMES.get(mode, mode)


#: (column, header, scale, decimals, higher is better) — the paper's six metrics, then ours.
TABLE_METRICS: List[Tuple[str, str, float, int, bool]] = [
    (key, METRICS[key].table_header, METRICS[key].table_scale, METRICS[key].table_decimals, METRICS[key].higher_is_better)
    for key in PAPER_METRICS + ("skeleton_dice", "components")
] + [("wall_s", "wall time (s)", 1.0, 1, False)]

# The metric columns of results.csv, in order.
METRIC_COLUMNS = ["cldice", "tprec", "tsens", "skeleton_dice", "dice", "iou", "chamfer_l2_mm", "re_error", "re_mse",
                  "reprojection_dice_view1", "reprojection_dice_view2", "voxels_predicted", "voxels_label",
                  "input_mask_cldice_view1", "input_mask_cldice_view2", "motion_mm", "motion_deg",
                  "calibration_shift_mm_view2", "true_shift_mm_view2",
                  "calibration_rotation_in_plane_deg_view2", "true_rotation_in_plane_deg_view2",
                  "calibration_rotation_tilt_deg_view2", "true_rotation_tilt_deg_view2",
                  "components", "largest_component_fraction", "components_label",
                  "depth_offset_mm", "cldice_depth_aligned", "dice_depth_aligned"]
