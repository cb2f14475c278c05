"""The 3D-QCA benchmark's own geometry (bench/qca.py): what it scores against must be the truth's."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import qca  # noqa: E402


def _line(start, end, step_mm=0.1):
    start, end = np.asarray(start, float), np.asarray(end, float)
    n = int(round(np.linalg.norm(end - start) / step_mm)) + 1
    return start + np.linspace(0.0, 1.0, n)[:, None] * (end - start)


def test_the_truth_span_follows_a_segment_across_a_junction():
    # A main vessel that divides at (20, 0, 0); the samples concatenated as a tree's are, the child the
    # segment does not follow between the two it crosses.
    main, other_child, followed = _line([0, 0, 0], [20, 0, 0]), _line([20, 0, 0], [20, -20, 0]), _line([20, 0, 0], [20, 20, 0])
    points = np.concatenate([main, other_child, followed])
    names = np.array(["main"] * len(main) + ["other"] * len(other_child) + ["followed"] * len(followed))
    segment = np.concatenate([_line([10, 0.1, 0], [20, 0.1, 0], 0.25), _line([20.1, 0.25, 0], [20.1, 10, 0], 0.25)])
    span = qca._truth_span(segment, points, names, cKDTree(points))
    length_mm = np.linalg.norm(np.diff(span, axis=0), axis=1).sum()
    assert abs(length_mm - 20.0) < 0.3, length_mm
    assert cKDTree(segment).query(span)[0].max() < 0.3  # nothing of the other child
    np.testing.assert_allclose(span[0], [10, 0, 0], atol=0.15)
    np.testing.assert_allclose(span[-1], [20, 10, 0], atol=0.15)


def test_the_truth_path_runs_from_the_ostium_through_each_ancestor_to_the_branch_end():
    # A root along x with two children leaving at x = 5 (one of them the path's) and a grandchild leaving
    # the path's child 2 mm up; stored as the phantoms store them, each child's first point on its parent.
    from SDFCARLib.phantoms import Branch, CentrelineTree

    root = _line([0, 0, 0], [10, 0, 0], 0.5)
    sibling, child = _line([5, 0, 0], [5, -4, 0], 0.5), _line([5, 0, 0], [5, 4, 0], 0.5)
    grandchild = _line([5, 2, 0], [8, 2, 0], 0.5)
    tree = CentrelineTree([Branch(p, np.ones(len(p)), n) for p, n in
                           ((root, "root"), (sibling, "sibling"), (child, "child"), (grandchild, "grandchild"))])

    def length(path):
        return np.linalg.norm(np.diff(path, axis=0), axis=1).sum()

    assert length(qca._truth_path_to(tree, [10.2, 0.1, 0])) == pytest.approx(10.0)
    assert length(qca._truth_path_to(tree, [5.1, 3.9, 0])) == pytest.approx(5.0 + 4.0)
    assert length(qca._truth_path_to(tree, [5.0, -4.2, 0])) == pytest.approx(5.0 + 4.0)
    path = qca._truth_path_to(tree, [8, 2.1, 0])
    assert length(path) == pytest.approx(5.0 + 2.0 + 3.0)
    assert np.abs(path[:, 1]).max() <= 2.0  # never down the sibling
    with pytest.raises(ValueError, match="ostium"):
        qca._truth_path_to(CentrelineTree([tree.branches[0], Branch(grandchild + [0, 5, 0], np.ones(len(grandchild)))]),
                           [8, 7, 0])


def test_a_third_view_analyses_the_same_tubes(monkeypatch):
    # --views adds AP cranial 30: the tubes' axes are drawn against the two views of the pair only, so the
    # three-view rows compare with the two-view ones tube by tube
    pair = [qca.tube_direction(seed, 15.0) for seed in range(10)]
    monkeypatch.setattr(qca, "VIEWS", list(qca.standard_geometry("lao30-rao30-cra30").views))
    assert len(qca.VIEWS) == 3
    with_third = [qca.tube_direction(seed, 15.0) for seed in range(10)]
    np.testing.assert_array_equal(pair, with_third)
    for direction in with_third:
        assert max(qca.axis_foreshortening_pct(direction)[:2]) <= 15.0
    # the limit does constrain: some first draw was rejected on the pair
    assert any(not np.array_equal(d, np.random.default_rng(seed).normal(size=3)) for seed, d in enumerate(pair))


def test_a_third_view_keeps_the_pair_s_frames_and_motion(monkeypatch):
    # the segmented-moving input with AP cranial 30 added: views 1 and 2 exactly as without it, a third of its own
    from SDFCARLib.analysis.phantoms import stenosed_tube

    tube = stenosed_tube(length_mm=40.0, direction=qca.tube_direction(0, 15.0), **qca.RECON_TUBES[0][1])
    masks2, dice2, frames2, moved2 = qca.segmented_masks(tube.tree, 0, moving=True)
    monkeypatch.setattr(qca, "VIEWS", list(qca.standard_geometry("lao30-rao30-cra30").views))
    masks3, dice3, frames3, moved3 = qca.segmented_masks(tube.tree, 0, moving=True)
    assert len(masks2) == len(frames2) == 2 and len(masks3) == len(frames3) == len(dice3) == 3
    for n in range(2):
        np.testing.assert_array_equal(masks3[n], masks2[n])
        np.testing.assert_array_equal(frames3[n], frames2[n])
    assert dice3[:2] == dice2 and masks3[2].any() and 0.8 < dice3[2] <= 1.0
    # the motion reported is the larger of the two moved views' (view 2's is the pair's)
    shift = lambda m: float(np.linalg.norm(m["translation_mm"]))  # noqa: E731
    assert shift(moved3) >= shift(moved2) > 0.0
