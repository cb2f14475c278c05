"""Display processing of simulated frames (the benchmark's DISP protocols): each step against its closed form."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erf

from SDFCARLib.display_processing import DisplaySettings, display_processed, processed_log_intensity

PLAIN = DisplaySettings(range_compression=0.0, edge_gain=0.0)


def test_without_compression_or_enhancement_the_grey_level_is_affine_in_log_intensity():
    counts = np.tile(np.geomspace(20.0, 4000.0, 256), (8, 1))
    grey = display_processed(counts, 0.3, DisplaySettings(range_compression=0.0, edge_gain=0.0,
                                                          window_percentiles=(0.0, 100.0))).astype(float)
    expected = 255.0 * (np.log(counts) - np.log(20.0)) / (np.log(4000.0) - np.log(20.0))
    assert np.abs(grey - expected).max() <= 0.5 + 1e-9  # rounding only
    assert grey[0, 0] == 0 and grey[0, -1] == 255


def test_edge_enhancement_overshoots_a_step_by_half_the_gain_times_its_height():
    # A step of height h in ln I: L + k (L − G∗L) is h + k h / 2 just after the edge and −k h / 2 just before,
    # and k h (1 − Φ(x/σ)) … at x from it: erf's closed form, sampled at the pixel centres.
    spacing, sigma, gain, h = 0.1, 0.8, 1.5, 0.7
    counts = np.ones((4, 400)) * 100.0
    counts[:, 200:] *= np.exp(h)
    settings = DisplaySettings(range_compression=0.0, edge_gain=gain, edge_scale_mm=sigma)
    processed = processed_log_intensity(counts, spacing, settings)[2]
    x = (np.arange(400) - 199.5) * spacing  # each pixel centre's distance from the edge (mm)
    blurred = h * 0.5 * (1.0 + erf(x / (sigma * np.sqrt(2.0))))
    step = np.where(x > 0, h, 0.0)
    expected = np.log(100.0) + step + gain * (step - blurred)
    inner = slice(60, 340)  # away from the row's ends (mode "nearest")
    assert np.allclose(processed[inner], expected[inner], atol=2e-3)
    assert processed[200] - np.log(100.0) == pytest.approx(h + gain * h * 0.5 * (1 - erf(0.05 / (sigma * np.sqrt(2)))), abs=2e-3)


def test_range_compression_flattens_large_scale_brightness_and_keeps_vessel_detail():
    spacing, scale, c = 0.5, 15.0, 0.6
    x = np.arange(1024) * spacing
    wavelength_wide, wavelength_fine = 400.0, 2.0
    wide = 0.5 * np.sin(2 * np.pi * x / wavelength_wide)
    fine = 0.05 * np.sin(2 * np.pi * x / wavelength_fine)
    counts = np.tile(1000.0 * np.exp(wide + fine), (16, 1))
    settings = DisplaySettings(range_compression=c, range_scale_mm=scale, edge_gain=0.0)
    processed = processed_log_intensity(counts, spacing, settings)[8] - np.log(1000.0)
    # a Gaussian low-pass passes a sinusoid of wavelength λ with gain exp(−2π²σ²/λ²)
    keep_wide = 1.0 - c * np.exp(-2 * np.pi**2 * scale**2 / wavelength_wide**2)
    inner = slice(200, 824)  # away from the row's ends (mode "nearest")
    # processed = a · wide + b · fine + constant (the median's offset): a the low-pass's share kept, b = 1
    design = np.stack([wide[inner], fine[inner], np.ones(624)], axis=1)
    (a, b, _), *_ = np.linalg.lstsq(design, processed[inner], rcond=None)
    assert a == pytest.approx(keep_wide, abs=0.01) and keep_wide < 0.5
    assert b == pytest.approx(1.0, abs=0.01)


def test_vessels_stay_dark_and_the_frame_is_eight_bit():
    rng = np.random.default_rng(0)
    counts = 1800.0 + 40.0 * rng.standard_normal((128, 128))
    counts[:, 60:66] *= 0.6  # a vessel: less intensity
    grey = display_processed(counts, 0.278)
    assert grey.dtype == np.uint8 and grey.min() == 0 and grey.max() == 255
    assert grey[:, 61:65].mean() < 0.5 * grey[:, :40].mean()


@pytest.mark.parametrize("field, value, message", [
    ("range_compression", 1.0, "range_compression"), ("edge_gain", -0.5, "edge_gain"),
    ("edge_scale_mm", 0.0, "edge_scale_mm"), ("window_percentiles", (50.0, 10.0), "window_percentiles"),
    ("bits", 7, "bits")])
def test_bad_settings_are_named(field, value, message):
    with pytest.raises(ValueError, match=message):
        display_processed(np.ones((8, 8)), 0.3, DisplaySettings(**{field: value}))


def test_a_frame_that_is_not_one_image_is_refused():
    with pytest.raises(ValueError, match="one 2-D image"):
        display_processed(np.ones((2, 8, 8)), 0.3)
    with pytest.raises(ValueError, match="pixel_spacing_mm"):
        display_processed(np.ones((8, 8)), 0.0)
