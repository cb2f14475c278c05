"""A tree rooted where no coronary ostium is (root_check.py): a guiding catheter, or a distal end, taken as the ostium."""

from __future__ import annotations

import numpy as np
import pytest

from SDFCARLib.analysis.phantoms import grid_around, voxelize_exact
from SDFCARLib.analysis.root_check import (MIN_NARROW_STRETCH_MM, THROUGH_JUNCTION_MM, THROUGH_MIN_ANGLE_DEG,
                                           THROUGH_MIN_LENGTH_MM, narrow_root, narrow_root_warning,
                                           through_vessel_root, through_vessel_root_warning)


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
    assert result.settings["through_vessel_root"] is None  # its left main's bifurcation is no vessel's side


def _line(start, direction, length_mm):
    direction = np.asarray(direction, float) / np.linalg.norm(direction)
    return np.asarray(start, float) + np.arange(0.0, length_mm + 1e-9, 0.5)[:, None] * direction


def _root_and_side_branch(junction_mm=2.0, angle_deg=160.0, side_mm=40.0, root_branch_mm=60.0):
    """A root branch along +x from the origin and a side branch leaving it ``junction_mm`` from the root at
    ``angle_deg`` to it."""
    from SDFCARLib.analysis.centreline import CentrelineBranch, CentrelineTree

    main = _line((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), root_branch_mm)
    at = int(round(junction_mm / 0.5))
    a = np.radians(angle_deg)
    side = _line(main[at], (np.cos(a), np.sin(a), 0.0), side_mm)
    # the side branch thickens towards its far end (the ostium's end)
    return CentrelineTree([CentrelineBranch(0, main, np.full(len(main), 1.5)),
                           CentrelineBranch(1, side, np.linspace(1.5, 2.0, len(side)), parent_id=0, parent_index=at)])


def test_a_root_two_long_branches_leave_both_ways_is_found_and_a_bifurcation_is_not():
    found = through_vessel_root(_root_and_side_branch())
    assert found["angle_deg"] == pytest.approx(160.0, abs=0.01) and found["junction_from_root_mm"] == pytest.approx(2.0)
    assert found["branch_ids"] == [0, 1] and found["lengths_mm"] == pytest.approx([58.0, 40.0])
    np.testing.assert_allclose(found["far_ends_mm"][0], (60.0, 0.0, 0.0))
    np.testing.assert_allclose(found["far_ends_mm"][1], (2.0 + 40.0 * np.cos(np.radians(160.0)), 40.0 * np.sin(np.radians(160.0)), 0.0))
    assert found["root_mm"] == [0.0, 0.0, 0.0] and found["likeliest_ostium_mm"] == found["far_ends_mm"][1]
    # the branches part under the angle; the junction as far as a left main's bifurcation; either way short
    assert through_vessel_root(_root_and_side_branch(angle_deg=THROUGH_MIN_ANGLE_DEG - 5.0)) is None
    assert through_vessel_root(_root_and_side_branch(angle_deg=THROUGH_MIN_ANGLE_DEG + 5.0)) is not None
    assert through_vessel_root(_root_and_side_branch(junction_mm=THROUGH_JUNCTION_MM + 3.0)) is None
    assert through_vessel_root(_root_and_side_branch(side_mm=THROUGH_MIN_LENGTH_MM - 5.0)) is None
    assert through_vessel_root(_root_and_side_branch(root_branch_mm=2.0 + THROUGH_MIN_LENGTH_MM - 5.0)) is None
    assert through_vessel_root_warning(None) is None
    text = through_vessel_root_warning(found)
    likeliest = ", ".join(f"{v:.1f}" for v in found["likeliest_ostium_mm"])
    assert "(0.0, 0.0, 0.0) LPS mm" in text and "160° apart" in text and f"({likeliest}) LPS mm" in text
    assert "likeliest ostium" in text and "--ostium " + likeliest.replace(",", "") + ";" in text  # ready to paste


def test_a_tree_rooted_at_a_ghost_on_its_vessel_s_side_is_warned_of_and_not_where_the_ostium_is_given():
    from SDFCARLib.analysis.pipeline import analyse_volume, summary
    from SDFCARLib.phantoms import Branch, CentrelineTree

    t = np.linspace(0.0, 1.0, 201)
    vessel = np.stack([-50.0 + 100.0 * t, 8.0 * np.sin(np.pi * t), np.zeros_like(t)], axis=1)  # 100 mm, bent
    # a blob thicker than the vessel's 4 mm ostium, on its middle: the tree's thickest end
    ghost = vessel[100] + np.linspace(0.0, 6.0, 20)[:, None] * np.array([0.0, 0.0, 1.0])
    tree = CentrelineTree([Branch(vessel, np.linspace(2.0, 1.0, t.size), "vessel"), Branch(ghost, np.full(20, 2.6), "ghost")])
    grid = grid_around(tree, 0.5)
    volume = voxelize_exact(tree, grid).astype(np.float32)
    result = analyse_volume(volume, grid, best_view=False)
    found = result.settings["through_vessel_root"]
    assert np.linalg.norm(np.asarray(found["root_mm"]) - vessel[100]) < 8.0  # rooted at the blob
    assert found["angle_deg"] > 120.0 and min(found["lengths_mm"]) > 40.0
    ends = np.asarray(found["far_ends_mm"])
    assert min(np.linalg.norm(ends - vessel[0], axis=1)) < 3.0 and min(np.linalg.norm(ends - vessel[-1], axis=1)) < 3.0
    assert np.linalg.norm(np.asarray(found["likeliest_ostium_mm"]) - vessel[0]) < 3.0  # the vessel's thick end
    assert any("lies on the side of a vessel" in w for w in summary(result)["warnings"])
    given = analyse_volume(volume, grid, ostium_mm=vessel[0], best_view=False)
    assert given.settings["through_vessel_root"] is None
    assert not any("side of a vessel" in w for w in summary(given)["warnings"])
