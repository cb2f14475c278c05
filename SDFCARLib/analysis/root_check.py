"""Is the tree's root a coronary ostium? A check for a root the main vessel widens away from.

Where no ostium is given, the tree is rooted at its thickest end (``centreline.py``). Every clinical
angiogram shows the guiding catheter entering the ostium, and the masks take it for a vessel; in the
reconstruction it continues the tree beyond the ostium to where it leaves a view, and its free end
becomes the root: lengths are counted from it, and the step from the catheter (2 mm for 6 F) to the
wider vessel reads as a stenosis at the start of the main branch. On reconstructions from realistic masks the
thickest end is sometimes a distal end, where the proximal vessel's own end came out thin or joined to a
ghost: the tree is then read backwards.

A coronary artery narrows from its ostium. The check reads the main branch's 3D sections: the median
equivalent diameter over its first ``ROOT_SPAN_MM`` against the widest median over ``WINDOW_MM``
windows up to ``SEARCH_MM`` along it. Where the vessel widens by ``MIN_WIDENING`` or more, after a narrow
stretch (the smoothed diameter under ``NARROW_SHARE`` × the widest) of at least ``MIN_NARROW_STRETCH_MM``,
the root is not an ostium as measured: a catheter, a distal end, or a long ostial lesion.
Nothing is cut; the analysis says so and how to give the ostium. Measured in bench/RESULTS.md §103f.
"""

from __future__ import annotations

from typing import Any, Dict, Optional

import numpy as np

ROOT_SPAN_MM = 5.0
WINDOW_MM = 3.0
SEARCH_MM = 60.0
#: trees measured 1.0–1.27 (the widest window at the first bifurcation), lone tubes ≤ 1.03, a tree with a catheter 2.0–2.5
MIN_WIDENING = 1.6
NARROW_SHARE = 0.8
MIN_NARROW_STRETCH_MM = 10.0


def narrow_root(arc_mm: np.ndarray, diameter_mm: np.ndarray) -> Optional[Dict[str, float]]:
    """Where the main branch (arc length and 3D section diameter per point, from the root) widens by
    ``MIN_WIDENING`` after a narrow stretch of ``MIN_NARROW_STRETCH_MM``: the root's and the wide part's
    diameters (mm), the widening and where the vessel reaches the wide part's ``NARROW_SHARE`` (mm from the
    root); None where it does not."""
    arc, diameter = np.asarray(arc_mm, float), np.asarray(diameter_mm, float)

    def median_over(start: float, span: float) -> float:
        inside = (arc >= start) & (arc <= start + span) & np.isfinite(diameter)
        return float(np.median(diameter[inside])) if inside.any() else float("nan")

    root = median_over(0.0, ROOT_SPAN_MM)
    if not root > 0:
        return None
    starts = np.arange(0.0, SEARCH_MM, 0.5)
    smoothed = np.array([median_over(s, WINDOW_MM) for s in starts])
    beyond = starts >= ROOT_SPAN_MM
    if not np.isfinite(smoothed[beyond]).any():
        return None
    wide = float(np.nanmax(smoothed[beyond]))
    if wide < MIN_WIDENING * root:
        return None
    reached = np.flatnonzero(np.isfinite(smoothed) & (smoothed >= NARROW_SHARE * wide))
    stretch = float(starts[reached[0]]) if reached.size else float("nan")
    if not stretch >= MIN_NARROW_STRETCH_MM:
        return None
    return {"root_diameter_mm": root, "wide_diameter_mm": wide, "widening": wide / root, "narrow_stretch_mm": stretch}


def narrow_root_warning(found: Optional[Dict[str, Any]]) -> Optional[str]:
    """The warning for ``narrow_root``'s finding (with ``root_mm``, the root's LPS position, added by the caller)."""
    if not found:
        return None
    where = ", ".join(f"{v:.1f}" for v in found["root_mm"])
    return (f"the tree's thickest end, taken as the ostium at ({where}) LPS mm, leads through "
            f"{found['narrow_stretch_mm']:.0f} mm of vessel {found['root_diameter_mm']:.1f} mm wide into one "
            f"{found['wide_diameter_mm']:.1f} mm wide ({found['widening']:.1f}×): a coronary artery narrows from its "
            "ostium, so this root is likely not the ostium — the guiding catheter, a distal end where the proximal "
            "vessel's own end came out thin, or a long ostial lesion. Lengths, positions and branch order are counted "
            "from it, and where it widens reads as a stenosis. Give the ostium where the artery begins (analyse --ostium "
            "X Y Z in LPS mm; in Slicer a one-point list as the Ostium; in Python analyse_result_dir(…, ostium_mm=…)); a "
            "catheter can also be erased from the masks before reconstructing.")
