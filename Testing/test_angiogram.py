"""Simulated angiograms: Beer–Lambert of the vessels on a smooth background, noise at the asked SNR."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from SDFCARLib.angiogram import AngiogramSettings, simulate_angiogram


def _tube(shape=(128, 160), row=64, radius_px=4.0):
    """Line integral (mm) of a horizontal cylinder of ``radius_px`` pixels at 0.3 mm/pixel."""
    r = np.abs(np.arange(shape[0]) - row)[:, None] * 0.3
    chord = 2.0 * np.sqrt(np.maximum((radius_px * 0.3) ** 2 - r**2, 0.0))
    return np.broadcast_to(chord, shape).copy()


def test_shape_dtype_and_determinism():
    line = _tube()
    frame, info = simulate_angiogram(line, 0.3, seed=3)
    assert frame.shape == line.shape and frame.dtype == np.uint16 and frame.max() <= 4095
    again, _ = simulate_angiogram(line, (0.3, 0.3), seed=3)
    other, _ = simulate_angiogram(line, 0.3, seed=4)
    assert np.array_equal(frame, again) and not np.array_equal(frame, other)
    eight, _ = simulate_angiogram(line, 0.3, seed=3, settings=AngiogramSettings(bits_stored=8))
    assert eight.dtype == np.uint8
    assert info["settings"]["snr"] == AngiogramSettings().snr
    with pytest.raises(dataclasses.FrozenInstanceError):
        AngiogramSettings().snr = 3.0  # type: ignore[misc]


def test_vessels_are_darker_than_their_surroundings():
    line = _tube()
    frame, info = simulate_angiogram(line, 0.3, seed=0)
    core = frame[62:67, 20:140].astype(float)
    beside = np.concatenate([frame[40:50, 20:140], frame[78:88, 20:140]]).astype(float)
    assert core.mean() < 0.85 * beside.mean()
    # Beer–Lambert: the noiseless contrast is exp(−μ·L) at the centre, up to the blur.
    ratio = info["noiseless"][64, 20:140] / info["noiseless"][45, 20:140]
    expected = np.exp(-AngiogramSettings().mu_per_mm * line[64, 0])
    assert np.median(ratio) == pytest.approx(expected, rel=0.1)


@pytest.mark.parametrize("snr", [10.0, 40.0])
def test_noise_matches_the_requested_snr(snr):
    flat = np.zeros((128, 128))
    settings = AngiogramSettings(snr=snr, ribs=0, diaphragm=False, background_amplitude=0.0)
    frame, info = simulate_angiogram(flat, 0.3, seed=1, settings=settings)
    noise = frame.astype(float) - info["noiseless"]
    measured = float(np.mean(info["noiseless"]) / np.std(noise))
    assert measured == pytest.approx(snr, rel=0.1)
    assert info["noise_sigma_at_reference"] == pytest.approx(info["reference_level"] / snr)


def test_background_is_smooth_and_the_collimator_is_dark():
    frame, info = simulate_angiogram(np.zeros((128, 128)), 0.3, seed=2,
                                     settings=AngiogramSettings(collimator_fraction=0.1))
    background = info["background"] - info["background"].mean()
    background = background * np.outer(np.hanning(128), np.hanning(128))  # no leakage from the image edges
    power = np.abs(np.fft.fft2(background)) ** 2
    freq = np.hypot(*np.meshgrid(np.fft.fftfreq(128), np.fft.fftfreq(128), indexing="ij"))
    # Structures of vessel size (periods under ~8 px = 2.4 mm) carry almost none of the power.
    assert power[freq > 0.125].sum() < 1e-4 * power.sum()
    assert np.ptp(info["background"]) > 0.05  # but it is not flat
    covered = info["collimator"]
    assert covered[0, 0] and covered[:, 0].all() and not covered[64, 64]
    assert 0.15 < covered.mean() < 0.5
    assert frame[covered].mean() < 0.2 * frame[~covered].mean()


def test_bad_arguments():
    with pytest.raises(ValueError, match="2-D image"):
        simulate_angiogram(np.zeros((2, 8, 8)), 0.3)
    with pytest.raises(ValueError, match="non-negative"):
        simulate_angiogram(-np.ones((8, 8)), 0.3)
    with pytest.raises(ValueError, match="pixel_spacing_mm must be positive"):
        simulate_angiogram(np.zeros((8, 8)), 0.0)
    with pytest.raises(ValueError, match="snr must be positive"):
        simulate_angiogram(np.zeros((8, 8)), 0.3, settings=AngiogramSettings(snr=0.0))


@pytest.mark.parametrize("shape, spacing_mm", [((64, 64), 0.278), ((96, 96), 0.278), ((64, 64), 0.3)])
def test_a_small_field_of_view_gives_an_angiogram_not_an_overflow(shape, spacing_mm):
    """A detector a few background scales (25 mm) wide or less: the smoothed field is nearly flat; its mean, scaled
    with its small spread, overflowed exp(−B) (all-zero frames, or a ZeroDivisionError)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow in exp
        for line_integral in (np.zeros(shape), np.ones(shape)):
            frame, info = simulate_angiogram(line_integral, spacing_mm, 0)
            assert 0.2 * 4095 < float(np.median(frame)) < 0.8 * 4095  # about the background level, not 0
