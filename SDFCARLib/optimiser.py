"""Per-patient self-supervised optimisation: build the problem, run the loop, finish the result.

``reconstruct(geometry, targets, settings)`` does three steps, each its own function (the first two,
with the frames' evidence and the calibrations asked for, are ``fit_field``):

1. ``build_problem`` checks the targets (one per view), chooses the support (every voxel, or the
   masks' visual hull widened by a margin), estimates the memory and picks the device, and builds
   the projectors and the view targets;
2. ``optimise`` runs Adam on the field (``field.ImplicitField``) against λ2·L_occ, plus λ1·L_geo
   in the modes that use it (``settings.MODES``), reporting progress and honouring cancel; when
   asked (``width_exclusion_fraction``), part way through it takes the pieces whose views see
   different widths out of the field, and the rest of the fit explains their pixels elsewhere;
3. ``finish`` evaluates the field on the grid, thresholds it, prunes the pieces no mask pixel
   needs when asked (``pruning.py``), removes the detached fragments that not every view confirms
   (``pruning.unconfirmed_fragments``) and joins the rest to the tree through the field
   (``connectivity.py``) when asked, grows into connected partial occupancy when asked, removes
   the pieces whose views see different widths where the tree stays whole when asked
   (``width_agreement.py``), removes the detached specks below a volume when asked
   (``min_fragment_volume_mm3``), fills in what every view shows and the result does not explain when asked
   (``unexplained_fill.py``), prunes once more when asked (``prune_last``), joins what is still apart once
   more when asked (``final_reconnect_max_gap_mm``), and writes the report.

Learning rates
    Adam moves every weight by about lr per step. The SDF's occupancy logit is −α·s, so a step of
    the SDF network's output layer moves the logit α = 50 times further than the same step of the
    occupancy network's: at lr 1e-2 the SDF modes saturate σ(−α·s) within a few steps and their
    gradient dies, while the occupancy network needs about 1e-2 to converge in a few hundred steps.
    The ``fast`` preset therefore trains the hash table (where the spatial detail lives, as in
    Instant-NGP) at 1e-2 and the MLP at 1e-3, the same for every mode, so the ablations stay
    like-for-like as in the paper (which uses one learning rate for all).

The loop calls ``progress(dict)`` with phase, step, total, losses, elapsed and ETA, and stops with
``ReconstructionCancelled`` as soon as ``cancel()`` returns true (checked every step).
"""

from __future__ import annotations

import dataclasses
import math
import platform
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import scipy
from scipy import ndimage
import skimage
import torch

from . import __version__
from .device import available_memory_bytes, check_host_memory, choose_device, device_description, estimate_memory_bytes
from .field import FieldConfig, ImplicitField
from .geometry import Geometry
from .hull import support_mask
from .losses import (DistanceSettings, GeometricLoss, ViewTarget, excess_path_loss, frame_target, make_target,
                     occupancy_loss, partial_occupancy_loss)
from .consistency import agreement_warnings, view_agreement, view_separation_warnings
from .evidence import (EvidenceError, EvidenceSettings, assumed_frame_intensity, is_binary_image, unreadable_intensity,
                       view_evidence)
from .mask_checks import mask_warnings, support_masks
from .masks import MaskError, binarise_mask, unseen_pixels
from .connectivity import ReconnectSettings, field_values, reconnect_fragments
from .metrics import component_counts, component_labels
from .projector import ConeBeamProjector, project_volume
from .qa import qa_warnings, reprojection_qa
from .pruning import PruneSettings, prune_redundant_branches, removal_zone, small_fragments, unconfirmed_fragments
from .revival import revival_offsets, unexplained_in_every_view
from .thin_weights import thin_vessel_weights
from .unexplained_fill import unexplained_fill
from .width_agreement import disagreeing_pieces
from .settings import (MASK_THRESHOLD_MM, TARGET_KINDS, ReconstructionError, RegionSettings, Settings, make_settings,
                       settings_from_values)

Progress = Optional[Callable[[Dict[str, Any]], None]]
Cancel = Optional[Callable[[], bool]]


class ReconstructionCancelled(RuntimeError):
    """The user cancelled the reconstruction."""


def field_config(settings: Settings) -> FieldConfig:
    f = settings.field
    return FieldConfig(
        levels=f.levels, features_per_level=f.features_per_level, log2_table_size=f.log2_table_size,
        base_resolution=f.base_resolution, max_resolution=f.max_resolution, width=f.width, depth=f.depth,
        kind=settings.mode.field_kind, alpha=f.alpha, initial_occupancy=f.initial_occupancy,
        initial_alpha=f.alpha_start if settings.mode.field_kind == "sdf" and settings.optimisation.alpha_ramp_fraction > 0 else None,
    )


def validate_targets(targets: Sequence[np.ndarray], geometry: Geometry, kind: str) -> List[np.ndarray]:
    """Check the per-view targets and return them as float32 arrays (masks as 0/1)."""
    if kind not in TARGET_KINDS:
        raise ReconstructionError(f"target kind must be one of {TARGET_KINDS}, got {kind!r}")
    if len(geometry.views) < 2:
        raise ReconstructionError(f"the geometry has {len(geometry.views)} view; a 3D reconstruction needs at least two views "
                                  "of the tree from different angles: add the other view to the geometry's views and give "
                                  "its mask")
    if len(targets) != len(geometry.views):
        raise ReconstructionError(f"{len(targets)} target image(s) for {len(geometry.views)} view(s) in the geometry; give one per view")
    out = []
    for n, (target, view) in enumerate(zip(targets, geometry.views), start=1):
        a = np.asarray(target)
        if kind == "mask":
            try:
                out.append(binarise_mask(a, view.detector_shape, source=f"view {n}").astype(np.float32))
            except MaskError as exc:
                raise ReconstructionError(str(exc)) from None
            continue
        if a.shape != tuple(view.detector_shape):
            raise ReconstructionError(
                f"view {n}: image shape {a.shape} differs from the detector shape {tuple(view.detector_shape)} "
                "in the geometry; use the image of that view or fix detector_shape")
        if not np.issubdtype(a.dtype, np.number) and a.dtype != bool:
            raise ReconstructionError(f"view {n}: image data type {a.dtype} is not numeric")
        a = a.astype(np.float32)
        if not np.all(np.isfinite(a)):
            raise ReconstructionError(f"view {n}: the image contains NaN or infinite values; fix the input image")
        if a.min() < 0:
            raise ReconstructionError(f"view {n}: line integrals must be non-negative (min {a.min():.3g})")
        if not a.any():
            raise ReconstructionError(f"view {n}: the line-integral image is all zero; there is no vessel to reconstruct")
        out.append(a)
    return out


def vessel_pixels(targets: Sequence[np.ndarray], kind: str) -> List[np.ndarray]:
    """Each view's vessel pixels. Line integrals have faint interpolation tails: a vessel pixel is
    one above the mask threshold there."""
    floor = 0.0 if kind == "mask" else MASK_THRESHOLD_MM
    return [np.asarray(t) > floor for t in targets]


@dataclass
class Reconstruction:
    """Result of ``reconstruct``: volumes on ``geometry.volume`` (arrays ``[i, j, k]``) and a report."""

    geometry: Geometry
    settings: Settings
    occupancy: np.ndarray  # float32 in [0, 1]
    field: np.ndarray  # float32: s (sdf modes, mm-free units) or logit (occupancy modes)
    segmentation: np.ndarray  # bool, occupancy >= threshold (grown into occupancy >= grow_threshold when set)
    support: Optional[np.ndarray]  # bool voxels the field was evaluated on (None: all)
    report: Dict[str, Any] = field(default_factory=dict)
    history: List[Dict[str, float]] = field(default_factory=list)
    # Per view (projected segmentation, vessel mask), bool: outputs.py draws qa_view<n>.png from them.
    qa_masks: List[Tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    # Per view, bool: its centreline pixels that only it can show (``consistency.view_agreement``), marked on
    # qa_view<n>.png; empty where the check did not run
    one_view_pixels: List[np.ndarray] = field(default_factory=list)


@dataclass
class Problem:
    """Everything the loop needs, built once: targets, support, device, projectors, losses."""

    geometry: Geometry
    settings: Settings
    target_kind: str
    targets: List[np.ndarray]  # float32 per view (masks as 0/1)
    support: Optional[np.ndarray]  # bool volume, None: every voxel
    voxels: np.ndarray  # flat indices of the voxels the field is evaluated on
    device: torch.device
    device_reason: str
    memory_estimate_bytes: int
    projectors: List[ConeBeamProjector]
    view_targets: List[ViewTarget]
    geometric: Optional[GeometricLoss]
    setup_s: float = 0.0
    warnings: List[str] = field(default_factory=list)  # for report.json (mask checks, support, consistency)
    consistency: List[float] = field(default_factory=list)  # per view: centreline with a partner (consistency.py)
    evidence: Optional[Dict[str, Any]] = None  # the frames' line-integral evidence, when used (evidence.py)
    # bool volume: voxels taken out of the field during the fit (width_exclusion_fraction), None: none
    excluded: Optional[np.ndarray] = None
    exclusion: Optional[Dict[str, Any]] = None  # what was taken out, for report.json
    # per support voxel, the offset added to its logit since the revival (revive_fraction; revival.py), None: none
    logit_offset: Optional[torch.Tensor] = None
    revival: Optional[Dict[str, Any]] = None  # what was revived, for report.json
    # where L_occ fits the frames' path lengths: the masks' own targets, which it fits after
    # frame_evidence_until_fraction of the steps (None: L_occ fits view_targets throughout)
    mask_targets: Optional[List[ViewTarget]] = None
    # per view, bool (H, W): the pixels whose 0 is no evidence (``unknown_pixels``), None: every pixel known
    unknown: Optional[List[np.ndarray]] = None
    # per view: share of its centreline that runs where another view cannot see (consistency.view_agreement)
    one_view_shares: List[float] = field(default_factory=list)
    one_view_pixels: List[np.ndarray] = field(default_factory=list)  # per view, bool (H, W): those centreline pixels
    # whether the pose checks before the fit found a motion between the views (``Calibration.motion_found``):
    # True found and corrected, False every view searched and none beyond noise, None not known (none ran)
    motion_found: Optional[bool] = None


def _normalised_points(geometry: Geometry, flat: np.ndarray, device: torch.device) -> torch.Tensor:
    shape = np.asarray(geometry.volume.shape)
    ijk = np.stack(np.unravel_index(flat, tuple(shape)), axis=-1)
    return torch.as_tensor((ijk + 0.5) / shape, dtype=torch.float32, device=device)


def _is_cancelled(cancel: Cancel) -> bool:
    return bool(cancel is not None and cancel())


def _report(progress: Progress, **info: Any) -> None:
    if progress is not None:
        progress(info)


def versions() -> Dict[str, str]:
    return {
        "sdfcar": __version__, "python": platform.python_version(), "torch": torch.__version__,
        "numpy": np.__version__, "scipy": scipy.__version__, "scikit-image": skimage.__version__,
    }


#: report.json's ``frame_evidence`` when the setting is off
FRAME_EVIDENCE_OFF = {"used": False, "why": "frame_evidence is off"}


@dataclass
class FrameEvidence:
    """The frames' vessel line integrals (evidence.py), read once for the calibration and the loss."""

    images: Optional[List[np.ndarray]]  # per view, mm; None: not read (``record["why"]`` says why)
    record: Dict[str, Any]  # report.json's ``frame_evidence``
    warnings: List[str]
    # False: frames processed for display — the images serve the motion search, L_occ fits the masks
    fits_path_lengths: bool = True


def read_frame_evidence(frames: Optional[Sequence[np.ndarray]], targets: Sequence[np.ndarray], geometry: Geometry,
                        settings: Settings, target_kind: str,
                        frame_intensity: Optional[Sequence[Optional[str]]] = None) -> FrameEvidence:
    """The frames' line integrals where a setting uses them (``frame_evidence``, ``calibrate_from_frames``).
    ``frame_intensity``: per view, the frame's DICOM Pixel Intensity Relationship (None: not known); where one
    is not LIN, L_occ does not fit the path lengths (``evidence.unreadable_intensity``), the motion search still
    reads the line integrals' positions off them."""
    if frame_intensity is not None and len(frame_intensity) != len(geometry.views):
        raise ReconstructionError(f"{len(frame_intensity)} pixel intensity relationship(s) for {len(geometry.views)} views: "
                                  "give one per view (None where not known), in the geometry's order")
    if not (settings.loss.frame_evidence or settings.calibration.calibrate_from_frames):
        return FrameEvidence(None, dict(FRAME_EVIDENCE_OFF), [])
    masks = vessel_pixels(validate_targets(targets, geometry, target_kind), target_kind)
    reading = EvidenceSettings(reach_px=settings.loss.frame_evidence_reach_px,
                               deblur_iterations=settings.loss.frame_deblur_iterations)
    images, record, warnings = _frame_evidence(frames, masks, geometry, target_kind, reading)
    if images is not None and settings.loss.frame_evidence_equal_totals and len(images) > 1:
        from .line_integral_consistency import equal_total_factors, rays_of

        # every view read here has path length: view_evidence refuses a frame without lumen profiles
        factors = equal_total_factors([rays_of(i, v) for i, v in zip(images, geometry.views)],
                                      geometry.volume.center_mm)
        images = [(i * f).astype(i.dtype) for i, f in zip(images, factors)]
        for view, f in zip(record["views"], factors):
            view["equal_total_factor"] = round(f, 4)
    unreadable = [(n, why) for n, why in enumerate(map(unreadable_intensity, frame_intensity or ()), start=1) if why]
    if images is not None and unreadable and settings.loss.frame_evidence:
        message = ("; ".join(f"view {n}: the frame's path lengths are not fitted: {why}" for n, why in unreadable)
                   + ". The masks alone are fitted (the frames still place the views, calibrate_from_frames); for the "
                   "frames' evidence export the runs unprocessed (Pixel Intensity Relationship LIN)")
        record = {"used": False, "why": message, "pixel_intensity_relationship": list(frame_intensity or ()),
                  "views": record.get("views")}
        return FrameEvidence(images, record, warnings + [message], fits_path_lengths=False)
    return FrameEvidence(images, record, warnings)


def _frame_evidence(frames: Optional[Sequence[np.ndarray]], masks: Sequence[np.ndarray], geometry: Geometry,
                    target_kind: str, reading: EvidenceSettings) -> Tuple[Optional[List[np.ndarray]], Dict[str, Any], List[str]]:
    """(per-view line integrals read off the frames or None, the report's record, warnings)."""
    if frames is None:
        return None, {"used": False, "why": "no frames were given"}, []
    if target_kind != "mask":
        return None, {"used": False, "why": "the targets are line integrals already"}, []
    if len(frames) != len(geometry.views):
        raise ReconstructionError(f"{len(frames)} frame(s) for {len(geometry.views)} views: give one frame per view, "
                                  "in the geometry's order, or none")
    if any(frame is not None and is_binary_image(frame) for frame in frames):
        # e.g. the sample case, whose "frames" are its masks: nothing to read, nothing to warn about
        return None, {"used": False, "why": "the frames are binary images (masks), not recorded X-ray frames"}, []
    images, views = [], []
    for n, (frame, mask, view) in enumerate(zip(frames, masks, geometry.views), start=1):
        if frame is None or np.shape(frame) != tuple(view.detector_shape):
            shape = None if frame is None else np.shape(frame)
            raise ReconstructionError(f"view {n}: the frame has shape {shape} but the view's detector is "
                                      f"{tuple(view.detector_shape)}: give the frame the mask was made from")
        try:
            found = view_evidence(frame, mask, view, reading)
        except EvidenceError as exc:
            message = (f"view {n}: the frames are not used as evidence, the masks alone are fitted: {exc}")
            return None, {"used": False, "why": message}, [message]
        images.append(found.line_integral_mm)
        views.append({"attenuation_per_mm": round(found.attenuation_per_mm, 5), "profiles": found.info["profiles"],
                      "attenuation_spread_per_mm": round(found.info["spread_per_mm"], 5)})
    return images, {"used": True, "views": views, "reach_px": reading.reach_px,
                    "deblur_iterations": reading.deblur_iterations}, []


def build_problem(geometry: Geometry, targets: Sequence[np.ndarray], settings: Settings, target_kind: str,
                  progress: Progress = None, check_masks: bool = True,
                  frames: Optional[Sequence[np.ndarray]] = None, evidence: Optional[FrameEvidence] = None,
                  unseen_read: Optional[Tuple[Optional[List[Optional[np.ndarray]]], List[str]]] = None) -> Problem:
    """Step 1: check the inputs, choose support and device, build projectors and losses.

    ``check_masks=False`` skips the mask and consistency checks (for the calibration's repeated
    short fits of the same masks, which the run itself checks once). ``frames``: the X-ray frames
    the masks were made from, one per view, for ``frame_evidence`` (``evidence``: their line
    integrals already read, by ``read_frame_evidence``; ``unseen_read``: ``frames_unseen``'s answer, already read
    for the frames' motion search: read once per run for it, the checks and the unknown pixels)."""
    t_start = time.perf_counter()
    arrays = validate_targets(targets, geometry, target_kind)
    _report(progress, phase="setup", step=0, total=settings.optimisation.total_steps, elapsed_s=0.0, eta_s=None,
            device=settings.run.device)
    grid = geometry.volume
    pixels = vessel_pixels(arrays, target_kind)
    warnings: List[str] = []
    consistency: List[float] = []
    one_view_shares: List[float] = []
    one_view_pixels: List[np.ndarray] = []
    # Hundreds of specks would each add a cone to the support (and time to every step), and, having
    # no partner in the other views, would read as a wrong geometry in the consistency check.
    despeckled, left_out = support_masks(pixels, geometry.views, grid)
    if target_kind == "mask" and check_masks:
        for n, (mask, view) in enumerate(zip(pixels, geometry.views), start=1):
            warnings += mask_warnings(mask, view.pixel_spacing_mm, source=f"view {n}")
        # Seconds to catch a wrong angle sign or a mask of the wrong view before minutes of work.
        warnings += view_separation_warnings(geometry)
        if unseen_read is None:
            unseen_read = frames_unseen(frames, geometry, target_kind)
        agreements = view_agreement(geometry, despeckled, unseen_read[0])
        consistency = [a.consistency for a in agreements]
        one_view_shares = [a.one_view_share for a in agreements]
        one_view_pixels = [a.one_view_image(v.detector_shape) for a, v in zip(agreements, geometry.views)]
        warnings += agreement_warnings(agreements)
    if settings.region.support == "hull":
        pixels = despeckled
        warnings += left_out
    if evidence is None:
        evidence = read_frame_evidence(frames, targets, geometry, settings, target_kind)
    evidence_images = evidence.images if settings.loss.frame_evidence and evidence.fits_path_lengths else None
    warnings += evidence.warnings
    if evidence_images is not None and target_kind == "mask" and settings.loss.frame_trim_mask_mm > 0:
        # the support keeps the masks as given (``pixels``): only what the fit, the finishing and the reprojection QA
        # read is trimmed
        from .evidence import border_trimmed_mask

        arrays = [border_trimmed_mask(a > 0, e, settings.loss.frame_trim_mask_mm,
                                      centre_fraction=settings.loss.frame_trim_centre_fraction).astype(np.float32)
                  for a, e in zip(arrays, evidence_images)]
    unknown = None
    if settings.region.frames_unseen_unknown:
        unknown, unreadable = unknown_pixels(frames, pixels, geometry, target_kind, unseen_read)
        warnings += unreadable
    for message in warnings:
        _report(progress, phase="warning", message=message, step=0, total=settings.optimisation.total_steps,
                elapsed_s=0.0, eta_s=None, device=settings.run.device)
    if settings.region.support == "hull":
        support = support_mask(pixels, geometry.views, grid, settings.region.support_margin_mm,
                               fields_of_view=None if unknown is None else [~u for u in unknown],
                               one_view_reach_mm=(settings.region.one_view_reach_mm if unknown is None
                                                  else settings.region.frames_unseen_reach_mm))
        voxels = np.flatnonzero(support.reshape(-1))
        if voxels.size == 0:
            raise ReconstructionError(
                "the masks' back-projections do not intersect inside the volume: check the view angles, "
                "that each mask belongs to its view (in the geometry's order), and the volume centre")
    else:
        support, voxels = None, np.arange(grid.num_voxels)
    needed_bytes = estimate_memory_bytes(settings, geometry, int(voxels.size))
    device, device_reason = choose_device(settings.run.device, needed_bytes)
    if device.type == "cpu" and settings.run.memory_check:
        check_host_memory(needed_bytes, available_memory_bytes())
    projectors = [
        ConeBeamProjector(view, grid, voxels=None if support is None else voxels, device=str(device))
        for view in geometry.views
    ]
    view_targets = [make_target(torch.as_tensor(a, device=device), target_kind, settings.loss.silhouette_length_mm)
                    for a in arrays]
    mask_targets = view_targets if evidence_images is not None else None
    if evidence_images is not None:
        # L_occ on the frames' path lengths; L_geo and the support stay on the masks.
        blur_mm = settings.loss.frame_blur_sigma_mm
        view_targets = [frame_target(torch.as_tensor(e, device=device), t,
                                     (blur_mm / v.pixel_spacing_mm[0], blur_mm / v.pixel_spacing_mm[1]))
                        for e, t, v in zip(evidence_images, view_targets, geometry.views)]
    if settings.loss.thin_vessel_weight_power > 0 and target_kind == "mask":
        weights = [torch.as_tensor(thin_vessel_weights(a > 0, settings.loss.thin_vessel_weight_power), device=device)
                   for a in arrays]
        view_targets = [dataclasses.replace(t, pixel_weight=w) for t, w in zip(view_targets, weights)]
        if mask_targets is not None:
            mask_targets = [dataclasses.replace(t, pixel_weight=w) for t, w in zip(mask_targets, weights)]
    known = None if unknown is None else [torch.as_tensor(~u, dtype=torch.float32, device=device) for u in unknown]
    if known is not None:
        view_targets = [dataclasses.replace(t, known=k) for t, k in zip(view_targets, known)]
        if mask_targets is not None:
            mask_targets = [dataclasses.replace(t, known=k) for t, k in zip(mask_targets, known)]
    geometric: Optional[GeometricLoss] = None
    if settings.mode.geometric_loss:
        loss = settings.loss
        geometric = GeometricLoss(
            [t.silhouette for t in view_targets],
            [float(np.mean(v.isocenter_pixel_spacing_mm)) for v in geometry.views],
            [None if support is None else p.pixels for p in projectors],
            DistanceSettings(loss.dt_downsample, loss.dt_threshold, loss.dt_truncation_mm, loss.dt_kernel_size,
                             loss.dt_tolerance_mm),
            known_pixels=known,
        )
    record = dict(evidence.record) if settings.loss.frame_evidence else dict(FRAME_EVIDENCE_OFF)
    if evidence_images is not None:
        record["lambda_occ"] = settings.loss.lambda_occ_frames  # the weight L_occ has on the frames' path lengths
        record["until_step"] = frames_until_step(settings)  # after it L_occ fits the masks
        if settings.loss.frame_excess_factor > 0:  # L_occ fits the masks; the frames cap the path length
            record["excess_factor"] = settings.loss.frame_excess_factor
            record["excess_tolerance_mm"] = settings.loss.frame_excess_tolerance_mm
    return Problem(geometry, settings, target_kind, arrays, support, voxels, device, device_reason, needed_bytes,
                   projectors, view_targets, geometric, time.perf_counter() - t_start, warnings, consistency, record,
                   mask_targets=mask_targets, unknown=unknown, one_view_shares=one_view_shares,
                   one_view_pixels=one_view_pixels)


def frames_unseen(frames: Optional[Sequence[Optional[np.ndarray]]], geometry: Geometry,
                  target_kind: str) -> Tuple[Optional[List[Optional[np.ndarray]]], List[str]]:
    """Per view, the pixels its frame cannot show a vessel in (``masks.unseen_pixels``: collimator, clipped parts),
    None for a view whose frame could not be read, with a warning each. None where there is nothing to read them
    off: no frames, line-integral targets, or binary "frames" (masks)."""
    if frames is None or target_kind != "mask" or len(frames) != len(geometry.views):
        return None, []
    if any(frame is None or np.shape(frame) != tuple(view.detector_shape) or is_binary_image(frame)
           for frame, view in zip(frames, geometry.views)):
        return None, []
    unseen: List[Optional[np.ndarray]] = []
    warnings = []
    for n, (frame, view) in enumerate(zip(frames, geometry.views), start=1):
        try:
            unseen.append(unseen_pixels(frame, view.pixel_spacing_mm, view.magnification))
        except MaskError as exc:
            unseen.append(None)
            warnings.append(f"view {n}: its frame's collimator and clipped parts could not be read ({exc}); every pixel of "
                            "its mask is taken as seen")
    return unseen, warnings


def unknown_pixels(frames: Optional[Sequence[Optional[np.ndarray]]], masks: Sequence[np.ndarray], geometry: Geometry,
                   target_kind: str, unseen: Optional[Tuple[Optional[List[Optional[np.ndarray]]], List[str]]] = None,
                   ) -> Tuple[Optional[List[np.ndarray]], List[str]]:
    """Per view, the pixels whose mask value says nothing (``frames_unseen_unknown``): those its frame cannot show a
    vessel in (``frames_unseen``; ``unseen``: its answer, when already read) that the mask leaves empty — a pixel the
    mask marks stays evidence — and the warnings of views whose frame could not be read (every pixel of those stays
    known). None where there is nothing to read them off."""
    images, warnings = unseen if unseen is not None else frames_unseen(frames, geometry, target_kind)
    if images is None:
        return None, warnings
    unknown = []
    for image, mask in zip(images, masks):
        mask = np.asarray(mask, bool)
        unknown.append(np.zeros_like(mask) if image is None else image & ~mask)
    return unknown, warnings


def frames_until_step(settings: Settings) -> int:
    """The last step at which L_occ fits the frames' path lengths (where they are used; ``frame_evidence_until_fraction``)."""
    return int(round(settings.loss.frame_evidence_until_fraction * settings.optimisation.steps))


def occupancy_targets(problem: Problem, step: int) -> Tuple[List[ViewTarget], float]:
    """L_occ's targets and weight at ``step`` (from 1): the frames' path lengths (λ_occ_frames) up to
    ``frames_until_step``, the masks (λ_occ) after it; without frames the problem's targets throughout."""
    if problem.mask_targets is not None and step > frames_until_step(problem.settings):
        return problem.mask_targets, problem.settings.loss.lambda_occ
    return problem.view_targets, problem.evidence.get("lambda_occ", problem.settings.loss.lambda_occ)


def caps_path_length(problem: Problem) -> bool:
    """Whether the frames only cap the path length (``frame_excess_factor`` > 0) while L_occ fits the masks."""
    return problem.mask_targets is not None and problem.settings.loss.frame_excess_factor > 0


def _mean_occupancy_loss(line_integrals: Sequence[torch.Tensor], targets: Sequence[ViewTarget]) -> torch.Tensor:
    return sum(occupancy_loss(t.rendered(li), t.image, t.occupancy_weight()) for li, t in zip(line_integrals, targets)) / len(targets)


def occupancy_terms(problem: Problem, step: int, line_integrals: Sequence[torch.Tensor]) -> Dict[str, torch.Tensor]:
    """The occupancy terms of the loss at ``step``: ``weighted`` (what the loss adds), ``l_occ`` (L_occ, mean
    over views) and, where the frames cap the path length, ``l_excess`` (``losses.excess_path_loss``), where the
    masks are fitted alongside the frames' path lengths, ``l_occ_masks``."""
    count = len(line_integrals)
    loss = problem.settings.loss
    if caps_path_length(problem):
        assert problem.mask_targets is not None
        l_occ = _mean_occupancy_loss(line_integrals, problem.mask_targets)
        if step > frames_until_step(problem.settings):
            return {"weighted": loss.lambda_occ * l_occ, "l_occ": l_occ}
        l_excess = sum(excess_path_loss(t.rendered(li), t.image, loss.frame_excess_factor,
                                        loss.frame_excess_tolerance_mm / t.reference_mm, t.known)
                       for li, t in zip(line_integrals, problem.view_targets)) / count
        return {"weighted": loss.lambda_occ * l_occ + loss.lambda_occ_frames * l_excess, "l_occ": l_occ,
                "l_excess": l_excess}
    targets, weight = occupancy_targets(problem, step)
    l_occ = _mean_occupancy_loss(line_integrals, targets)
    terms = {"weighted": weight * l_occ, "l_occ": l_occ}
    if targets is not problem.mask_targets and problem.mask_targets is not None and loss.lambda_occ_masks_with_frames > 0:
        l_masks = _mean_occupancy_loss(line_integrals, problem.mask_targets)
        terms.update(weighted=terms["weighted"] + loss.lambda_occ_masks_with_frames * l_masks, l_occ_masks=l_masks)
    return terms


COARSE_START_LEVELS = 2  # the encoding's levels active at the first step of a coarse-to-fine fit


def optimise(problem: Problem, model: ImplicitField, progress: Progress = None, cancel: Cancel = None,
             progress_interval_s: float = 0.5, snapshot: Optional[Callable[[int, np.ndarray], None]] = None,
             snapshot_every: int = 0, fit: int = 0) -> Tuple[List[Dict[str, float]], float]:
    """Step 2: Adam on ``model`` against the problem's losses. Returns (history, optimisation seconds).
    ``fit``: which of the ``ensemble_fits`` this is (from 0): progress counts the steps of every fit."""
    settings, device = problem.settings, problem.device
    o = settings.optimisation
    encoded = model.prepare(_normalised_points(problem.geometry, problem.voxels, device))
    optimiser = torch.optim.Adam([
        {"params": [model.encoding.table], "lr": o.table_learning_rate or o.learning_rate},
        {"params": list(model.mlp.parameters()), "lr": o.learning_rate},
    ])
    # A linear warm-up keeps Adam's first, sign-like steps from saturating σ(−α·s).
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimiser, lambda n: min(1.0, (n + 1) / o.warmup_steps) if o.warmup_steps > 0 else 1.0)
    history: List[Dict[str, float]] = []
    fade_steps = o.coarse_to_fine_fraction * o.steps
    # the ramp starts where the model was built to start (field_config decides whether it ramps at all)
    alpha_steps = o.alpha_ramp_fraction * o.steps if model.config.initial_alpha is not None else 0
    exclusion_steps = exclusion_schedule(settings)
    revival_step = revive_step(settings)
    allowed: Optional[torch.Tensor] = None
    averaging_from = averaging_start(settings)
    parameters = [p for group in optimiser.param_groups for p in group["params"]]  # what Adam trains
    averaged: List[torch.Tensor] = []
    t_loop = time.perf_counter()
    last_report = -math.inf
    for step in range(1, o.steps + 1):
        if _is_cancelled(cancel):
            raise ReconstructionCancelled(f"cancelled at step {step - 1} of {o.steps}")
        optimiser.zero_grad(set_to_none=True)
        if fade_steps:
            # two levels from the start, the rest faded in one after another over the first fade_steps
            levels = model.encoding.levels
            model.encoding.fade_in_levels(COARSE_START_LEVELS + (levels - COARSE_START_LEVELS) * (step - 1) / fade_steps)
        if alpha_steps:
            model.alpha = ramped_alpha(model.config.initial_alpha, model.config.alpha, (step - 1) / alpha_steps)
        if step - 1 in exclusion_steps:
            paused = time.perf_counter()
            allowed = _exclude_disagreeing_pieces(problem, model, step - 1)
            t_loop += time.perf_counter() - paused
        if step - 1 == revival_step:
            paused = time.perf_counter()
            _revive_unexplained(problem, model, allowed, step - 1)
            t_loop += time.perf_counter() - paused
        occupancy = model.occupancy_from_raw(model.raw(encoded, checkpoint_points=o.checkpoint_points), problem.logit_offset)
        if allowed is not None:
            occupancy = occupancy * allowed
        line_integrals = [projector.render(occupancy) for projector in problem.projectors]
        terms = occupancy_terms(problem, step, line_integrals)
        loss = terms["weighted"]
        l_geo = torch.zeros((), device=device)
        if problem.geometric is not None:
            l_geo = problem.geometric([t.silhouette_of(li) for li, t in zip(line_integrals, problem.view_targets)])
            loss = loss + settings.loss.lambda_geo * l_geo
        if settings.loss.lambda_binary > 0:
            loss = loss + settings.loss.lambda_binary * partial_occupancy_loss(occupancy)
        loss.backward()
        optimiser.step()
        scheduler.step()
        if averaging_from is not None and step > averaging_from:
            with torch.no_grad():
                if not averaged:
                    averaged = [p.detach().clone() for p in parameters]
                else:
                    for mean, p in zip(averaged, parameters):
                        mean.lerp_(p, 1.0 / (step - averaging_from))
        losses = {"loss": float(loss.detach()), "l_occ": float(terms["l_occ"].detach()), "l_geo": float(l_geo.detach())}
        for extra in ("l_excess", "l_occ_masks"):
            if extra in terms:
                losses[extra] = float(terms[extra].detach())
        history.append({"step": step, **losses})
        if snapshot is not None and snapshot_every > 0 and step % snapshot_every == 0:
            paused = time.perf_counter()
            snapshot(step, evaluate_volume(model, problem)[0])
            t_loop += time.perf_counter() - paused
        now = time.perf_counter()
        if now - last_report >= progress_interval_s or step == o.steps:
            elapsed = now - t_loop
            done = fit * o.steps + step
            _report(progress, phase="optimise", step=done, total=o.total_steps, elapsed_s=elapsed,
                    eta_s=elapsed / step * (o.total_steps - done), device=str(device), **losses)
            last_report = now
    model.alpha = model.config.alpha  # the result is read at the final α whatever the ramp
    if averaged:
        with torch.no_grad():
            for p, mean in zip(parameters, averaged):
                p.copy_(mean)
    return history, time.perf_counter() - t_loop


def ramped_alpha(alpha_start: float, alpha: float, progress: float) -> float:
    """σ(−α·s)'s α at ``progress`` (0 → 1, clipped) through the ramp: geometric from ``alpha_start`` to ``alpha``,
    so that each step multiplies it by the same factor."""
    return alpha_start * (alpha / alpha_start) ** min(max(progress, 0.0), 1.0)


def averaging_start(settings: Settings) -> Optional[int]:
    """The step after which the parameters are averaged into the result (``average_last_fraction``; never
    before the last exclusion, which changes what the field fits), or None when off."""
    o = settings.optimisation
    if not o.average_last_fraction:
        return None
    start = o.steps - max(1, round(o.average_last_fraction * o.steps))
    revival = revive_step(settings)
    return max([start] + exclusion_schedule(settings) + ([] if revival is None else [revival]))


def revive_step(settings: Settings) -> Optional[int]:
    """The step (from 0) before which saturated voxels under unexplained mask pixels are revived
    (``revive_fraction``), or None when off."""
    o = settings.optimisation
    return round(o.revive_fraction * o.steps) if o.revive_fraction else None


def _revive_unexplained(problem: Problem, model: ImplicitField, allowed: Optional[torch.Tensor], step: int) -> None:
    """``revival.py`` on the fit so far: sets ``problem.logit_offset`` and records what it revived."""
    t0 = time.perf_counter()
    o = problem.settings.optimisation
    with torch.no_grad():
        points = _normalised_points(problem.geometry, problem.voxels, problem.device)
        logits = model.logit_from_raw(model.raw(points))
        if problem.logit_offset is not None:
            logits = logits + problem.logit_offset
        occupancy = torch.sigmoid(logits)
        if allowed is not None:  # excluded voxels render nothing and are not revived
            occupancy = occupancy * allowed
        rendered = [projector.render(occupancy).cpu().numpy() for projector in problem.projectors]
        revive = unexplained_in_every_view(rendered, vessel_pixels(problem.targets, problem.target_kind),
                                           problem.geometry.views, problem.geometry.volume, problem.voxels)
        if allowed is not None:
            revive &= allowed.cpu().numpy() > 0
        offsets = revival_offsets(logits, revive, o.revive_occupancy)
        problem.logit_offset = offsets if problem.logit_offset is None else problem.logit_offset + offsets
    problem.revival = problem.revival or {"revivals": []}
    problem.revival["revivals"].append({"step": step, "revived_voxels": int((offsets > 0).sum()),
                                        "occupancy": o.revive_occupancy, "seconds": round(time.perf_counter() - t0, 3)})


def exclusion_schedule(settings: Settings) -> List[int]:
    """The steps after which the width check's pieces are taken out of the field: the first at
    ``width_exclusion_fraction`` of the steps, ``width_exclusion_repeats`` in all, evenly spaced to the end."""
    region, steps = settings.region, settings.optimisation.steps
    if not region.width_exclusion_fraction or not region.width_agreement_min_ratio:
        return []
    first = region.width_exclusion_fraction
    return sorted({round((first + k * (1.0 - first) / region.width_exclusion_repeats) * steps)
                   for k in range(region.width_exclusion_repeats)})


def _exclude_disagreeing_pieces(problem: Problem, model: ImplicitField, step: int) -> torch.Tensor:
    """The width check (``disagreeing_pieces``, keeping the tree whole) on the fit so far; what it would
    remove is taken out of the field for the rest of the fit (``problem.excluded``). Returns the support
    voxels' weights, 0 where excluded."""
    t0 = time.perf_counter()
    settings, geometry = problem.settings, problem.geometry
    region = settings.region
    occupancy_volume, _ = evaluate_volume(model, problem)
    segmentation = occupancy_volume >= region.threshold
    references = vessel_pixels(problem.targets, problem.target_kind)
    checked, finishing = segmentation, {}
    if region.exclusion_takes_finishing_removals and segmentation.any():
        traced = problem.projectors if problem.support is not None else None  # as in finish
        checked, finishing = finishing_removals(segmentation, references, geometry, region, traced, problem.unknown)
    kept, record = disagreeing_pieces(checked, references, geometry, region.width_agreement_min_ratio,
                                      region.prune_piece_mm, keep_connected=True, measure=region.width_agreement_measure,
                                      unknown=problem.unknown, views=region.width_agreement_views)
    zone = removal_zone(segmentation, kept, geometry.volume.spacing_mm)
    problem.excluded = zone if problem.excluded is None else problem.excluded | zone
    problem.exclusion = problem.exclusion or {"exclusions": []}
    problem.exclusion["exclusions"].append({"step": step, "removed_pieces": record["removed_pieces"],
                                            "removed_voxels": record["removed_voxels"], **finishing,
                                            "seconds": round(time.perf_counter() - t0, 3)})
    problem.exclusion["excluded_voxels"] = int(problem.excluded.sum())
    keep = ~problem.excluded.reshape(-1)[problem.voxels]
    return torch.as_tensor(keep, dtype=torch.float32, device=problem.device)


def prune_settings(region: RegionSettings) -> PruneSettings:
    """The pruning ``region`` asks for."""
    return PruneSettings(max_piece_mm=region.prune_piece_mm, tolerance=region.prune_tolerance,
                         keep_connected=region.prune_keep_connected, split_disconnected_pieces=region.prune_split_pieces)


def finishing_removals(segmentation: np.ndarray, references: Sequence[np.ndarray], geometry: Geometry,
                       region: RegionSettings, projectors: Optional[Sequence[ConeBeamProjector]],
                       unknown: Optional[Sequence[np.ndarray]] = None) -> Tuple[np.ndarray, Dict[str, int]]:
    """The segmentation less what ``finish``'s pruning and fragment check (as ``region`` asks) would remove,
    and how many voxels each removed. ``projectors``: the fit's own (they hold every voxel of the support), or None;
    ``unknown``: per view the pixels whose mask value says nothing, or None."""
    counts: Dict[str, int] = {}
    if region.prune:
        kept, _ = prune_redundant_branches(segmentation, references, geometry,
                                           prune_settings(region),
                                           projectors=projectors)
        counts["pruned_voxels"] = int((segmentation & ~kept).sum())
        segmentation = segmentation & kept
    if region.drop_unconfirmed_fragments and segmentation.any():
        removed, _ = unconfirmed_fragments(segmentation, references, geometry, projectors=projectors, unknown=unknown)
        counts["unconfirmed_voxels"] = int(removed.sum())
        segmentation = segmentation & ~removed
    return segmentation, counts


def erase_removed(segmentation: np.ndarray, kept: np.ndarray, occupancy_volume: np.ndarray, field_volume: np.ndarray,
                  geometry: Geometry, settings: Settings) -> np.ndarray:
    """Empties what a finishing step removed (``pruning.removal_zone``) in the occupancy and the field, in
    place, so that the outputs agree with the segmentation; returns the new segmentation."""
    zone = removal_zone(segmentation, kept, geometry.volume.spacing_mm)
    occupancy_volume[zone] = 0.0
    field_volume[zone] = float(field_volume.max()) if settings.mode.field_kind == "sdf" else float(field_volume.min())
    return occupancy_volume >= settings.region.threshold


#: report.json's ``last_pruning`` where prune_last_only_without_motion skipped it, by ``Problem.motion_found``
LAST_PRUNING_SKIPPED = {
    True: "the frames' pose check found a motion between the views: corrected, they still disagree by about a "
          "millimetre, and pruning last would remove true vessel (bench/RESULTS.md §98e)",
    None: "no pose check told that the views agree (no frames, calibrate_from_frames off, or a view it could not "
          "search or measure)",
}


def finish(problem: Problem, model: ImplicitField, history: List[Dict[str, float]], optimise_s: float,
           t_start: float, progress: Progress = None, cancel: Cancel = None,
           volumes: Optional[Tuple[np.ndarray, np.ndarray]] = None) -> Reconstruction:
    """Step 3: the field on the grid, thresholded and (when asked) pruned, with the report. ``volumes``:
    (occupancy, raw field) to finish instead of the model's (changed in place)."""
    settings, geometry = problem.settings, problem.geometry
    steps = settings.optimisation.total_steps
    _report(progress, phase="output", step=steps, total=steps, elapsed_s=optimise_s, eta_s=0.0, device=str(problem.device))
    t_out = time.perf_counter()
    occupancy_volume, field_volume = volumes if volumes is not None else evaluate_volume(model, problem)
    # whatever steps below the settings switch on: a cancel during the evaluation is honoured here
    if _is_cancelled(cancel):
        raise ReconstructionCancelled("cancelled after evaluating the field on the grid")
    segmentation = occupancy_volume >= settings.region.threshold
    # The fit's projectors already traced every ray through the support, which holds every voxel the
    # steps below keep; over the whole grid (no support) their matrices are too large to reread.
    traced = problem.projectors if problem.support is not None else None
    references = vessel_pixels(problem.targets, problem.target_kind)
    pruning: Optional[Dict[str, Any]] = None
    if settings.region.prune and segmentation.any():
        if _is_cancelled(cancel):
            raise ReconstructionCancelled("cancelled before pruning")
        _report(progress, phase="prune", step=steps, total=steps, elapsed_s=optimise_s, eta_s=None, device=str(problem.device))
        kept, pruning = prune_redundant_branches(
            segmentation, references, geometry,
            prune_settings(settings.region),
            projectors=traced)
        segmentation = erase_removed(segmentation, kept, occupancy_volume, field_volume, geometry, settings)
    unconfirmed: Optional[Dict[str, Any]] = None
    reconnection: Optional[Dict[str, Any]] = None
    if (settings.region.drop_unconfirmed_fragments or settings.region.reconnect) and segmentation.any():
        if _is_cancelled(cancel):
            raise ReconstructionCancelled("cancelled before checking and joining the fragments")
        segmentation, unconfirmed, reconnection = drop_then_join_fragments(
            segmentation, occupancy_volume, field_volume, references, geometry, problem.support, settings, projectors=traced,
            unknown=problem.unknown)
    # last: grown only from what pruning and the fragment checks kept (before them it grows ghosts too);
    # the grown voxels' occupancy is raised to the threshold, as bridges are filled, so that occupancy.nrrd,
    # the surface and `analyse` keep reading the segmentation as occupancy ≥ threshold
    grown = grown_segmentation(segmentation, occupancy_volume, settings.region) & ~segmentation
    grown_voxels = int(grown.sum()) if settings.region.grow_threshold else None
    if grown.any():
        occupancy_volume[grown] = settings.region.threshold
        field_volume[grown] = field_values(np.float32(settings.region.threshold), settings.mode.field_kind, settings.field.alpha)
        segmentation = segmentation | grown
    width_check: Optional[Dict[str, Any]] = None
    if settings.region.width_agreement_min_ratio and segmentation.any():
        if _is_cancelled(cancel):
            raise ReconstructionCancelled("cancelled before checking the views' widths")
        # after growing, as measured (RESULTS §29b); only where the tree stays whole: cut where a ghost
        # joins two true vessels, the tree lost more than the ghost (the rule cutting freely scored lower)
        kept, width_check = disagreeing_pieces(segmentation, references, geometry,
                                               settings.region.width_agreement_min_ratio, settings.region.prune_piece_mm,
                                               keep_connected=True, measure=settings.region.width_agreement_measure,
                                               unknown=problem.unknown, views=settings.region.width_agreement_views)
        segmentation = erase_removed(segmentation, kept, occupancy_volume, field_volume, geometry, settings)
    small: Optional[Dict[str, Any]] = None
    if settings.region.min_fragment_volume_mm3 and segmentation.any():
        removed, small = small_fragments(segmentation, geometry.volume.spacing_mm, settings.region.min_fragment_volume_mm3)
        segmentation = erase_removed(segmentation, segmentation & ~removed, occupancy_volume, field_volume, geometry, settings)
    filled: Optional[Dict[str, Any]] = None
    if settings.region.fill_unexplained and segmentation.any():
        if _is_cancelled(cancel):
            raise ReconstructionCancelled("cancelled before filling in the unexplained vessels")
        segmentation, filled = fill_unexplained(segmentation, occupancy_volume, field_volume, references, geometry,
                                                problem.support, settings, projectors=traced, unknown=problem.unknown)
    last_pruning: Optional[Dict[str, Any]] = None
    enough_views = 0 < settings.region.prune_last_min_views_any_motion <= len(geometry.views)
    if (settings.region.prune_last and settings.region.prune_last_only_without_motion and problem.motion_found is not False
            and not enough_views):
        last_pruning = {"skipped": LAST_PRUNING_SKIPPED[problem.motion_found]}
    elif settings.region.prune_last and segmentation.any():
        if _is_cancelled(cancel):
            raise ReconstructionCancelled("cancelled before pruning again")
        _report(progress, phase="prune", step=steps, total=steps, elapsed_s=optimise_s, eta_s=None, device=str(problem.device))
        # with each piece's parts apart, so that a component kept whole is whole voxel by voxel: this late, only
        # final_reconnect_max_gap_mm (off in `fast`) could join what a cut would leave apart
        last = dataclasses.replace(prune_settings(settings.region), split_disconnected_pieces=True)
        kept, last_pruning = prune_redundant_branches(segmentation, references, geometry, last, projectors=traced)
        segmentation = erase_removed(segmentation, kept, occupancy_volume, field_volume, geometry, settings)
    final_reconnection: Optional[Dict[str, Any]] = None
    if settings.region.final_reconnect_max_gap_mm and segmentation.any():
        if _is_cancelled(cancel):
            raise ReconstructionCancelled("cancelled before joining the fragments again")
        # after the specks went: a long bridge to a speck would mostly join a ghost (two in three, RESULTS §58a)
        segmentation, final_reconnection = join_fragments(segmentation, occupancy_volume, field_volume, geometry, problem.support,
                                                          settings, settings.region.final_reconnect_max_gap_mm)
    projected = reprojected_masks(segmentation, geometry, projectors=traced)
    if _is_cancelled(cancel):
        raise ReconstructionCancelled("cancelled after reprojecting the result")
    if problem.unknown is not None:  # only what each view could see: a vessel behind its collimator disagrees with nothing
        projected = [p & ~u for p, u in zip(projected, problem.unknown)]
    one_view = problem.one_view_pixels or [None] * len(geometry.views)
    qa = [reprojection_qa(p, m, v, o) for p, m, v, o in zip(projected, references, geometry.views, one_view)]
    qa_warned = qa_warnings(qa)
    for message in qa_warned:
        _report(progress, phase="warning", message=message, step=steps, total=steps, elapsed_s=optimise_s,
                eta_s=None, device=str(problem.device))
    output_s = time.perf_counter() - t_out
    report: Dict[str, Any] = {
        "method": settings.mode.title,
        "settings": settings.to_dict(),
        "target_kind": problem.target_kind,
        "seed": settings.run.seed,
        "device": device_description(problem.device),
        "device_reason": problem.device_reason,
        "memory_estimate_bytes": problem.memory_estimate_bytes,
        "versions": versions(),
        "geometry": geometry.to_dict(),
        "geometry_digest": geometry.digest(),
        "support_voxels": int(problem.voxels.size),
        "segmented_voxels": int(segmentation.sum()),
        "grown_voxels": grown_voxels,  # added below the threshold by grow_threshold (None: off)
        "pruning": pruning,
        "width_agreement": width_check,
        "width_exclusion": problem.exclusion,
        "revival": problem.revival,
        "reconnection": reconnection,
        "final_reconnection": final_reconnection,
        "unconfirmed_fragments": unconfirmed,
        "small_fragments": small,
        "unexplained_fill": filled,
        "last_pruning": last_pruning,
        # the pose checks before the fit: True a motion found and corrected, False none beyond noise, None not known
        "motion_found": problem.motion_found,
        "components": component_counts(segmentation),
        "projector_nonzeros": [p.nnz for p in problem.projectors],
        "final_losses": {k: v for k, v in history[-1].items() if k != "step"} if history else {},
        "reprojection_dice": [q["dice"] for q in qa],
        "reprojection_qa": qa,
        "timings_s": {"setup": problem.setup_s, "optimise": optimise_s, "output": output_s,
                      "total": time.perf_counter() - t_start, "per_step": optimise_s / steps},
        "warnings": list(problem.warnings) + qa_warned,
        "view_consistency": list(problem.consistency),
        # per view, the share of its vessel centreline that runs where another view cannot show it (seen by one view)
        "one_view_share": [round(v, 4) for v in problem.one_view_shares],
        "frame_evidence": problem.evidence,
        # per view, the share of the detector whose mask value was taken as unknown (None: every pixel known)
        "unknown_pixel_fraction": None if problem.unknown is None else [round(float(u.mean()), 4) for u in problem.unknown],
    }
    return Reconstruction(geometry, settings, occupancy_volume, field_volume, segmentation, problem.support, report, history,
                          list(zip(projected, references)), list(problem.one_view_pixels))


def fill_unexplained(segmentation: np.ndarray, occupancy_volume: np.ndarray, field_volume: np.ndarray,
                     masks: Sequence[np.ndarray], geometry: Geometry, support: Optional[np.ndarray], settings: Settings,
                     projectors: Optional[Sequence[ConeBeamProjector]] = None,
                     unknown: Optional[Sequence[np.ndarray]] = None) -> Tuple[np.ndarray, Dict[str, Any]]:
    """The segmentation with ``unexplained_fill``'s voxels joined to it through the field (``reconnect_max_gap_mm``,
    inside the support) and the fill that stays apart from every component of the segmentation dropped: the result
    is in no more pieces than before (the join may also bridge the segmentation's own pieces, as ``reconnect`` does).
    The added voxels' occupancy is raised to the threshold at least (as bridges are filled) and the field set to
    match, in place. Returns the new segmentation and the report."""
    region = settings.region
    explained = reprojected_masks(segmentation, geometry, projectors=projectors)
    fill, info = unexplained_fill(segmentation, masks, explained, geometry, support, unknown, region.prune_piece_mm)
    info.update(added_voxels=0, apart_voxels=0, bridges=[])
    # a fill component no bridge can reach from the segmentation is left out before joining: the join starts from the
    # largest component, which must be the tree's, not a large fill elsewhere
    labels, sizes = component_labels(fill)
    if sizes.size:
        reach = ndimage.distance_transform_edt(~segmentation, sampling=geometry.volume.spacing_mm) <= region.reconnect_max_gap_mm
        near = np.unique(labels[reach & fill])
        info["apart_voxels"] = int((fill & ~np.isin(labels, near[near > 0])).sum())
        fill = np.isin(labels, near[near > 0])
    if not fill.any():
        return segmentation, info
    raised = occupancy_volume.astype(np.float32)
    raised[fill] = np.maximum(raised[fill], region.threshold)
    # every component in turn (largest first), so that fill beside a second tree of the segmentation joins it too
    joined, joined_occupancy, _, reconnection = reconnect_fragments(
        segmentation | fill, raised, geometry.volume.spacing_mm, support,
        ReconnectSettings(region.reconnect_max_gap_mm, region.reconnect_min_occupancy, region.threshold, True))
    labels, _ = component_labels(joined)
    own = np.unique(labels[segmentation])
    kept = np.isin(labels, own[own > 0])
    added = kept & ~segmentation
    occupancy_volume[added] = np.maximum(joined_occupancy[added], region.threshold)
    field_volume[added] = field_values(occupancy_volume[added], settings.mode.field_kind, settings.field.alpha)
    bridges = []
    for bridge in reconnection["bridges"]:  # where a bridge joined kept voxels: in LPS mm for the 3D-QCA, as join_fragments
        ijk = np.asarray(bridge.pop("voxels_ijk"), dtype=np.int64).reshape(-1, 3)
        if ijk.size and kept[tuple(ijk.T)].all():
            bridge["points_mm"] = np.round(geometry.volume.index_to_world(ijk.astype(np.float64)), 3).tolist()
            bridges.append(bridge)
    info.update(added_voxels=int(added.sum()), apart_voxels=info["apart_voxels"] + int((joined & ~kept).sum()), bridges=bridges)
    return kept, info


def grown_segmentation(segmentation: np.ndarray, occupancy: np.ndarray, region: RegionSettings) -> np.ndarray:
    """The segmentation grown into the 26-connected voxels of occupancy ≥ ``grow_threshold`` (hysteresis)."""
    if not region.grow_threshold or region.grow_threshold >= region.threshold or not segmentation.any():
        return segmentation
    candidates, _ = component_labels((occupancy >= region.grow_threshold) | segmentation)
    return np.isin(candidates, np.unique(candidates[segmentation]))


def drop_then_join_fragments(
    segmentation: np.ndarray,
    occupancy_volume: np.ndarray,
    field_volume: np.ndarray,
    masks: Sequence[np.ndarray],
    geometry: Geometry,
    support: Optional[np.ndarray],
    settings: Settings,
    projectors: Optional[Sequence[ConeBeamProjector]] = None,
    unknown: Optional[Sequence[np.ndarray]] = None,
) -> Tuple[np.ndarray, Optional[Dict[str, Any]], Optional[Dict[str, Any]]]:
    """The detached fragments that some view does not confirm removed, then the rest joined to the tree.

    Each step as ``settings.region`` asks (``drop_unconfirmed_fragments``, ``reconnect``). Ghosts go
    first: joined to the tree first, a ghost would be part of the largest component, which the
    confirmation step never judges (RESULTS §19). ``occupancy_volume`` and ``field_volume`` are updated
    in place (removed voxels emptied, bridges filled); returns the new segmentation and the two steps'
    reports (None for a step that is off). Bridges carry their gap's points in LPS mm. ``unknown``: per view the
    pixels whose mask value says nothing (``Problem.unknown``), None: all known.
    """
    region = settings.region
    unconfirmed: Optional[Dict[str, Any]] = None
    if region.drop_unconfirmed_fragments and segmentation.any():
        removed, unconfirmed = unconfirmed_fragments(segmentation, masks, geometry, projectors=projectors, unknown=unknown)
        if removed.any():
            segmentation = erase_removed(segmentation, segmentation & ~removed, occupancy_volume, field_volume, geometry,
                                         settings)
    reconnection: Optional[Dict[str, Any]] = None
    if region.reconnect and segmentation.any():
        segmentation, reconnection = join_fragments(segmentation, occupancy_volume, field_volume, geometry, support, settings,
                                                    region.reconnect_max_gap_mm)
    return segmentation, unconfirmed, reconnection


def join_fragments(segmentation: np.ndarray, occupancy_volume: np.ndarray, field_volume: np.ndarray, geometry: Geometry,
                   support: Optional[np.ndarray], settings: Settings, max_gap_mm: float) -> Tuple[np.ndarray, Dict[str, Any]]:
    """The fragments joined to the tree across gaps up to ``max_gap_mm`` (``connectivity.reconnect_fragments``);
    ``occupancy_volume`` and ``field_volume`` are filled along the bridges in place. Returns the new segmentation
    and the report, whose bridges carry their gap's points in LPS mm."""
    region = settings.region
    segmentation, joined_occupancy, changed, reconnection = reconnect_fragments(
        segmentation, occupancy_volume, geometry.volume.spacing_mm, support,
        ReconnectSettings(max_gap_mm, region.reconnect_min_occupancy, region.threshold, region.reconnect_every_component))
    occupancy_volume[changed] = joined_occupancy[changed]
    field_volume[changed] = field_values(joined_occupancy[changed], settings.mode.field_kind, settings.field.alpha)
    for bridge in reconnection["bridges"]:  # where the vessel was broken, in LPS mm for the 3D-QCA
        ijk = np.asarray(bridge.pop("voxels_ijk"), dtype=np.float64).reshape(-1, 3)
        bridge["points_mm"] = np.round(geometry.volume.index_to_world(ijk), 3).tolist()
    return segmentation, reconnection


def fitted_loss(geometry: Geometry, targets: Sequence[np.ndarray], settings: Settings, target_kind: str,
                last_steps: int, cancel: Cancel = None) -> float:
    """The mean loss of the last ``last_steps`` steps of a field fitted from scratch (the run's seed):
    how well ``geometry`` lets one field explain every view (``calibration.py``)."""
    torch.manual_seed(settings.run.seed)
    problem = build_problem(geometry, targets, settings, target_kind, check_masks=False)
    model = ImplicitField(field_config(settings)).to(problem.device)
    history, _ = optimise(problem, model, cancel=cancel)
    return float(np.mean([h["loss"] for h in history[-last_steps:]]))


@dataclass
class EnsembleFit:
    """One fit of an ensemble kept whole for ``finish`` (``ensemble_combine`` "best_reprojection"): the trained
    field, its loss history, its seed and what its mid-fit steps left on the problem (``FitState``)."""

    model: ImplicitField
    history: List[Dict[str, float]]
    seed: int
    state: "FitState"


@dataclass
class FitState:
    """What one fit's mid-fit steps set on the problem: the voxels its width exclusion took out (and the
    record of it), the revival's logit offsets (and the record); each fit of an ensemble has its own."""

    excluded: Optional[np.ndarray]
    exclusion: Optional[Dict[str, Any]]
    logit_offset: Optional[torch.Tensor]
    revival: Optional[Dict[str, Any]]

    @classmethod
    def of(cls, problem: "Problem") -> "FitState":
        return cls(problem.excluded, problem.exclusion, problem.logit_offset, problem.revival)

    def apply_to(self, problem: "Problem") -> None:
        problem.excluded, problem.exclusion, problem.logit_offset, problem.revival = (
            self.excluded, self.exclusion, self.logit_offset, self.revival)


@dataclass
class FittedField:
    """What ``fit_field`` leaves for ``finish``: the problem (at the calibrated geometry), the trained
    field, its loss history and timings, and what the calibrations and the frames' evidence found."""

    problem: Problem
    model: ImplicitField
    history: List[Dict[str, float]]
    optimise_s: float
    t_start: float
    calibrations: List[Any]
    evidence: FrameEvidence
    volumes: Optional[Tuple[np.ndarray, np.ndarray]] = None  # (occupancy, raw field) when not the model's (ensemble_fits)
    # each fit's (occupancy, raw field) where fit_field was asked to keep them (ensemble_fits > 1)
    members: List[Tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    # every fit kept whole, to be finished and the best reprojecting one kept (ensemble_combine "best_reprojection")
    fits: List[EnsembleFit] = field(default_factory=list)

    def finished(self, settings: Optional[Settings] = None, progress: Progress = None,
                 cancel: Cancel = None) -> Reconstruction:
        """``finish`` of this fit; ``settings`` (default: the fit's own) may change what ``finish`` decides —
        threshold, growing, pruning, the fragment steps — so benchmarks compare those rules on one fit."""
        problem = self.problem if settings is None else dataclasses.replace(self.problem, settings=settings)
        if self.fits:
            return self._best_reprojecting(problem, progress, cancel)
        volumes = None if self.volumes is None else (self.volumes[0].copy(), self.volumes[1].copy())
        return finish(problem, self.model, self.history, self.optimise_s, self.t_start, progress, cancel, volumes)

    def _best_reprojecting(self, problem: Problem, progress: Progress, cancel: Cancel) -> Reconstruction:
        """Each fit finished on its own; the result is the one whose segmentation reprojects best onto the
        masks (highest mean reprojection Dice over the views; the first fit on a tie). The fits' own
        reprojection Dice and the choice are in the report's ``ensemble_choice``; the problem is left with
        the kept fit's exclusion and revival."""
        best, chosen = None, 0
        scores: List[List[float]] = []
        for n, fit in enumerate(self.fits):
            fit.state.apply_to(problem)
            result = finish(problem, fit.model, fit.history, self.optimise_s, self.t_start, progress, cancel)
            scores.append([float(d) for d in result.report["reprojection_dice"]])
            if best is None or np.mean(scores[-1]) > np.mean(scores[chosen]):
                best, chosen = result, n
        self.fits[chosen].state.apply_to(problem)
        best.report["ensemble_choice"] = {
            "combine": "best_reprojection", "seeds": [fit.seed for fit in self.fits],
            "reprojection_dice": scores, "chosen_fit": chosen, "chosen_seed": self.fits[chosen].seed}
        return best


def fit_field(geometry: Geometry, targets: Sequence[np.ndarray], settings: Settings, target_kind: str = "mask",
              frames: Optional[Sequence[np.ndarray]] = None, progress: Progress = None, cancel: Cancel = None,
              keep_members: bool = False, frame_intensity: Optional[Sequence[Optional[str]]] = None,
              **loop: Any) -> FittedField:
    """``reconstruct`` up to the trained field: the frames' evidence, the calibrations asked for, the
    problem and the optimisation (``reconstruct``'s arguments; ``loop``: ``optimise``'s progress interval
    and snapshots; ``keep_members``: with ``ensemble_fits`` > 1, keep each fit's volumes, for benchmarks).
    ``finish`` makes the result of it."""
    settings.validate()
    t_start = time.perf_counter()
    if settings.run.threads:
        torch.set_num_threads(int(settings.run.threads))
    torch.manual_seed(settings.run.seed)
    np.random.seed(settings.run.seed % (2**32))
    evidence = read_frame_evidence(frames, targets, geometry, settings, target_kind, frame_intensity)
    calibrations, unseen_read = check_poses(geometry, targets, settings, target_kind, frames, evidence, progress, cancel)
    if calibrations:
        geometry = calibrations[-1].geometry
    problem = build_problem(geometry, targets, settings, target_kind, progress, frames=frames, evidence=evidence,
                            unseen_read=unseen_read)
    problem.motion_found = motion_found_by(calibrations)
    if _is_cancelled(cancel):
        raise ReconstructionCancelled("cancelled before the optimisation started")
    model = ImplicitField(field_config(settings)).to(problem.device)
    history, optimise_s = optimise(problem, model, progress, cancel, **loop)
    volumes, members, fits = None, [], []
    if settings.optimisation.ensemble_fits > 1 and settings.optimisation.ensemble_combine == "best_reprojection":
        fits, optimise_s = _ensemble_fits(problem, model, history, optimise_s, progress, cancel, **loop)
    elif settings.optimisation.ensemble_fits > 1:
        volumes, optimise_s, members = _ensemble_volumes(problem, model, history, optimise_s, progress, cancel, keep_members,
                                                         **loop)
    return FittedField(problem, model, history, optimise_s, t_start, calibrations, evidence, volumes, members, fits)


def check_poses(geometry: Geometry, targets: Sequence[np.ndarray], settings: Settings, target_kind: str,
                frames: Optional[Sequence[np.ndarray]], evidence: FrameEvidence, progress: Progress = None,
                cancel: Cancel = None) -> Tuple[List[Any], Optional[List[Optional[np.ndarray]]]]:
    """The pose checks the settings ask for before the fit, in order: from the frames' line integrals
    (``calibrate_from_frames``), then by re-fitting (``calibrate``). Returns the ``Calibration``s (the last one's
    geometry is the corrected one) and the frames' unseen pixels where the first check read them (else None)."""
    calibrations: List[Any] = []
    unseen_read = None
    if settings.calibration.calibrate_from_frames and len(geometry.views) > 1 and evidence.images is not None:
        from .calibration import calibrate_from_frames

        unseen_read = frames_unseen(frames, geometry, target_kind)
        unseen = unknown_pixels(frames, targets, geometry, target_kind, unseen_read)[0]
        calibrations.append(calibrate_from_frames(
            geometry, evidence.images, progress, settings.calibration.calibration_min_consistency_gain,
            unseen if settings.calibration.calibration_skip_truncated_planes else None, confirm_unseen=unseen,
            min_untruncated_gain=settings.calibration.calibration_min_untruncated_gain))
        geometry = calibrations[-1].geometry
    if settings.calibration.calibrate and len(geometry.views) > 1:
        from .calibration import calibrate

        calibrations.append(calibrate(geometry, targets, settings, target_kind, progress=progress, cancel=cancel))
        torch.manual_seed(settings.run.seed)
    return calibrations, unseen_read


def motion_found_by(calibrations: Sequence[Any]) -> Optional[bool]:
    """Over the pose checks that ran (``Calibration``s): True where any found a motion, False where every one
    searched every view and found none beyond noise, None where none ran or one could not tell."""
    from .calibration import combined_motion_found

    return combined_motion_found([calibration.motion_found() for calibration in calibrations])


def _ensemble_fits(problem: Problem, first: ImplicitField, first_history: List[Dict[str, float]], first_s: float,
                   progress: Progress, cancel: Cancel, **loop: Any) -> Tuple[List[EnsembleFit], float]:
    """``ensemble_fits`` fits of the problem kept whole (``first`` already trained on the run's seed; the
    others on seed + 1, …, each from its own initialisation, with its own mid-fit exclusion and revival),
    and the fits' seconds together."""
    settings = problem.settings
    fits = [EnsembleFit(first, first_history, settings.run.seed, FitState.of(problem))]
    optimise_s = first_s
    for member in range(1, settings.optimisation.ensemble_fits):
        FitState(None, None, None, None).apply_to(problem)
        torch.manual_seed(settings.run.seed + member)
        model = ImplicitField(field_config(settings)).to(problem.device)
        history, seconds = optimise(problem, model, progress, cancel, fit=member, **loop)
        optimise_s += seconds
        fits.append(EnsembleFit(model, history, settings.run.seed + member, FitState.of(problem)))
    return fits, optimise_s


def _ensemble_volumes(problem: Problem, first: ImplicitField, first_history: List[Dict[str, float]], first_s: float,
                      progress: Progress, cancel: Cancel, keep_members: bool = False, **loop: Any
                      ) -> Tuple[Tuple[np.ndarray, np.ndarray], float, List[Tuple[np.ndarray, np.ndarray]]]:
    """``_ensemble_fits``, averaged: the mean of the fits' occupancy volumes (each with its own exclusion and
    revival) with the raw field that gives it, the fits' seconds together, and (``keep_members``) each fit's
    (occupancy, raw field). Afterwards ``problem.excluded`` is None (each fit's exclusion is in its own
    volume) and ``problem.exclusion`` and ``problem.revival`` list every fit's."""
    fits, optimise_s = _ensemble_fits(problem, first, first_history, first_s, progress, cancel, **loop)
    occupancy_sum = np.zeros(problem.geometry.volume.shape, dtype=np.float64)
    members = []
    for fit in fits:
        fit.state.apply_to(problem)
        volumes = evaluate_volume(fit.model, problem)
        occupancy_sum += volumes[0]
        if keep_members:
            members.append(volumes)
    records = [fit.state.exclusion for fit in fits]
    revivals = [fit.state.revival for fit in fits]
    problem.excluded, problem.logit_offset = None, None
    problem.exclusion = {"fits": records} if any(records) else None
    problem.revival = {"fits": revivals} if any(revivals) else None
    return volumes_of_occupancy(occupancy_sum / len(fits), problem.settings), optimise_s, members


def volumes_of_occupancy(occupancy: np.ndarray, settings: Settings) -> Tuple[np.ndarray, np.ndarray]:
    """(occupancy, the raw field that gives it): what ``finish`` takes, for an occupancy no one field gave."""
    occupancy = np.asarray(occupancy, dtype=np.float32)
    return occupancy, field_values(occupancy, settings.mode.field_kind, settings.field.alpha)


def reconstruct(
    geometry: Geometry,
    targets: Sequence[np.ndarray],
    settings: Union[Settings, Dict[str, Any], None] = None,
    target_kind: str = "mask",
    progress: Progress = None,
    cancel: Cancel = None,
    progress_interval_s: float = 0.5,
    snapshot: Optional[Callable[[int, np.ndarray], None]] = None,
    snapshot_every: int = 0,
    frames: Optional[Sequence[np.ndarray]] = None,
    frame_intensity: Optional[Sequence[Optional[str]]] = None,
) -> Reconstruction:
    """Reconstruct the vessel tree seen in ``targets`` (one image per view of ``geometry``).

    ``settings``: a ``Settings``, or as the jobs take them a dict of a ``preset`` (default ``fast``) and the
    settings it changes by key, e.g. ``{"steps": 200}``; None: ``fast``.
    ``frames``: the X-ray frames the masks were drawn or segmented on, one per view (optional);
    with ``frame_evidence`` the occupancy is fitted to the path lengths read off them (``evidence.py``).
    ``frame_intensity``: per view, the frame's DICOM Pixel Intensity Relationship (0028,1040), None where not
    known; path lengths are read only off LIN frames (``evidence.unreadable_intensity``). A frame of 8-bit grey
    levels whose relationship is not known is taken as DISP, with a warning (``evidence.assumed_relationship``).

    ``snapshot(step, occupancy)`` — for benchmarks of time to accuracy — receives the occupancy
    volume every ``snapshot_every`` steps (its time is excluded from the optimisation timings).
    """
    if isinstance(settings, dict):
        settings = settings_from_values(settings)
    settings = settings or make_settings()
    # an 8-bit frame nobody said anything of was processed for display (evidence.assumed_relationship)
    frame_intensity, assumed = assumed_frame_intensity(frames, frame_intensity)
    for message in assumed:
        _report(progress, phase="warning", message=message, step=0, total=settings.optimisation.total_steps,
                elapsed_s=0.0, eta_s=None, device=str(settings.run.device))
    fitted = fit_field(geometry, targets, settings, target_kind, frames, progress, cancel, frame_intensity=frame_intensity,
                       progress_interval_s=progress_interval_s, snapshot=snapshot, snapshot_every=snapshot_every)
    calibrations, evidence = fitted.calibrations, fitted.evidence
    result = fitted.finished(progress=progress, cancel=cancel)
    if frame_intensity is not None:  # for `analyse`: whether its frames' absorbance can be read (densitometry)
        result.report["frame_intensity"] = list(frame_intensity)
    if assumed:
        result.report["frame_intensity_assumed"] = assumed
        result.report["warnings"] = assumed + result.report["warnings"]
    if settings.optimisation.ensemble_fits > 1:
        result.report["ensemble_seeds"] = [settings.run.seed + k for k in range(settings.optimisation.ensemble_fits)]
    if calibrations:
        result.report["calibration"] = calibrations[-1].report()
        if len(calibrations) > 1:  # from the frames, then the re-fit search on top
            result.report["calibration"]["first"] = calibrations[0].report()
    elif settings.calibration.calibrate_from_frames:
        result.report["calibration"] = {"method": "none", "why": "no frames to read the motion from" if frames is None
                                        else f"the frames' line integrals could not be read: {evidence.record.get('why')}"}
    for calibration in calibrations:
        result.report["warnings"] = calibration.warnings + result.report["warnings"]
        for message in calibration.warnings:
            _report(progress, phase="warning", message=message, step=settings.optimisation.total_steps,
                    total=settings.optimisation.total_steps, elapsed_s=0.0, eta_s=None, device=str(settings.run.device))
    return result


@torch.no_grad()
def evaluate_volume(model: ImplicitField, problem: Problem, chunk: int = 262144) -> Tuple[np.ndarray, np.ndarray]:
    """(occupancy, raw field) on the whole grid; outside the support the field is marked as clearly outside."""
    grid, voxels = problem.geometry.volume, problem.voxels
    raw_values = []
    for start in range(0, voxels.size, chunk):
        points = _normalised_points(problem.geometry, voxels[start:start + chunk], problem.device)
        raw_values.append(model.raw(points).float().cpu())
    raw = torch.cat(raw_values) if raw_values else torch.zeros(0)
    offset = None if problem.logit_offset is None else problem.logit_offset.float().cpu()
    occupancy = model.occupancy_from_raw(raw, offset).numpy()
    if offset is not None:  # the field whose σ(−α·s) is that occupancy (revival.py)
        raw = raw - offset / model.alpha if model.config.kind == "sdf" else raw + offset
    occ_volume = np.zeros(grid.num_voxels, dtype=np.float32)
    occ_volume[voxels] = occupancy
    if model.config.kind == "sdf":
        outside = max(float(raw.max()) if raw.numel() else 1.0, 1.0)
    else:
        outside = min(float(raw.min()) if raw.numel() else -10.0, -10.0)
    field_volume = np.full(grid.num_voxels, outside, dtype=np.float32)
    field_volume[voxels] = raw.numpy()
    if problem.excluded is not None:  # taken out during the fit (width_exclusion_fraction)
        occ_volume[problem.excluded.reshape(-1)] = 0.0
        field_volume[problem.excluded.reshape(-1)] = outside
    return occ_volume.reshape(grid.shape), field_volume.reshape(grid.shape)


def reprojected_masks(segmentation: np.ndarray, geometry: Geometry, mask_threshold_mm: float = MASK_THRESHOLD_MM,
                      projectors: Optional[Sequence[ConeBeamProjector]] = None) -> List[np.ndarray]:
    """Per view, the segmentation's projected mask (line integral above the mask threshold).

    ``projectors``: one per view whose inputs hold every segmented voxel (the reconstruction's own,
    whose rays are already traced); otherwise the segmentation is projected afresh."""
    if not segmentation.any():
        return [np.zeros(view.detector_shape, dtype=bool) for view in geometry.views]
    segmented = np.flatnonzero(segmentation.reshape(-1))
    if projectors is None or not all(p.covers(segmented) for p in projectors):
        volume = segmentation.astype(np.float32)
        return [project_volume(volume, view, geometry.volume) > mask_threshold_mm for view in geometry.views]
    masks = []
    for view, projector in zip(geometry.views, projectors):
        integrals, pixels, _ = projector.group_integrals(segmentation.astype(np.int64), 1)
        mask = np.zeros(view.detector_shape, dtype=bool)
        mask.reshape(-1)[pixels[integrals[:, 0] > mask_threshold_mm]] = True
        masks.append(mask)
    return masks

