"""Lumen area from the frames' absorbance (analysis/frame_density.py): closed forms and a simulated tube."""

from __future__ import annotations

import numpy as np
import pytest

from SDFCARLib.analysis.diameter import projected_widths
from SDFCARLib.analysis.frame_density import attenuation_per_mm, densities, density_diameter, integrated_absorbance
from SDFCARLib.analysis.frame_widths import frame_widths
from SDFCARLib.angiogram import AngiogramSettings
from SDFCARLib.geometry import standard_geometry
from SDFCARLib.lumen_profile import blurred_chord

VIEWS = standard_geometry("lao30-rao30").views


def test_integrated_absorbance_is_attenuation_times_area_on_a_sloped_background():
    x = np.arange(-5.0, 5.0, 0.05)
    mu, radius = 0.25, 1.1
    profile = 1.3 + 0.02 * x + mu * blurred_chord(x, 0.2, radius, 0.3)
    assert integrated_absorbance(x, profile, radius + 0.2 + 3 * 0.3) == pytest.approx(mu * np.pi * radius ** 2, rel=5e-3)


def test_the_area_of_a_slit_lumen_is_the_same_from_its_narrow_and_its_wide_side():
    # An elliptical throat (semi-axes 1.5 and 0.5 mm): seen across its long axis it is 3 mm wide, across the
    # short one 1 mm; the chord is 2·b·√(1 − x²/a²) either way and its integral π·a·b.
    x = np.arange(-6.0, 6.0, 0.01)
    mu = 0.3

    def chord(a, b):
        return 2.0 * b * np.sqrt(np.clip(1.0 - (x / a) ** 2, 0.0, None))

    wide, narrow = mu * chord(1.5, 0.5), mu * chord(0.5, 1.5)
    for profile in (wide, narrow):
        assert integrated_absorbance(x, profile, 2.0) == pytest.approx(mu * np.pi * 1.5 * 0.5, rel=2e-3)
    # Both views' areas give the equivalent diameter of the ellipse, 2·√(a·b), not the widths' 3 and 1 mm.
    d = density_diameter(np.array([[integrated_absorbance(x, wide, 2.0)], [integrated_absorbance(x, narrow, 2.0)]]),
                         [mu, mu])
    assert d[0] == pytest.approx(2.0 * np.sqrt(1.5 * 0.5), rel=2e-3)


def test_integrated_absorbance_needs_background_on_both_sides():
    x = np.arange(-2.0, 2.0, 0.1)
    assert integrated_absorbance(x, np.ones_like(x), 1.9) is None


def test_density_diameter_of_a_simulated_tube_after_calibrating_each_view(tube_frames):
    realistic, points, tangents = tube_frames
    psf = AngiogramSettings().psf_sigma_mm
    per_view, attenuations = [], []
    for frame, mask, view in zip(realistic.frames, realistic.masks, VIEWS):
        guesses = projected_widths(points, tangents, mask, view)
        widths = frame_widths(points, tangents, frame, view, guesses, psf_sigma_mm=psf)
        d = densities(points, tangents, frame, view, guesses, psf_sigma_mm=psf)
        assert np.isfinite(d).all() and (d > 0).all()
        attenuations.append(attenuation_per_mm(d, widths, np.ones(len(points), bool)))
        per_view.append(d)
    # The same iodine seen by two views of the same system: the same attenuation per mm of lumen.
    assert attenuations[0] == pytest.approx(attenuations[1], rel=0.1)
    diameter = density_diameter(np.stack(per_view), attenuations)
    assert np.mean(np.abs(diameter - 2.0)) < 0.1  # the bar for healthy diameters is 0.15 mm


def test_calibration_and_diameter_without_enough_points():
    d = np.array([1.0, 2.0, np.nan, 3.0])
    assert attenuation_per_mm(d, np.ones(4), np.ones(4, bool)) is None  # 3 usable points
    out = density_diameter(np.array([[1.0, np.nan], [np.nan, np.nan]]), [0.5, None])
    assert out[0] == pytest.approx(np.sqrt(4 * 2.0 / np.pi)) and np.isnan(out[1])
