"""Settings: the published recipe as defaults, presets, modes, typed overrides, and no torch on import."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from SDFCARLib.settings import (
    GROUPS,
    METRICS,
    MODES,
    PRESETS,
    SETTING_KEYS,
    ReconstructionError,
    Settings,
    make_settings,
    parse_setting_overrides,
    setting_help,
)


def test_importing_settings_loads_no_torch():
    code = "import sys, SDFCARLib.settings; assert 'torch' not in sys.modules, 'torch was imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_defaults_are_the_published_recipe_and_paper_adds_nothing():
    s = make_settings("paper")
    assert PRESETS["paper"] == {} and s.to_dict() == {**Settings().to_dict(), "preset": "paper"}
    assert s.run.preset == "paper" and s.run.mode == "sdfcar"
    assert s.optimisation.learning_rate == 1e-4 and s.optimisation.steps == 5000
    assert (s.loss.lambda_geo, s.loss.lambda_occ, s.field.alpha) == (1.0, 0.25, 50.0)
    assert (s.field.levels, s.field.log2_table_size, s.field.features_per_level) == (16, 19, 2)
    assert (s.field.width, s.field.depth) == (256, 8)
    assert s.region.support == "full" and s.loss.dt_downsample == 1


def test_fast_preset_keeps_losses_and_representation():
    paper, fast = make_settings("paper"), make_settings("fast")
    assert fast.run.preset == "fast" and fast.region.support == "hull" and fast.region.prune
    assert fast.optimisation.steps < paper.optimisation.steps
    assert (fast.loss.lambda_geo, fast.loss.lambda_occ, fast.field.alpha) == (1.0, 0.25, 50.0)
    assert fast.mode.field_kind == paper.mode.field_kind == "sdf"
    # every key of a preset is a setting
    assert all(set(values) <= set(SETTING_KEYS) for values in PRESETS.values())


def test_ensemble_preset_is_fast_fitted_three_times():
    fast, ensemble = make_settings("fast").to_dict(), make_settings("ensemble").to_dict()
    assert fast["ensemble_fits"] == 1 and ensemble["ensemble_fits"] == 3
    assert {key: value for key, value in ensemble.items() if fast[key] != value} == {"preset": "ensemble", "ensemble_fits": 3}
    assert make_settings("ensemble").optimisation.total_steps == 3 * make_settings("fast").optimisation.steps


@pytest.mark.parametrize("preset", sorted(PRESETS))
@pytest.mark.parametrize("mode, kind, geometric", [
    ("sdfcar", "sdf", True), ("neca", "occupancy", False), ("occ-combined", "occupancy", True), ("sdf-occ", "sdf", False),
])
def test_modes_select_representation_and_loss(preset, mode, kind, geometric):
    s = make_settings(preset, mode=mode)
    assert s.run.mode == mode and s.run.preset == preset
    assert s.mode.field_kind == kind and MODES[mode].geometric_loss is geometric
    assert s.to_dict()["mode"] == mode


def test_keys_are_unique_across_groups_and_round_trip():
    keys = [f for cls in GROUPS.values() for f in cls.__dataclass_fields__]
    assert len(keys) == len(set(keys)) == len(SETTING_KEYS)
    s = make_settings("fast", steps=30, seed=5, support_margin_mm=1.5)
    assert Settings.from_dict(s.to_dict()) == s
    assert s.replace(steps=31).optimisation.steps == 31 and s.optimisation.steps == 30


def test_overrides_and_none_values():
    s = make_settings("fast", steps=30, seed=5, learning_rate=None)
    assert s.optimisation.steps == 30 and s.run.seed == 5
    assert s.optimisation.learning_rate == make_settings("fast").optimisation.learning_rate


@pytest.mark.parametrize("kwargs, fragment", [
    (dict(preset="slow"), "unknown preset 'slow'"),
    (dict(mode="nerf"), "unknown mode 'nerf'"),
    (dict(stepz=10), "unknown setting(s): stepz"),
    (dict(steps=0), "steps"),
    (dict(learning_rate=-1.0), "learning_rate"),
    (dict(alpha=0.0), "alpha"),
    (dict(device="tpu"), "device"),
    (dict(support="box"), "support"),
    (dict(dt_downsample=0), "dt_downsample"),
    (dict(threshold=1.0), "threshold"),
    (dict(threads=0), "threads"),
    (dict(lambda_occ_frames=-0.5), "lambda_occ_frames is a loss weight"),
    (dict(lambda_binary=-0.01), "lambda_binary is a loss weight"),
    (dict(frame_blur_sigma_mm=-0.3), "frame_blur_sigma_mm is a detector blur in mm"),
    (dict(coarse_to_fine_fraction=-0.1), "coarse_to_fine_fraction is the share of the steps"),
    (dict(coarse_to_fine_fraction=1.0), "coarse_to_fine_fraction"),
    (dict(alpha_ramp_fraction=1.5), "alpha_ramp_fraction is the share of the steps over which α rises"),
    (dict(alpha_ramp_fraction=-0.1), "alpha_ramp_fraction"),
    (dict(alpha_ramp_fraction=0.5, alpha_start=60.0), "alpha_start must be positive and at most alpha (50)"),
    (dict(alpha_ramp_fraction=0.5, alpha_start=0.0), "alpha_start"),
    (dict(average_last_fraction=1.0), "average_last_fraction is the share of the last steps"),
    (dict(average_last_fraction=-0.1), "average_last_fraction"),
    (dict(ensemble_fits=0), "ensemble_fits is how many fits the result is made from: at least 1"),
    (dict(ensemble_combine="median"), "ensemble_combine is how the fits make the result: 'mean' or 'best_reprojection', got 'median'"),
    (dict(grow_threshold=0.6), "grow_threshold must be 0 (off) or an occupancy up to threshold (0.5)"),
    (dict(grow_threshold=-0.1), "grow_threshold"),
    (dict(width_agreement_min_ratio=1.0), "width_agreement_min_ratio must be 0 (off) or an agreement"),
    (dict(width_agreement_min_ratio=-0.2), "width_agreement_min_ratio"),
    (dict(width_exclusion_fraction=1.0), "width_exclusion_fraction is the share of the steps"),
    (dict(width_exclusion_fraction=-0.1), "width_exclusion_fraction"),
    (dict(width_exclusion_repeats=0), "width_exclusion_repeats must be at least 1"),
    (dict(final_reconnect_max_gap_mm=-1.0), "final_reconnect_max_gap_mm must be 0 (off) or a gap in mm"),
    (dict(min_fragment_volume_mm3=-1.0), "min_fragment_volume_mm3 must be 0 (off) or a volume in mm³"),
    (dict(prune_last_min_views_any_motion=-1), "prune_last_min_views_any_motion must be 0 (no exception) or a number"),
    (dict(one_view_reach_mm=-1.0), "one_view_reach_mm is how far (mm) the support follows a single view"),
    (dict(frames_unseen_reach_mm=-0.5), "frames_unseen_reach_mm is how far (mm)"),
    (dict(calibration_min_untruncated_gain=-1.0), "calibration_min_untruncated_gain must be 0 (no check) or more"),
    (dict(calibration_min_untruncated_gain=float("nan")), "calibration_min_untruncated_gain"),
])
def test_bad_settings(kwargs, fragment):
    kwargs = dict(kwargs)
    preset = kwargs.pop("preset", "fast")
    with pytest.raises(ReconstructionError) as info:
        make_settings(preset, **kwargs)
    assert fragment in str(info.value)


def test_setting_overrides_are_typed_from_the_fields():
    assert parse_setting_overrides(["support_margin_mm=2", "memory_check=false", "levels=8",
                                    "table_learning_rate=none", "support=hull"]) == {
        "support_margin_mm": 2.0, "memory_check": False, "levels": 8, "table_learning_rate": None, "support": "hull"}
    assert isinstance(parse_setting_overrides(["support_margin_mm=2"])["support_margin_mm"], float)
    for item, message in [("levels=8.5", "whole number"), ("learning_rate=fast", "takes a number"),
                          ("noequals", "KEY=VALUE"), ("bogus=1", "unknown setting"),
                          ("memory_check=maybe", "true or false"), ("alpha=inf", "finite"),
                          ("steps=none", "needs a value")]:
        with pytest.raises(ReconstructionError, match=message):
            parse_setting_overrides([item])
    with pytest.raises(ReconstructionError, match="use --seed"):
        parse_setting_overrides(["seed=3"], reserved={"seed": "use --seed"})


def test_help_lists_every_key_with_its_default():
    text = setting_help()
    assert all(f"{key}=" in text for key in SETTING_KEYS)
    assert "steps=5000" in text and "alpha=50.0" in text
    # a command leaves out what it sets by its own flags, as its --set refuses them
    text = setting_help(exclude={"steps", "seed"})
    listed = set(re.findall(r"(\w+)=", text))
    assert listed == set(SETTING_KEYS) - {"steps", "seed"} and "alpha=50.0" in text


def test_metric_registry():
    assert METRICS["cldice"].higher_is_better and not METRICS["chamfer_l2_mm"].higher_is_better
    assert METRICS["chamfer_l2_mm"].unit == "mm"
    assert METRICS["dice"].table_header == "Dice (%)" and METRICS["re_mse"].table_header == "reMSE (×1e-4)"


def test_settings_from_values_take_a_preset_and_its_changes_as_the_jobs_do():
    from SDFCARLib.settings import settings_from_values

    assert settings_from_values({}) == make_settings("fast")
    assert settings_from_values({"preset": "paper", "steps": 7}) == make_settings("paper", steps=7)
    values = {"preset": "fast", "steps": 9}
    settings_from_values(values)
    assert values == {"preset": "fast", "steps": 9}  # the caller's dict is left as it was
    with pytest.raises(ReconstructionError, match="unknown preset"):
        settings_from_values({"preset": "quick"})


@pytest.mark.parametrize("given, message", [
    (dict(calibrate="false"), "setting calibrate is a switch: give True or False, got 'false' (str)"),
    (dict(memory_check=0), "setting memory_check is a switch: give True or False, got 0 (int)"),
    (dict(steps="3"), "setting steps takes a whole number, got '3' (str)"),
    (dict(steps=2.5), "setting steps takes a whole number, got 2.5 (float)"),
    (dict(steps=True), "setting steps takes a whole number, got True (bool)"),
    (dict(learning_rate="1e-3"), "setting learning_rate takes a number, e.g. 1e-3, got '1e-3' (str)"),
    (dict(learning_rate=float("nan")), "setting learning_rate must be a finite number, got nan"),
    (dict(device=0), "setting device takes a name (text), got 0 (int)"),
    (dict(alpha=None), None),  # None leaves a setting at the preset's value (make_settings' rule)
])
def test_settings_of_the_wrong_type_are_refused_by_name(given, message):
    """A script's or a JSON file's values are not read as text: "false" would switch a setting on."""
    from SDFCARLib.settings import Settings

    if message is None:
        assert make_settings("fast", **given) == make_settings("fast")
        return
    with pytest.raises(ReconstructionError) as info:
        make_settings("fast", **given)
    assert message in str(info.value)
    with pytest.raises(ReconstructionError, match="needs a value"):
        Settings.from_dict({"steps": None})


def test_numpy_numbers_and_whole_floats_are_taken_as_plain_values():
    import numpy as np

    s = make_settings("fast", steps=np.int64(7), seed=3.0, calibrate=np.bool_(True), learning_rate=np.float32(0.5),
                      support_margin_mm=2, threads=None)
    assert (s.optimisation.steps, s.run.seed, s.calibration.calibrate) == (7, 3, True)
    assert type(s.optimisation.steps) is int and type(s.calibration.calibrate) is bool
    assert type(s.optimisation.learning_rate) is float and type(s.region.support_margin_mm) is float
    assert s.run.threads is None


def test_settings_from_values_refuse_what_is_not_a_dict():
    from SDFCARLib.settings import settings_from_values

    for values in (None, ["preset", "fast"], "fast"):
        with pytest.raises(ReconstructionError, match="the settings are a dict of setting keys and values"):
            settings_from_values(values)
