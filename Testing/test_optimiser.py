"""Optimiser: presets and modes, input validation, and tiny end-to-end reconstructions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.losses import partial_occupancy_loss, silhouette
from SDFCARLib.field import ImplicitField
from SDFCARLib.optimiser import (ReconstructionCancelled, averaging_start, build_problem, evaluate_volume, field_config,
                                   fit_field, optimise, ramped_alpha, reconstruct, validate_targets)
from SDFCARLib.settings import MODES, ReconstructionError, Settings, make_settings
from SDFCARLib.phantoms import Branch, CentrelineTree, simulate_views, voxelize
from SDFCARLib.projector import project_volume


# --- target validation -------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def case():
    grid = VolumeGrid((24, 24, 24), (2.0, 2.0, 2.0))
    views = [CArmView(a, 0.0, 1000.0, 750.0, (1.0, 1.0), (64, 64)) for a in (30.0, -30.0)]
    tree = CentrelineTree([Branch(np.array([[-12.0, -6.0, -10.0], [0.0, 2.0, 0.0], [12.0, 6.0, 10.0]]),
                                  np.array([3.0, 2.5, 2.0]))])
    label = voxelize(tree, grid)
    line_integrals, masks = simulate_views(label, grid, views)
    return Geometry(grid, views), label, line_integrals, masks


def _masks(case):
    return [m.astype(np.uint8) * 255 for m in case[3]]


def test_validate_targets_accepts_and_normalises_masks(case):
    geometry = case[0]
    out = validate_targets(_masks(case), geometry, "mask")
    assert all(a.dtype == np.float32 and set(np.unique(a)) == {0.0, 1.0} for a in out)
    out = validate_targets([m.astype(bool) for m in case[3]], geometry, "mask")
    assert len(out) == 2
    out = validate_targets(case[2], geometry, "line_integral")
    np.testing.assert_allclose(out[0], case[2][0])


def _replace(items, index, value):
    items = list(items)
    items[index] = value
    return items


@pytest.mark.parametrize("make_bad, fragment", [
    (lambda m: m[:1], "1 target image(s) for 2 view(s)"),
    (lambda m: m + m[:1], "3 target image(s) for 2 view(s)"),
    (lambda m: _replace(m, 1, m[1][:60]), "view 2: mask shape (60, 64) differs from the detector shape"),
    (lambda m: _replace(m, 0, np.where(m[0] > 0, np.nan, 0.0)), "view 1: the mask contains NaN"),
    (lambda m: _replace(m, 1, np.zeros_like(m[1])), "view 2: the mask is empty"),
    (lambda m: _replace(m, 0, np.full_like(m[0], 255)), "view 1: the mask covers the whole image"),
    (lambda m: _replace(m, 0, m[0] // 255 * np.arange(64, dtype=np.uint8)[None, :]), "view 1: the mask is not binary"),
    (lambda m: _replace(m, 1, np.full(m[1].shape, "a")), "view 2: data type"),
])
def test_validate_targets_errors(case, make_bad, fragment):
    with pytest.raises(ReconstructionError) as info:
        validate_targets(make_bad(_masks(case)), case[0], "mask")
    assert fragment in str(info.value)


def test_validate_line_integral_targets_errors(case):
    geometry, _, line_integrals, _ = case
    with pytest.raises(ReconstructionError, match="non-negative"):
        validate_targets(_replace(line_integrals, 0, line_integrals[0] - 1.0), geometry, "line_integral")
    with pytest.raises(ReconstructionError, match="all zero"):
        validate_targets(_replace(line_integrals, 1, np.zeros_like(line_integrals[1])), geometry, "line_integral")
    with pytest.raises(ReconstructionError, match="target kind"):
        validate_targets(line_integrals, geometry, "density")


def test_reconstruct_rejects_bad_input_before_working(case):
    geometry = case[0]
    calls = []
    with pytest.raises(ReconstructionError, match="mask is empty"):
        reconstruct(geometry, _replace(_masks(case), 0, np.zeros((64, 64))), make_settings("fast", steps=5),
                    progress=calls.append)
    assert calls == []
    # masks whose back-projections never meet inside the volume (mask 2 of a distant region)
    corner = np.zeros((64, 64), np.uint8)
    corner[:3, :3] = 1
    far = _replace(_masks(case), 1, corner)
    with pytest.raises(ReconstructionError, match="do not intersect"):
        reconstruct(geometry, far, make_settings("fast", steps=5))
    # one view alone: no depth to reconstruct
    one_view = Geometry(geometry.volume, geometry.views[:1])
    with pytest.raises(ReconstructionError, match="the geometry has 1 view; a 3D reconstruction needs at least two views"):
        reconstruct(one_view, _masks(case)[:1], make_settings("fast", steps=5), progress=calls.append)
    assert calls == []


def test_reconstruct_takes_its_settings_as_the_jobs_do_a_preset_and_the_keys_it_changes(case):
    geometry = case[0]
    with pytest.raises(ReconstructionError, match="unknown preset"):
        reconstruct(geometry, _masks(case), {"preset": "quick", "steps": 5})
    result = reconstruct(geometry, _masks(case), {"steps": 5, "device": "cpu", "reconnect": False})
    assert isinstance(result.settings, Settings)
    assert result.settings == make_settings("fast", steps=5, device="cpu", reconnect=False)
    assert result.settings.run.preset == "fast" and result.settings.optimisation.steps == 5


# --- tiny reconstructions -----------------------------------------------------------------------------------------------
STEPS = 100  # the fast preset warms up for 20 steps; the occupancy modes need ~100 here


@pytest.fixture(scope="module", params=sorted(MODES))
def run(request, case):
    geometry = case[0]
    events = []
    result = reconstruct(geometry, _masks(case), make_settings("fast", mode=request.param, steps=STEPS, device="cpu"),
                         progress=events.append, progress_interval_s=0.0)
    return request.param, result, events


def test_reconstruction_outputs(run, case):
    mode, result, _ = run
    grid = case[0].volume
    assert result.occupancy.shape == result.field.shape == result.segmentation.shape == grid.shape
    assert result.occupancy.dtype == np.float32 and result.segmentation.dtype == bool
    assert np.all((result.occupancy >= 0) & (result.occupancy <= 1))
    np.testing.assert_array_equal(result.segmentation, result.occupancy >= result.settings.region.threshold)
    assert result.support is not None and result.support.shape == grid.shape
    assert not np.any(case[1] & ~result.support)  # the fast preset's support holds the whole vessel
    assert not np.any(result.occupancy[~result.support])
    assert result.settings.run.mode == mode and result.geometry == case[0]
    assert len(result.history) == STEPS and result.history[-1]["step"] == STEPS
    assert all(np.isfinite(h["loss"]) for h in result.history)


def test_reconstruction_report(run):
    mode, result, _ = run
    report = result.report
    for key in ("settings", "seed", "device", "versions", "timings_s", "final_losses", "reprojection_dice", "geometry"):
        assert key in report, key
    assert report["settings"]["mode"] == mode and report["seed"] == 0
    assert len(report["reprojection_dice"]) == 2
    assert all(0.0 <= d <= 1.0 for d in report["reprojection_dice"])
    assert report["timings_s"]["total"] > 0
    assert report["device"].startswith("cpu")
    assert "torch" in report["versions"]
    assert (report["final_losses"]["l_geo"] > 0) == MODES[mode].geometric_loss
    # the fast preset prunes whatever it segmented
    assert report["pruning"] is None if not result.segmentation.any() else report["pruning"]["pieces"] >= 1


def test_progress_reaches_total_with_increasing_steps(run):
    _, result, events = run
    steps = [e["step"] for e in events if e.get("phase") == "optimise"]
    assert steps == list(range(1, STEPS + 1))  # progress_interval_s=0: every step, in order
    last = [e for e in events if e.get("phase") == "optimise"][-1]
    assert last["total"] == STEPS and last["eta_s"] == pytest.approx(0.0)
    assert all(e["elapsed_s"] >= 0 for e in events)
    assert all({"loss", "l_occ", "l_geo", "eta_s"} <= set(e) for e in events if e.get("phase") == "optimise")
    assert events[0]["phase"] == "setup"
    after = [e["phase"] for e in events[events.index(last) + 1:]]
    assert after == ["output"] + (["prune"] if result.report["pruning"] is not None else [])


def test_reconstruction_beats_the_empty_prediction(run, case):
    # Independently of the optimiser's own bookkeeping: reproject the occupancy volume, compare it
    # with the masks in the optimiser's image model, and compare the volume with the label.
    # The empty prediction scores L_occ = mean(mask) and soft Dice 0.
    mode, result, _ = run
    geometry, label, _, masks = case
    tau = result.settings.loss.silhouette_length_mm
    occupancy = result.occupancy
    rendered = [silhouette(torch.as_tensor(project_volume(occupancy, v, geometry.volume)), tau).numpy() for v in geometry.views]
    l_occ = np.mean([np.mean((r - m) ** 2) for r, m in zip(rendered, masks)])
    l_occ_empty = np.mean([np.mean(m.astype(float)) for m in masks])
    soft_dice = 2 * float((occupancy * label).sum()) / (float(occupancy.sum()) + float(label.sum()))
    assert l_occ < 0.5 * l_occ_empty, f"{mode}: L_occ {l_occ:.4f} vs empty {l_occ_empty:.4f}"
    assert soft_dice > 0.1, f"{mode}: soft Dice {soft_dice:.3f}"


def test_line_integral_targets(case):
    geometry, label, line_integrals, _ = case
    result = reconstruct(geometry, line_integrals, make_settings("fast", mode="neca", steps=10, device="cpu"),
                         target_kind="line_integral")
    assert result.report["target_kind"] == "line_integral"
    assert result.history[-1]["l_occ"] < result.history[0]["l_occ"]


# --- cancel and repeatability ---------------------------------------------------------------------------------------------
def test_cancel_at_step_k(case):
    geometry = case[0]
    seen = []

    def cancel():
        return bool(seen) and seen[-1] >= 3

    with pytest.raises(ReconstructionCancelled, match="step 3"):
        reconstruct(geometry, _masks(case), make_settings("fast", steps=50, device="cpu"),
                    progress=lambda e: seen.append(e["step"]), cancel=cancel, progress_interval_s=0.0)
    assert max(seen) == 3


def test_cancel_before_start(case):
    with pytest.raises(ReconstructionCancelled):
        reconstruct(case[0], _masks(case), make_settings("fast", steps=50, device="cpu"), cancel=lambda: True)


def test_same_seed_same_result_different_seed_different_result(case):
    geometry = case[0]

    def once(seed):
        return reconstruct(geometry, _masks(case), make_settings("fast", steps=5, seed=seed, device="cpu"))

    a, b, c = once(1), once(1), once(2)
    np.testing.assert_array_equal(a.field, b.field)
    np.testing.assert_array_equal(a.occupancy, b.occupancy)
    assert [h["loss"] for h in a.history] == [h["loss"] for h in b.history]
    assert not np.array_equal(a.field, c.field)
    assert a.report["seed"] == 1 and c.report["seed"] == 2


def test_a_coarse_to_fine_fit_differs_from_one_with_every_level_from_the_start_and_finds_the_vessel(case):
    """coarse_to_fine_fraction (on in fast) reaches the fit (the fading itself: test_field.py), and the
    vessel is still found."""
    def fitted(fraction):
        return reconstruct(case[0], _masks(case), make_settings("fast", steps=40, seed=3, device="cpu",
                                                                 coarse_to_fine_fraction=fraction))

    every_level, coarse_first = fitted(0.0), fitted(0.5)
    assert coarse_first.report["settings"]["coarse_to_fine_fraction"] == 0.5
    assert not np.array_equal(every_level.field, coarse_first.field)
    assert coarse_first.segmentation.sum() > 0.5 * case[1].sum()
    assert every_level.segmentation.sum() > 0.5 * case[1].sum()


def test_the_alpha_ramp_is_geometric_and_clipped():
    assert ramped_alpha(10.0, 50.0, 0.0) == 10.0 and ramped_alpha(10.0, 50.0, 1.0) == pytest.approx(50.0)
    assert ramped_alpha(10.0, 50.0, 0.5) == pytest.approx(math.sqrt(10.0 * 50.0))  # the geometric mean half-way
    assert ramped_alpha(10.0, 50.0, -1.0) == 10.0 and ramped_alpha(10.0, 50.0, 2.0) == pytest.approx(50.0)


def test_a_fit_with_the_alpha_ramp_differs_and_is_read_at_the_final_alpha(case):
    """alpha_ramp_fraction reaches the fit, the vessel is still found, and the written field is the one whose
    σ(−α·s) at the configured α is the occupancy (a ramp over every step ends just short of that α)."""
    def fitted(fraction):
        return reconstruct(case[0], _masks(case), make_settings("fast", steps=40, seed=3, device="cpu",
                                                                 alpha_ramp_fraction=fraction, alpha_start=10.0))

    sharp, ramped = fitted(0.0), fitted(1.0)
    assert ramped.report["settings"]["alpha_ramp_fraction"] == 1.0
    assert not np.array_equal(sharp.field, ramped.field)
    assert ramped.segmentation.sum() > 0.5 * case[1].sum()
    inside = ramped.occupancy > 0
    np.testing.assert_allclose(ramped.occupancy[inside], 1.0 / (1.0 + np.exp(50.0 * ramped.field[inside].astype(np.float64))),
                               atol=1e-5)


def test_averaging_starts_after_the_last_exclusion_on_the_last_fifth_in_fast():
    assert averaging_start(make_settings("fast", steps=400)) == 320  # fast: the last fifth
    assert averaging_start(make_settings("fast", steps=400, average_last_fraction=0.0)) is None
    assert averaging_start(make_settings("paper")) is None  # the published recipe: Adam's last step
    assert averaging_start(make_settings("fast", steps=400, average_last_fraction=0.1)) == 360
    # the field fits something else before the exclusion at 60 %: the average starts after it
    assert averaging_start(make_settings("fast", steps=400, average_last_fraction=0.5)) == 240
    assert averaging_start(make_settings("fast", steps=400, average_last_fraction=0.5, width_exclusion_fraction=0.0)) == 200
    assert averaging_start(make_settings("fast", steps=10, average_last_fraction=0.01, width_exclusion_fraction=0.0)) == 9


def test_the_averaged_fit_holds_the_mean_of_the_last_iterates(case, monkeypatch):
    """average_last_fraction: the parameters the fit ends with are the mean of those after each of the
    averaged steps (Adam's own iterates, recorded as it makes them), not the last iterate."""
    settings = make_settings("fast", steps=8, seed=3, device="cpu", average_last_fraction=0.5,
                             width_exclusion_fraction=0.0)
    problem = build_problem(case[0], _masks(case), settings, "mask")
    torch.manual_seed(3)
    model = ImplicitField(field_config(settings))
    iterates = []
    adam_step = torch.optim.Adam.step

    def recording_step(self, *args, **kwargs):
        out = adam_step(self, *args, **kwargs)
        iterates.append([p.detach().clone() for group in self.param_groups for p in group["params"]])
        return out

    monkeypatch.setattr(torch.optim.Adam, "step", recording_step)
    optimise(problem, model)
    assert len(iterates) == 8
    parameters = [model.encoding.table] + list(model.mlp.parameters())
    for n, parameter in enumerate(parameters):
        mean = torch.stack([step[n] for step in iterates[4:]]).mean(dim=0)
        torch.testing.assert_close(parameter.detach(), mean, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(parameters[0].detach(), iterates[-1][0])  # the table moved over those steps


def test_an_ensemble_is_the_mean_occupancy_of_single_fits_of_its_seeds(case):
    """ensemble_fits: each fit is the one a single run with its seed (the run's, then + 1) makes, with its own
    mid-fit exclusion, and the result is made from the mean of their occupancies."""
    common = dict(steps=30, device="cpu", threads=1, width_exclusion_fraction=0.5)
    fitted = fit_field(case[0], _masks(case), make_settings("fast", seed=3, ensemble_fits=2, **common), keep_members=True)
    singles = [fit_field(case[0], _masks(case), make_settings("fast", seed=seed, **common)) for seed in (3, 4)]
    assert len(fitted.members) == 2
    for (occupancy, raw), single in zip(fitted.members, singles):
        single_occupancy, single_raw = evaluate_volume(single.model, single.problem)
        np.testing.assert_allclose(occupancy, single_occupancy, atol=1e-6)
        np.testing.assert_allclose(raw, single_raw, atol=1e-6)
    assert not np.allclose(fitted.members[0][0], fitted.members[1][0], atol=1e-3)  # two different fits
    mean = (fitted.members[0][0] + fitted.members[1][0]) / 2
    np.testing.assert_allclose(fitted.volumes[0], mean, atol=1e-6)
    inside = (mean > 1e-4) & (mean < 1 - 1e-4)  # where the raw field is not clipped
    np.testing.assert_allclose(1 / (1 + np.exp(50.0 * fitted.volumes[1][inside])), mean[inside], rtol=1e-4, atol=1e-6)
    # each fit took out what its own width check found; the report keeps both records
    assert [record is not None for record in fitted.problem.exclusion["fits"]] == [True, True]


def test_an_ensemble_reports_progress_over_all_its_fits_and_its_seeds(case):
    seen = []
    settings = make_settings("fast", steps=40, seed=3, device="cpu", ensemble_fits=2)
    result = reconstruct(case[0], _masks(case), settings, progress=seen.append, progress_interval_s=0.0)
    steps = [info["step"] for info in seen if info["phase"] == "optimise"]
    assert steps == list(range(1, 81))  # the second fit counts on from the first
    assert {info["total"] for info in seen if "total" in info} == {80}
    assert result.report["ensemble_seeds"] == [3, 4]
    assert result.report["timings_s"]["per_step"] == pytest.approx(result.report["timings_s"]["optimise"] / 80)
    assert (result.segmentation & case[1].astype(bool)).sum() > 0.5 * case[1].sum()


def test_a_best_reprojecting_ensemble_keeps_the_single_fit_whose_result_reprojects_best(case):
    """ensemble_combine "best_reprojection": each fit is finished as a single run with its seed would be (its
    own exclusion), and the result is, whole, the one whose segmentation has the highest mean reprojection Dice."""
    common = dict(steps=80, device="cpu", threads=1, width_exclusion_fraction=0.5)
    singles = {seed: reconstruct(case[0], _masks(case), make_settings("fast", seed=seed, **common)) for seed in (3, 4, 5)}
    scores = {seed: float(np.mean(r.report["reprojection_dice"])) for seed, r in singles.items()}
    assert len(set(scores.values())) == 3  # the draws differ, so the choice is tested
    result = reconstruct(case[0], _masks(case), make_settings("fast", seed=3, ensemble_fits=3,
                                                              ensemble_combine="best_reprojection", **common))
    chosen = max(scores, key=scores.get)
    choice = result.report["ensemble_choice"]
    assert choice["seeds"] == [3, 4, 5] and choice["chosen_seed"] == chosen and choice["chosen_fit"] == chosen - 3
    np.testing.assert_allclose(choice["reprojection_dice"], [singles[s].report["reprojection_dice"] for s in (3, 4, 5)])
    single = singles[chosen]
    np.testing.assert_array_equal(result.segmentation, single.segmentation)
    np.testing.assert_allclose(result.occupancy, single.occupancy, atol=1e-6)
    def without_seconds(report):
        return [{k: v for k, v in e.items() if k != "seconds"} for e in report["width_exclusion"]["exclusions"]]
    assert without_seconds(result.report) == without_seconds(single.report)  # the chosen fit's own exclusion
    assert [h["loss"] for h in result.history] == pytest.approx([h["loss"] for h in single.history])
    assert result.report["ensemble_seeds"] == [3, 4, 5]


def test_partial_occupancy_term_makes_the_fitted_field_more_binary(case):
    """lambda_binary (L_bin, off by default) reaches the fit: the same run with it holds less of its
    vessel mass at partial occupancy, and the vessel is still there."""
    def fitted(weight):
        result = reconstruct(case[0], _masks(case), make_settings("fast", steps=40, seed=3, device="cpu",
                                                                   lambda_binary=weight))
        occupancy = torch.sigmoid(-result.settings.field.alpha * torch.as_tensor(result.field))
        return float(partial_occupancy_loss(occupancy)), float(occupancy.sum())

    (share_off, _), (share_on, mass_on) = fitted(0.0), fitted(0.01)
    assert share_on < 0.5 * share_off
    assert mass_on > 0.5 * case[1].sum()  # more binary, not emptied
