"""Mask sanity: each warning on a constructed mask, none on clean simulated masks; specks and the support."""

from __future__ import annotations

import numpy as np
import pytest

from SDFCARLib.geometry import Geometry
from SDFCARLib.mask_checks import MAX_SPECKS, mask_warnings, support_masks
from SDFCARLib.optimiser import build_problem
from SDFCARLib.settings import make_settings


def _vessel(shape=(128, 128)) -> np.ndarray:
    """A clean, connected 'tree': two crossing bands well inside the image."""
    m = np.zeros(shape, dtype=bool)
    m[60:66, 20:110] = True
    m[20:110, 40:45] = True
    return m


def _speckle(mask: np.ndarray, count: int, seed: int = 0, largest: int = 2) -> np.ndarray:
    """``count`` isolated specks of 1 to ``largest``² pixels away from the vessel."""
    rng = np.random.default_rng(seed)
    out, placed = mask.copy(), 0
    while placed < count:
        r, c = rng.integers(3, mask.shape[0] - 5), rng.integers(3, mask.shape[1] - 5)
        if mask[r - 2:r + 4, c - 2:c + 4].any() or out[r - 1:r + 3, c - 1:c + 3].any():
            continue
        h, w = rng.integers(1, largest + 1, 2)
        out[r:r + h, c:c + w] = True
        placed += 1
    return out


def test_clean_simulated_masks_give_no_warning(tiny_case):
    for mask, view in zip(tiny_case.masks, tiny_case.geometry.views):
        assert mask_warnings(mask, view.pixel_spacing_mm) == []
    assert mask_warnings(_vessel()) == []


def test_border_warning():
    m = _vessel()
    m[:, :3] = True  # a collimator edge segmented along the left side
    (message,) = mask_warnings(m, source="view 2")
    assert message.startswith("view 2:") and "border" in message and "collimator" in message
    one_vessel_leaving = _vessel()
    one_vessel_leaving[60:66, 0:20] = True  # a vessel crossing the border is normal
    assert mask_warnings(one_vessel_leaving) == []
    # a blade's edge inside the image, slightly tilted, is not in the border ring but is named
    blade = _vessel()
    for c in range(4, 124):
        blade[10 + c // 40: 12 + c // 40, c] = True
    (message,) = mask_warnings(blade)
    assert "straight line across the image near row" in message and "collimator" in message
    assert "down the image" in mask_warnings(blade.T)[0]
    # … also between side blades, which keep it from the image's sides
    between = _vessel()
    between[12:14, 11:117] = True
    assert "straight line across the image near row 13" in mask_warnings(between)[0]
    # a catheter enters at one side and ends inside: not a blade's edge
    catheter = _vessel()
    catheter[20:128, 100:104] = True
    assert mask_warnings(catheter) == []


def test_speck_warning_counts_the_specks():
    m = _speckle(_vessel(), 60)
    (message,) = mask_warnings(m, pixel_spacing_mm=(0.4, 0.4))
    assert "60 specks" in message and "2 mm²" in message
    # the advice names a setting that exists (it once named one that did not)
    from SDFCARLib.masks import AngioMaskSettings

    assert "min_length_mm" in message and hasattr(AngioMaskSettings(), "min_length_mm")
    assert mask_warnings(_speckle(_vessel(), MAX_SPECKS - 5)) == []


@pytest.mark.parametrize("vessel_rows, word", [(80, "implausibly much"), (0, "only")])
def test_coverage_warnings(vessel_rows, word):
    m = np.zeros((200, 200), dtype=bool)
    m[60:60 + vessel_rows, 20:180] = True  # 32 % of the image
    m[100, 100:105] = True  # 5 pixels: 0.0125 %
    messages = mask_warnings(m)
    assert len(messages) == 1 and word in messages[0] and "% of the image" in messages[0], messages


def test_support_masks_leave_out_specks_only_of_noisy_masks(tiny_case):
    views, grid = tiny_case.geometry.views, tiny_case.geometry.volume
    clean = [m.copy() for m in tiny_case.masks]
    kept, messages = support_masks(clean, views, grid)
    assert messages == [] and all(np.array_equal(a, b) for a, b in zip(kept, clean))
    noisy = [_speckle(clean[0], 60), clean[1]]
    kept, messages = support_masks(noisy, views, grid)
    assert len(messages) == 1 and messages[0].startswith("view 1:") and "left out of the support" in messages[0]
    assert np.array_equal(kept[0], clean[0]) and np.array_equal(kept[1], clean[1])


def test_build_problem_warns_and_bounds_the_support(tiny_case):
    geometry: Geometry = tiny_case.geometry
    settings = make_settings("fast", steps=1)
    clean = [m.astype(np.float32) for m in tiny_case.masks]
    noisy = [_speckle(m, 80, seed=n, largest=1).astype(np.float32) for n, m in enumerate(tiny_case.masks)]
    events = []
    problem = build_problem(geometry, noisy, settings, "mask", progress=events.append)
    reference = build_problem(geometry, clean, settings, "mask")
    assert reference.warnings == []
    warned = [e["message"] for e in events if e["phase"] == "warning"]
    assert warned == problem.warnings and len(warned) == 4  # a speck warning and a support note per view
    assert problem.voxels.size == reference.voxels.size  # the specks did not grow the support
    assert np.array_equal(problem.targets[0], noisy[0])  # the loss keeps the user's mask
