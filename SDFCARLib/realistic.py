"""Realistic input for benchmarks: masks segmented from simulated angiograms of a moving heart.

Masks projected from a known tree are clean and consistent; a user's masks are not. This module
makes the input a user has from a ground-truth label, and keeps the truth for scoring only:

1. Motion. Each view after the first sees the object moved rigidly (random direction, random
   size up to ``max_shift_mm`` and ``max_rotation_deg``, from the case's seed) — table, patient
   and heart move between two non-simultaneous acquisitions. The views handed to the
   reconstruction keep their nominal poses, as DICOM tags would give them; the truth stays in the
   first view's frame.
2. Angiograms. The line integrals of the (moved) label become detector frames
   (``angiogram.simulate_angiogram``: Beer–Lambert with an anatomical background, quantum noise
   at ``snr``, detector blur).
3. Masks. Each frame is segmented by SDFCAR's own pipeline (``masks.segment_angiogram``) with the
   frame's pixel spacing and magnification — never from the truth — so thin, faint vessels drop
   out unevenly between the views and borders land a pixel off, as in real masks.
4. Display processing (optional, ``display``): the frames are stored as a system stores them for
   viewing (``display_processing.py``: logarithm, range compression, edge enhancement, 8-bit
   window; Pixel Intensity Relationship ``DISP``) and the masks are segmented on those as the
   product segments a DISP frame (``masks.mask_settings_for_intensity``), as a user's exported runs
   mostly are. ``RealisticInput.frame_intensity`` then says ``DISP`` per view.
5. Collimation (optional, ``collimator_fraction``): every frame behind shutters over that share of each
   side, as runs are mostly collimated; a vessel the shutter covers in one view is missing from that
   view's mask only.

``RealisticInput.info`` records the motion, the mask pipeline's parameters and the masks' Dice and
clDice against the true silhouettes (line integral > ``settings.MASK_THRESHOLD_MM``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

import numpy as np

from .angiogram import AngiogramSettings, simulate_angiogram
from .display_processing import DISPLAY_INTENSITY, display_processed
from .geometry import CArmView, Geometry
from .masks import AngioMaskSettings, MaskError, mask_settings_for_intensity, segment_angiogram
from .metrics import cldice, mask_dice
from .phantoms import simulate_views
from .settings import MASK_THRESHOLD_MM


@dataclass(frozen=True)
class RealisticOptions:
    max_shift_mm: float = 3.0  # object motion between the acquisitions, per view after the first
    max_rotation_deg: float = 2.0
    snr: float = 25.0  # background signal-to-noise ratio of the simulated frames
    # the mask pipeline's edge rule (masks.AngioMaskSettings.edge_*): its own defaults
    mask_edge_fraction: float = AngioMaskSettings.edge_fraction
    mask_edge_taper_radius_mm: Optional[float] = AngioMaskSettings.edge_taper_radius_mm
    mask_edge_grow_mm: float = AngioMaskSettings.edge_grow_mm
    mask_edge_max_radius_mm: Optional[float] = AngioMaskSettings.edge_max_radius_mm
    mask_min_contrast: float = AngioMaskSettings.min_contrast
    display: bool = False  # frames processed for display (DISP) before they are segmented and handed over
    # the share of each side of every frame under the collimator's shutter (angiogram.AngiogramSettings); 0: none
    collimator_fraction: float = 0.0

    def check(self) -> None:
        for name in ("max_shift_mm", "max_rotation_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number, 0 or more, got {value!r}")
        if not (math.isfinite(self.snr) and self.snr > 0):
            raise ValueError(f"snr must be a positive finite number (the frames' background signal-to-noise), got {self.snr!r}")
        if not (math.isfinite(self.collimator_fraction) and 0.0 <= self.collimator_fraction < 0.4):
            raise ValueError(f"collimator_fraction is the share of each side of a frame under the shutter: 0 (none) up to "
                             f"under 0.4, got {self.collimator_fraction!r}")


@dataclass
class RealisticInput:
    geometry: Geometry  # the nominal geometry the reconstruction is given
    true_views: List[CArmView]  # the views with the motion that produced the images
    frames: List[np.ndarray]  # simulated angiograms (uint16 counts)
    masks: List[np.ndarray]  # segmented from the frames: the reconstruction's input
    true_masks: List[np.ndarray]  # silhouettes of the moved truth (for scoring)
    info: Dict[str, Any] = field(default_factory=dict)
    # per view, the frames' Pixel Intensity Relationship as a DICOM run would carry it; None: linear counts
    # handed over as arrays (path lengths are read off them)
    frame_intensity: Optional[List[str]] = None


def random_motion(rng: np.random.Generator, max_shift_mm: float, max_rotation_deg: float):
    """A rotation vector (degrees) and translation (mm) in random directions with random sizes up to the maxima."""
    def vector(size: float) -> np.ndarray:
        direction = rng.normal(size=3)
        return direction / np.linalg.norm(direction) * size * rng.uniform(0.5, 1.0)
    return vector(max_rotation_deg), vector(max_shift_mm)


def realistic_input(label: np.ndarray, geometry: Geometry, seed: int,
                    options: RealisticOptions = RealisticOptions()) -> RealisticInput:
    """Frames and image-segmented masks of ``label`` (on ``geometry.volume``) with motion between views."""
    options.check()
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a whole number, 0 or more, got {seed!r}")
    rng = np.random.default_rng([int(seed), 12])  # its own stream: the tree's seed is used elsewhere
    true_views = [geometry.views[0]]
    motions = [{"rotation_deg": [0.0] * 3, "translation_mm": [0.0] * 3}]
    for view in geometry.views[1:]:
        rotation, translation = random_motion(rng, options.max_shift_mm, options.max_rotation_deg)
        true_views.append(view.with_object_motion(rotation, translation))
        motions.append({"rotation_deg": [round(float(v), 4) for v in rotation],
                        "translation_mm": [round(float(v), 4) for v in translation]})
    line_integrals, true_masks = simulate_views(label, geometry.volume, true_views, MASK_THRESHOLD_MM)
    frames, masks, per_view = [], [], []
    for n, (li, view, truth) in enumerate(zip(line_integrals, true_views, true_masks), start=1):
        frame, _ = simulate_angiogram(li, view.pixel_spacing_mm, rng,
                                      AngiogramSettings(snr=options.snr, collimator_fraction=options.collimator_fraction))
        if options.display:  # no draw from rng: the scene and its noise are the linear protocol's
            frame = display_processed(frame, view.pixel_spacing_mm)
        try:
            # as the product segments a frame of that relationship (on display frames the edge rule does not trim)
            settings = mask_settings_for_intensity(DISPLAY_INTENSITY if options.display else None,
                                                   AngioMaskSettings(edge_fraction=options.mask_edge_fraction,
                                                                     edge_taper_radius_mm=options.mask_edge_taper_radius_mm,
                                                                     edge_grow_mm=options.mask_edge_grow_mm,
                                                                     edge_max_radius_mm=options.mask_edge_max_radius_mm,
                                                                     min_contrast=options.mask_min_contrast))
            segmented = segment_angiogram(frame, view.pixel_spacing_mm, view.magnification, settings)
        except MaskError as exc:
            raise MaskError(f"view {n}: the simulated angiogram could not be segmented: {exc}") from None
        frames.append(frame)
        masks.append(segmented.mask)
        per_view.append({
            "mask_dice": mask_dice(segmented.mask, truth),
            "mask_cldice": cldice(segmented.mask, truth),
            "mask_components": int(segmented.parameters.get("components", -1)),
        })
    info = {"motion": motions, "views": per_view, "snr": options.snr,
            "max_shift_mm": options.max_shift_mm, "max_rotation_deg": options.max_rotation_deg,
            "display": options.display, "collimator_fraction": options.collimator_fraction}
    intensity = [DISPLAY_INTENSITY] * len(frames) if options.display else None
    return RealisticInput(geometry, true_views, frames, masks, true_masks, info, intensity)
