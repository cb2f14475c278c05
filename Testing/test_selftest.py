"""The shared self-test scenario, run headless with the real MRML of slicer-core.

The Slicer module's SDFCARTest runs the same ``SDFCARLib.selftest.run_selftest``; here it runs
against a bare slicer-core scene. The real scenario is one short reconstruction; the other tests
replace the reconstruction by known answers to show that the checks catch what they should.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("slicer", reason="the self-test needs the slicer-core package (pip install slicer-core)")

from SDFCARLib import mrml, optimiser, selftest  # noqa: E402


def node_ids(scene):
    return [scene.GetNthNode(i).GetID() for i in range(scene.GetNumberOfNodes())]


@pytest.fixture(scope="module")
def case():
    return selftest.selftest_case()


def test_selftest_scenario_passes_headless(case):
    scene = mrml.new_scene()
    messages = []
    t0 = time.perf_counter()
    result = selftest.run_selftest(scene, log=messages.append, case=case)
    elapsed = time.perf_counter() - t0
    for key, floor in selftest.FLOORS.items():
        assert result.metrics[key] >= floor, key
    assert scene.GetFirstNodeByName("SDFCAR self-test").IsA("vtkMRMLSegmentationNode")
    assert scene.GetFirstNodeByName("SDFCAR self-test surface").GetPolyData().GetNumberOfPoints() > 0
    assert any("passed" in m for m in messages)
    # The scenario is meant for a quick check in Slicer: a few tens of seconds on a CPU.
    assert elapsed < 180, f"the self-test took {elapsed:.0f} s"


def fake_reconstruct(segmentation_of):
    """A stand-in for optimiser.reconstruct whose segmentation is ``segmentation_of(label)``."""
    def run(geometry, targets, settings=None, **kwargs):
        label = run.case.label
        seg = segmentation_of(label)
        occupancy = seg.astype(np.float32)
        report = {"settings": settings.to_dict(), "geometry_digest": geometry.digest(), "reprojection_dice": [1.0, 1.0],
                  "final_losses": {"loss": 0.0, "l_occ": 0.0, "l_geo": 0.0}}
        return optimiser.Reconstruction(geometry, settings, occupancy, occupancy, seg, None, report)
    return run


def test_selftest_checks_pass_for_the_ground_truth(case, monkeypatch):
    fake = fake_reconstruct(lambda label: label.copy())
    fake.case = case
    monkeypatch.setattr(optimiser, "reconstruct", fake)
    scene = mrml.new_scene()
    result = selftest.run_selftest(scene, log=lambda m: None, case=case)
    assert result.metrics["dice"] == 1.0 and result.metrics["cldice"] == 1.0
    # Every centreline point lies inside its own tube, hence in the ground truth's voxels (±1 voxel).
    assert result.metrics["centreline_in_segment"] >= 0.95


def test_selftest_catches_a_misplaced_result_and_cleans_up(case, monkeypatch):
    # The ground truth mirrored along x: what a missing LPS→RAS flip of x would produce.
    fake = fake_reconstruct(lambda label: label[::-1].copy())
    fake.case = case
    monkeypatch.setattr(optimiser, "reconstruct", fake)
    scene = mrml.new_scene()
    before = node_ids(scene)
    with pytest.raises(selftest.SelfTestFailure, match="below the floor"):
        selftest.run_selftest(scene, log=lambda m: None, keep_nodes=False, case=case)
    assert node_ids(scene) == before


def test_selftest_floors_can_be_raised(case, monkeypatch):
    fake = fake_reconstruct(lambda label: label.copy())
    fake.case = case
    monkeypatch.setattr(optimiser, "reconstruct", fake)
    with pytest.raises(selftest.SelfTestFailure, match="'reprojection_dice' failed: 1.000 is below the floor 1.100"):
        selftest.run_selftest(mrml.new_scene(), log=lambda m: None, floors={"reprojection_dice": 1.1}, case=case)
