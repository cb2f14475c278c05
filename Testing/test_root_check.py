"""A tree rooted where no coronary ostium is (root_check.py): a guiding catheter, or a distal end, taken as the ostium."""

from __future__ import annotations

import numpy as np
import pytest

from SDFCARLib.analysis.phantoms import grid_around, voxelize_exact
from SDFCARLib.analysis.root_check import MIN_NARROW_STRETCH_MM, narrow_root, narrow_root_warning


def test_a_vessel_that_doubles_after_a_long_narrow_stretch_is_found_and_a_tapering_one_is_not():
    arc = np.arange(0.0, 80.0, 0.1)
    catheter = np.where(arc < 30.0, 2.0, 4.0)  # 2 mm for 30 mm, then the 4 mm artery
    found = narrow_root(arc, catheter)
    assert found["root_diameter_mm"] == pytest.approx(2.0) and found["wide_diameter_mm"] == pytest.approx(4.0)
    assert found["widening"] == pytest.approx(2.0) and 27.0 <= found["narrow_stretch_mm"] <= 30.0
    assert narrow_root(arc, np.linspace(4.0, 1.5, arc.size)) is None  # an artery narrows from its ostium
    # a short narrowing at the root (an ostial lesion of a few millimetres) is no catheter
    short = np.where(arc < MIN_NARROW_STRETCH_MM - 4.0, 2.0, 4.0)
    assert narrow_root(arc, short) is None
    assert narrow_root(arc, np.where(arc < 30.0, 3.0, 4.0)) is None  # 1.33×: a bifurcation's wide section, not a step
    unknown = catheter.copy()
    unknown[::3] = np.nan  # sections the rays could not close
    assert narrow_root(arc, unknown)["widening"] == pytest.approx(2.0)
    assert narrow_root(arc, np.full(arc.size, np.nan)) is None and narrow_root(arc[:0], catheter[:0]) is None
    assert narrow_root_warning(None) is None
    text = narrow_root_warning(dict(found, root_mm=[1.0, 2.0, 3.0]))
    assert "(1.0, 2.0, 3.0) LPS mm" in text and "guiding catheter" in text and "--ostium" in text


def test_a_catheter_continuing_the_tree_is_warned_of_and_an_ostium_given_or_a_tree_without_one_is_not():
    from SDFCARLib.analysis.pipeline import analyse_volume, summary
    from SDFCARLib.phantoms import Branch, CentrelineTree, lad_tree

    tree = lad_tree(0)  # its main vessel 4 mm wide at the ostium
    ostium = tree.branches[0].points[0]
    up = np.array([-0.3, 0.0, 1.0]) / np.hypot(0.3, 1.0)  # towards the head and the patient's right, as from the aorta
    catheter = Branch(ostium + np.linspace(0.0, 30.0, 60)[:, None] * up, np.full(60, 1.0), "catheter")  # 6 F: 2 mm
    with_catheter = CentrelineTree(tree.branches + [catheter], tree.name)

    def analysed(t, ostium_mm=None):
        grid = grid_around(t, 0.5)
        result = analyse_volume(voxelize_exact(t, grid).astype(np.float32), grid, ostium_mm=ostium_mm, best_view=False)
        return result, [w for w in summary(result)["warnings"] if "likely not the ostium" in w]

    result, [warning] = analysed(with_catheter)
    found = result.settings["narrow_root"]
    assert np.linalg.norm(np.asarray(found["root_mm"]) - catheter.points[-1]) < 3.0  # rooted at the catheter's free end
    assert found["widening"] > 1.6 and found["narrow_stretch_mm"] == pytest.approx(30.0, abs=4.0)
    assert "guiding catheter" in warning
    result, warnings = analysed(with_catheter, ostium_mm=ostium)  # the user says where the artery begins
    assert warnings == [] and result.settings["narrow_root"] is None
    result, warnings = analysed(tree)
    assert warnings == [] and result.settings["narrow_root"] is None
