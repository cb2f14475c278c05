"""Settings of a reconstruction, its presets and modes, the standard protocols and the metric registry.

This module imports nothing heavy (no torch, no scikit-image), so the command line, the Slicer
module and the benchmark read the lists from here instead of copying them, and ``--help`` stays
fast.

Settings
    ``Settings`` groups the values by the component they steer: ``field`` (hash encoding + MLP),
    ``optimisation`` (Adam, steps), ``loss`` (λ's and the distance maps of L_geo), ``region``
    (where the field is evaluated and what of it becomes the result: support, threshold,
    pruning) and ``run`` (preset, mode, seed, device, threads). Every key is unique across the
    groups, so a setting is also named by its key alone — ``make_settings("fast", steps=200)``,
    ``--set steps=200``, and the flat dict in ``report.json`` (``Settings.to_dict``).

    The defaults are the published recipe (the ``paper`` preset). ``fast`` is written as the
    difference from it: the field only on the masks' visual hull, a smaller network and table, a
    higher learning rate for the hash table, fewer steps, L_geo on 2× max-pooled images, the
    skeleton pieces no mask pixel needs pruned afterwards (``pruning.py``), the detached fragments
    that not every view confirms removed (``pruning.unconfirmed_fragments``), the rest joined to the
    tree where both views show vessel across the gap (``connectivity.py``), the partial occupancy
    connected to the result taken in (``grow_threshold``), the detached specks below 16 mm³ removed last
    (``min_fragment_volume_mm3``), and, where the X-ray frames
    are given with the masks, the occupancy fitted to the path lengths they show (``evidence.py``). Why each differs is
    said next to it; what it measured is in ``bench/RESULTS.md``.

Modes
    The paper's method and its ablations (Tables 1–4): which representation the field has and
    whether L_geo is used.

Protocols
    The views, grid and detector the benchmarks and the sample case use, and the line-integral
    threshold (mm) that turns a simulated view into a mask.

Metrics
    Every reported metric once: its key (as in ``metrics.py`` and the tables), title, unit and which
    direction is better.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass
from typing import Any, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple


class ReconstructionError(ValueError):
    """The inputs or settings cannot be reconstructed; the message names the problem and the fix."""


# --- modes ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Mode:
    key: str
    title: str  # the long name (report.json, the Slicer module)
    table_title: str  # the short row name of the paper's tables
    field_kind: str  # "sdf": s(x) with occupancy σ(−α·s); "occupancy": the logit itself
    geometric_loss: bool  # λ1·L_geo + λ2·L_occ when true, L_occ alone otherwise


MODES: Dict[str, Mode] = {m.key: m for m in (
    Mode("sdfcar", "SDF-CAR (SDF rep. + combined loss)", "SDF-CAR", "sdf", True),
    Mode("neca", "NeCA (occupancy rep. + occupancy loss)", "NeCA", "occupancy", False),
    Mode("occ-combined", "Occ. rep. + combined loss", "Occ. Rep. + Combined Loss", "occupancy", True),
    Mode("sdf-occ", "SDF rep. + occupancy loss", "SDF Rep. + Occ. Loss", "sdf", False),
)}
DEFAULT_MODE = "sdfcar"
TARGET_KINDS = ("mask", "line_integral")
SUPPORTS = ("hull", "full")
DEVICES = ("auto", "cpu", "cuda")


# --- settings ---------------------------------------------------------------------------------------
@dataclass
class FieldSettings:
    """The implicit field (``field.py``): multiresolution hash encoding, then a residual MLP."""

    levels: int = 16
    features_per_level: int = 2
    log2_table_size: int = 19
    base_resolution: int = 16
    max_resolution: int = 256
    width: int = 256
    depth: int = 8
    alpha: float = 50.0  # occupancy σ(−α·s) of the SDF modes
    # the SDF modes' α at the first step when alpha_ramp_fraction > 0: it rises geometrically to alpha over that
    # share of the steps, so that early on the occupancy changes over a wider band of s (coarse to sharp)
    alpha_start: float = 10.0
    initial_occupancy: float = 0.01  # the output bias starts every voxel at this occupancy


ENSEMBLE_COMBINES = ("mean", "best_reprojection")


@dataclass
class OptimisationSettings:
    """Adam on the hash table and the MLP."""

    steps: int = 5000
    learning_rate: float = 1e-4
    table_learning_rate: Optional[float] = None  # the hash table's; None: learning_rate
    warmup_steps: int = 0  # linear warm-up of both learning rates
    # >0: the encoding's finer levels are faded in over this share of the steps, coarse to fine (0: all from the start)
    coarse_to_fine_fraction: float = 0.0
    # >0: the parameters averaged over this last share of the steps (after any exclusion) become the result,
    # against Adam's jitter about the minimum at a constant rate (0: off, the published recipe; `fast` 0.2, RESULTS §38c)
    average_last_fraction: float = 0.0
    # >1: this many fits from different seeds (the run's seed, then seed + 1, …) on the same problem, each with
    # its own mid-fit exclusion; the result is made from them as ensemble_combine says (1: one fit)
    ensemble_fits: int = 1
    # "mean": the result is made from the mean of the fits' occupancies; "best_reprojection": each fit is finished
    # and the result is the one whose segmentation reprojects best onto the masks (highest mean reprojection Dice)
    ensemble_combine: str = "mean"
    # >0: after this share of the steps, the voxels on rays every view leaves unexplained whose occupancy has
    # saturated below revive_occupancy start again at it (revival.py; 0: off)
    revive_fraction: float = 0.0
    revive_occupancy: float = 0.01
    # >0: the SDF's α rises from alpha_start to alpha over this share of the steps (0: alpha throughout)
    alpha_ramp_fraction: float = 0.0
    checkpoint_points: int = 262144  # >0: the MLP in checkpointed chunks of this many points (memory)

    @property
    def total_steps(self) -> int:
        """The steps of every fit together (``ensemble_fits`` × ``steps``): what progress counts."""
        return self.steps * self.ensemble_fits


@dataclass
class LossSettings:
    """λ1·L_geo + λ2·L_occ (``losses.py``)."""

    lambda_geo: float = 1.0
    lambda_occ: float = 0.25
    silhouette_length_mm: float = 0.3  # path length at which a rendered ray counts as vessel
    dt_downsample: int = 1  # L_geo on images max-pooled by this factor
    dt_threshold: float = 0.5
    dt_truncation_mm: float = 5.0  # distances clipped here
    dt_kernel_size: int = 3
    # >0: L_geo ignores differences of the signed distance below this (mm at the isocenter): the masks'
    # borders are uncertain by about a pixel, and with frame_evidence L_occ then sets the width (0: off;
    # 0.14–0.56 level on the realistic suites: RESULTS §57b)
    dt_tolerance_mm: float = 0.0
    # where the frames are given with the masks: L_occ on the rays' path lengths read off the frames
    # (evidence.py) instead of the masks, so a ghost in the shadow of a real vessel costs what it adds
    frame_evidence: bool = False
    # the frames' path lengths are kept on the masks widened by this many pixels, 0 outside (evidence.py;
    # `fast` 0, RESULTS §62d–e)
    frame_evidence_reach_px: int = 2
    # the views' path lengths scaled to one common total before they are fitted (line_integral_consistency.
    # equal_total_factors): every view sees the same volume, but each frame's path lengths carry its own attenuation
    # estimate (up to a fifth apart). Off: static LAD +2.2, RCA −0.6, two views with motion LAD −3.0 (RESULTS §69)
    frame_evidence_equal_totals: bool = False
    # >0: the frames' path lengths restored by this many Richardson–Lucy steps against the detector's blur
    # before they are fitted (evidence.py; 0: off)
    frame_deblur_iterations: int = 0
    # λ2 when L_occ fits the frames' path lengths (they say how much vessel a ray crossed, which a mask
    # does not); 0.5 was better on static realistic cases but worse on moving LAD ones (RESULTS §18b)
    lambda_occ_frames: float = 0.25
    # the share of the steps over which L_occ fits the frames' path lengths; after it L_occ fits the masks'
    # silhouettes (weighed lambda_occ). 1: the whole fit; 0.8: LAD level, RCA −0.9, Dice lower (RESULTS §61e)
    frame_evidence_until_fraction: float = 1.0
    # >0: L_occ fits the masks' silhouettes (weighed lambda_occ) and the frames only cap the path length: a ray
    # costs (weighed lambda_occ_frames) only where it crosses more than this × the frame's path length +
    # frame_excess_tolerance_mm — a ghost in a real vessel's shadow still costs what it adds, but the frames'
    # blurred profile no longer shapes the lumen (0: off, L_occ fits the frames' path lengths; 1.2–1.5 far
    # worse: the frames' path lengths must also ask for vessel, RESULTS §62b)
    frame_excess_factor: float = 0.0
    frame_excess_tolerance_mm: float = 0.3
    # >0 (with the frames' path lengths fitted, frame_excess_factor 0): L_occ on the masks' silhouettes too,
    # weighed this, alongside the frames' (their sharp border against the frames' blurred profile; 0: off;
    # 0.25 lower on both suites, the lumen wider: RESULTS §62c)
    lambda_occ_masks_with_frames: float = 0.0
    # >0: the detector's blur (Gaussian σ, detector mm) that the frames' path lengths carry; L_occ on the frames
    # then compares the rendering blurred alike (0: off; 0.3 was far worse on realistic trees: RESULTS §33d)
    frame_blur_sigma_mm: float = 0.0
    # >0: L_occ weighs a mask pixel by (median radius / its vessel's radius)^this, the mask's mean weight 1
    # (thin_weights.py: a thin vessel's few pixels otherwise weigh little; 0: off, every pixel alike; 1: LAD level,
    # RCA lower, the thin stretches lost about as often: RESULTS §65)
    thin_vessel_weight_power: float = 0.0
    # >0: where the frames are read as evidence (frame_evidence), L_geo, L_occ and the finishing steps read
    # the masks less the border pixels whose path length on the frame (smoothed over a pixel) is below this
    # (mm); the support stays on the masks as given (0: off; 0.3 better on the LAD suites, level on RCA,
    # worse on 721A: RESULTS §56c)
    frame_trim_mask_mm: float = 0.0
    # >0: the trim's threshold is lowered to this fraction of the path length at the nearest centreline
    # pixel where that is less (thin vessels keep their border; evidence.border_trimmed_mask; 0: off; with
    # trim 0.4 and 0.3: LAD +3.3, RCA +0.3, 721A −1.9: RESULTS §57c)
    frame_trim_centre_fraction: float = 0.0
    # weight of L_bin (losses.partial_occupancy_loss), the field's mass at partial occupancy; 0: off
    lambda_binary: float = 0.0


@dataclass
class RegionSettings:
    """Where the field is evaluated, and what of it becomes the result."""

    support: str = "full"  # "full": every voxel; "hull": the masks' visual hull widened by the margin
    support_margin_mm: float = 0.5
    # how far beyond the part every view sees the support follows a single view (hull.support_mask) off a view's
    # detector (behind its collimator: frames_unseen_reach_mm)
    one_view_reach_mm: float = 15.0
    threshold: float = 0.5  # segmentation = occupancy ≥ threshold
    # 0: off. Otherwise, after pruning and the fragment steps, the segmentation also takes the voxels
    # ≥ grow_threshold 26-connected to it (hysteresis; their occupancy is raised to the threshold): a
    # vessel thinner than a voxel comes out of the fit as partial occupancy, which one threshold breaks
    grow_threshold: float = 0.0
    prune: bool = False  # remove the skeleton pieces no mask pixel needs (pruning.py)
    prune_piece_mm: float = 6.0
    prune_tolerance: float = 0.02
    # prune only where the pieces left of a component stay one part (a ghost spur is peeled from its tip;
    # a tube's stretch that other vessels cover in both views is not cut out)
    prune_keep_connected: bool = False
    # judge keep_connected on each skeleton piece's 26-connected parts (pruning.parts_of_pieces): a piece in two parts
    # makes the pieces' graph join voxels that do not touch, and a cut can then pass for whole (prune_last always splits)
    prune_split_pieces: bool = False
    # remove the detached fragments that some view does not need (pruning.unconfirmed_fragments) ...
    drop_unconfirmed_fragments: bool = False
    # ... then join the remaining fragments to the tree along short paths of the field (connectivity.py)
    reconnect: bool = False
    reconnect_max_gap_mm: float = 8.0  # longest gap a bridge may cross (inside the support)
    # lowest geometric-mean occupancy along the gap; 0: none asked, the support (both views show vessel
    # there) and the gap's length decide (σ(−α·s) is nearly binary, so a gap's occupancy tells little: RESULTS §19)
    reconnect_min_occupancy: float = 0.0
    # false: fragments join the largest component only; true: then each component still apart in turn, largest
    # first, joins what it reaches (a second tree, a phantom's separate tubes, is mended too)
    reconnect_every_component: bool = False
    # 0: off. Otherwise, last, the skeleton pieces (prune_piece_mm) whose views see the vessel with
    # widths agreeing less than this (median of smaller / larger half-width, width_agreement.py) are
    # removed, each only where the rest of its component stays in one part (a ghost bridge is kept)
    width_agreement_min_ratio: float = 0.0
    # how each view's half-width map is read (width_agreement.py): "centreline", the distance map at the nearest
    # skeleton pixel; "thickness", the mask's local thickness (a free end's cap reads the vessel behind it);
    # "open_ends", the centreline's, unread at a skeleton end's cap; "axis", the distance to the mask's edge read at the
    # projections of the segmentation's 3D skeleton (a vessel merged with a neighbour in one view reads its own width)
    width_agreement_measure: str = "centreline"
    # whose half-widths a voxel's agreement compares (width_agreement.AGREEMENT_VIEWS): "all" the views', or with three
    # views or more "best_pair", the best-agreeing pair's (one view's crossing vessel no longer removes a true one)
    width_agreement_views: str = "all"
    # 0: off. Otherwise, last, after min_fragment_volume_mm3's specks went, the fragments still apart are joined
    # to the tree once more (as reconnect does, inside the support) across gaps up to this many mm: growing brings
    # fragments closer. Fewer pieces for less clDice (bridges take the shortest supported path, not a missed
    # vessel's: RESULTS §32c)
    final_reconnect_max_gap_mm: float = 0.0
    # 0: off. Otherwise, after everything above but the final reconnection, the detached pieces (every component
    # but the largest) smaller than this many mm³ are removed (pruning.small_fragments): specks no step could join
    # to the tree, two in three off any true vessel
    min_fragment_volume_mm3: float = 0.0
    # after those specks went (before the final reconnection): where every view shows vessel the result does not
    # explain, the hull of those pixels is added (pieces whose views' widths disagree and short crossings left out),
    # joined to the tree through the field, and what stays apart dropped (unexplained_fill.py): the vessels the fit
    # never placed (RESULTS §97, §98; on in `fast`)
    fill_unexplained: bool = False
    # after all the steps above (before the final reconnection): pruning once more, as ``prune`` and
    # ``prune_keep_connected`` say. Growing, joining and the fill come after the first pruning and add pieces that
    # no mask pixel needs; each piece's parts apart, so a component is kept whole voxel by voxel. With motion it removes
    # true vessel the corrected views still disagree on (9 of 10 cases lower, by 0.3–2.0: RESULTS §98): `fast` prunes last
    # only where the views were found aligned (prune_last_only_without_motion) or are three or more
    prune_last: bool = False
    # with prune_last: prune last only where the frames' pose check (calibrate_from_frames) searched every view and
    # found no motion beyond what noise allows; skipped where it found one (the corrected views still disagree by
    # about a millimetre), could not tell, or did not run (no frames): there it is not known that the views agree
    prune_last_only_without_motion: bool = False
    # ... but with at least this many views, prune last whatever the check found: the third view keeps what two
    # misaligned views would let the cover remove (three views with motion +0.6 / +0.8, clean level / +0.3: RESULTS §99e–g).
    # 0: no exception
    prune_last_min_views_any_motion: int = 0
    # 0: off. Otherwise, at this share of the steps, the pieces that width check would remove from the
    # fit's segmentation so far are taken out of the field for the rest of the fit, so that the fit may
    # explain their mask pixels elsewhere (with width_agreement_min_ratio 0, the check off, nothing is taken out)
    width_exclusion_fraction: float = 0.0
    width_exclusion_repeats: int = 1  # how many times, the later ones evenly spaced between it and the end
    # at those steps, also take out what pruning and the fragment check (prune, drop_unconfirmed_fragments)
    # would remove from the fit's segmentation, so the fit may re-place their pixels too; false: the width check's
    # alone (taken out so early, thin true stretches are lost: RESULTS §32a)
    exclusion_takes_finishing_removals: bool = False
    # where the X-ray frames are given: a pixel the frame cannot show a vessel in (masks.unseen_pixels: collimator,
    # clipped, the filters' margin along the image edge) and the mask leaves empty is unknown, not background: the
    # losses (L_occ, L_geo), the fragment and width checks and the reprojection QA leave it out, and the support
    # follows the other views there only frames_unseen_reach_mm. Off: level on the collimated suites (RESULTS §90)
    frames_unseen_unknown: bool = False
    # with frames_unseen_unknown (and frames): how far beyond the part every view sees the support follows a single view,
    # in place of one_view_reach_mm; one view cannot place a vessel in depth, and 4 or 15 mm let the fit put ghosts
    # there that took the mask pixels of true vessels (RESULTS §90)
    frames_unseen_reach_mm: float = 0.0


#: a calibration candidate's score is its mean loss over this many last steps (Adam's steps are noisy)
CALIBRATION_SCORE_STEPS = 20


@dataclass
class CalibrationSettings:
    """Search of each view's observable rigid motion before the reconstruction (``calibration.py``)."""

    # where the frames are given: the motion between the views that their line integrals' epipolar
    # consistency observes (line_integral_consistency.py; every pair at once with 3+ views; seconds, no re-fit)
    calibrate_from_frames: bool = False
    # ... and applied only where the motion found divides the views' inconsistency by at least this: without
    # motion, noise in the segmented masks lets the search divide it by up to 1.4 with spurious turns that
    # cost clDice; simulated motions (up to 3 mm / 2°) divide it by 2.4–114 on 18 of 20 cases (RESULTS §20). 1: always
    calibration_min_consistency_gain: float = 2.0
    # ... comparing only the epipolar planes on which no vessel runs into a view's collimator, clipped part or image
    # edge (their integrals miss what the view cannot see). On collimated static pairs every plane let the search turn
    # two views of twenty by 3–3.8° that were not there (−44, −43 clDice points); skipping the truncated planes stops
    # that, but with motion it found poses that scored lower on 14 of 20 cases (RESULTS §91): off, measured
    calibration_skip_truncated_planes: bool = False
    # ... and, searched on every plane, applied only where the motion found also divides the inconsistency by at least
    # this on the planes no such vessel lies on (two views; a turn that hides what a collimator cuts makes them no more
    # consistent: 0.50× and 0.91× on the two spurious static turns, 2.0–66× where the views moved, RESULTS §93). 0: off
    calibration_min_untruncated_gain: float = 1.5
    calibrate: bool = False  # the search by re-fitting the field per candidate pose (minutes per view)
    calibration_range_mm: float = 4.0  # shift candidates within ± this
    # rotation candidates within ± this; 0 (the default) searches the shift only: on masks segmented from
    # images the re-fitted loss does not locate rotations (bench/RESULTS.md, section 12c)
    calibration_rotation_range_deg: float = 0.0
    calibration_candidates: int = 5  # evenly over the range, then two between the best and its neighbours
    calibration_steps: int = 150  # the re-fit per candidate


@dataclass
class RunSettings:
    """What to run and where."""

    preset: str = "paper"
    mode: str = DEFAULT_MODE
    seed: int = 0
    device: str = "auto"  # "auto" | "cpu" | "cuda" | "cuda:N"
    memory_check: bool = True  # refuse CPU runs whose estimated peak exceeds the available memory
    threads: Optional[int] = None  # CPU threads for torch; None: torch's default


GROUPS: Dict[str, type] = {
    "field": FieldSettings, "optimisation": OptimisationSettings, "loss": LossSettings,
    "region": RegionSettings, "calibration": CalibrationSettings, "run": RunSettings,
}


def _field_types(cls: type) -> Dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


#: every setting's key → (its group, its type)
SETTING_KEYS: Dict[str, Tuple[str, Any]] = {
    key: (group, kind) for group, cls in GROUPS.items() for key, kind in _field_types(cls).items()
}


@dataclass
class Settings:
    field: FieldSettings = dataclasses.field(default_factory=FieldSettings)
    optimisation: OptimisationSettings = dataclasses.field(default_factory=OptimisationSettings)
    loss: LossSettings = dataclasses.field(default_factory=LossSettings)
    region: RegionSettings = dataclasses.field(default_factory=RegionSettings)
    calibration: CalibrationSettings = dataclasses.field(default_factory=CalibrationSettings)
    run: RunSettings = dataclasses.field(default_factory=RunSettings)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "Settings":
        """Settings from flat keys (``to_dict``'s form); unknown keys are an error."""
        unknown = sorted(set(values) - set(SETTING_KEYS))
        if unknown:
            raise ReconstructionError(f"unknown setting(s): {', '.join(unknown)}; known: {', '.join(sorted(SETTING_KEYS))}")
        grouped: Dict[str, Dict[str, Any]] = {group: {} for group in GROUPS}
        for key, value in values.items():
            grouped[SETTING_KEYS[key][0]][key] = checked_setting_value(key, value, SETTING_KEYS[key][1])
        return cls(**{group: GROUPS[group](**kw) for group, kw in grouped.items()})

    def to_dict(self) -> Dict[str, Any]:
        """Every setting by its key (flat), as ``report.json`` and the job folders store them."""
        out: Dict[str, Any] = {}
        for group in GROUPS:
            out.update(dataclasses.asdict(getattr(self, group)))
        return out

    def replace(self, **values: Any) -> "Settings":
        """A copy with some settings changed, by key."""
        return Settings.from_dict({**self.to_dict(), **values})

    @property
    def mode(self) -> Mode:
        return MODES[self.run.mode]

    def validate(self) -> None:
        """Raise ``ReconstructionError`` naming the first setting out of range and its range."""
        f, o, l, r, run = self.field, self.optimisation, self.loss, self.region, self.run
        if run.preset not in PRESETS:
            raise ReconstructionError(f"unknown preset {run.preset!r}; choose one of {', '.join(PRESETS)}")
        if run.mode not in MODES:
            raise ReconstructionError(f"unknown mode {run.mode!r}; choose one of {', '.join(MODES)}")
        if r.support not in SUPPORTS:
            raise ReconstructionError(f"support must be 'hull' or 'full', got {r.support!r}")
        if o.steps < 1:
            raise ReconstructionError(f"steps must be at least 1, got {o.steps}")
        check_seed(run.seed)
        for name, value, low, high in (("levels", f.levels, 1, 64), ("features_per_level", f.features_per_level, 1, 64),
                                       ("log2_table_size", f.log2_table_size, 1, 30),
                                       ("base_resolution", f.base_resolution, 1, 1 << 16),
                                       ("max_resolution", f.max_resolution, f.base_resolution, 1 << 16),
                                       ("width", f.width, 1, 1 << 14), ("depth", f.depth, 1, 256)):
            if not low <= value <= high:
                raise ReconstructionError(f"{name} is a size of the field's network, a whole number from {low} to {high}, "
                                          f"got {value}")
        for name, value in (("learning_rate", o.learning_rate), ("alpha", f.alpha),
                            ("silhouette_length_mm", l.silhouette_length_mm)):
            if not value > 0:
                raise ReconstructionError(f"{name} must be positive, got {value}")
        for name, value in (("lambda_geo", l.lambda_geo), ("lambda_occ", l.lambda_occ),
                            ("lambda_occ_frames", l.lambda_occ_frames), ("lambda_binary", l.lambda_binary),
                            ("lambda_occ_masks_with_frames", l.lambda_occ_masks_with_frames)):
            if not value >= 0:
                raise ReconstructionError(f"{name} is a loss weight and must not be negative, got {value}")
        if not l.frame_trim_mask_mm >= 0:
            raise ReconstructionError(f"frame_trim_mask_mm is a path length in mm (0: off), got {l.frame_trim_mask_mm}")
        if not 0 <= l.dt_tolerance_mm < l.dt_truncation_mm:
            raise ReconstructionError(f"dt_tolerance_mm is a distance in mm from 0 (off) up to dt_truncation_mm "
                                      f"({l.dt_truncation_mm:g}), got {l.dt_tolerance_mm}")
        if not 0 <= l.frame_trim_centre_fraction < 1:
            raise ReconstructionError(f"frame_trim_centre_fraction is a fraction in [0, 1) (0: off), got {l.frame_trim_centre_fraction}")
        if not 0 < l.frame_evidence_until_fraction <= 1:
            raise ReconstructionError(f"frame_evidence_until_fraction is the share of the steps that fit the frames, in (0, 1] "
                                      f"(1: every step; frame_evidence=false fits none), got {l.frame_evidence_until_fraction}")
        if not (l.frame_excess_factor == 0 or l.frame_excess_factor >= 1):
            raise ReconstructionError(f"frame_excess_factor is how many times the frame's path length a ray may cross "
                                      f"before it costs: at least 1, or 0 (off: L_occ fits the frames' path lengths), "
                                      f"got {l.frame_excess_factor}")
        if not (isinstance(l.frame_evidence_reach_px, int) and l.frame_evidence_reach_px >= 0):
            raise ReconstructionError(f"frame_evidence_reach_px is how many pixels beyond the masks the frames' path lengths "
                                      f"are kept, a whole number from 0, got {l.frame_evidence_reach_px!r}")
        if not (isinstance(l.frame_deblur_iterations, int) and 0 <= l.frame_deblur_iterations <= 50):
            raise ReconstructionError(f"frame_deblur_iterations is how many Richardson–Lucy steps restore the frames' path "
                                      f"lengths against the detector's blur, a whole number from 0 (off) to 50, got "
                                      f"{l.frame_deblur_iterations!r}")
        if not l.frame_excess_tolerance_mm >= 0:
            raise ReconstructionError(f"frame_excess_tolerance_mm is a path length in mm, 0 or more, got "
                                      f"{l.frame_excess_tolerance_mm}")
        if not l.thin_vessel_weight_power >= 0:
            raise ReconstructionError(f"thin_vessel_weight_power is the power of the thin vessels' weight in L_occ, 0 (off) "
                                      f"or more, got {l.thin_vessel_weight_power}")
        if not l.frame_blur_sigma_mm >= 0:
            raise ReconstructionError(f"frame_blur_sigma_mm is a detector blur in mm (0: off), got {l.frame_blur_sigma_mm}")
        if o.table_learning_rate is not None and not o.table_learning_rate > 0:
            raise ReconstructionError(f"table_learning_rate must be positive or none, got {o.table_learning_rate}")
        if l.dt_downsample < 1:
            raise ReconstructionError("dt_downsample must be at least 1")
        if o.warmup_steps < 0 or o.checkpoint_points < 0:
            raise ReconstructionError("warmup_steps and checkpoint_points must not be negative")
        if not 0 <= o.alpha_ramp_fraction <= 1:
            raise ReconstructionError(f"alpha_ramp_fraction is the share of the steps over which α rises from alpha_start: "
                                      f"0 (off) up to 1, got {o.alpha_ramp_fraction}")
        if o.alpha_ramp_fraction > 0 and not 0 < f.alpha_start <= f.alpha:
            raise ReconstructionError(f"alpha_start must be positive and at most alpha ({f.alpha:g}) for α to rise to it, "
                                      f"got {f.alpha_start}")
        if not 0 <= o.revive_fraction < 1:
            raise ReconstructionError(f"revive_fraction is the share of the steps after which saturated voxels under unexplained "
                                      f"mask pixels are revived: 0 (off) up to below 1, got {o.revive_fraction}")
        if not 0 < o.revive_occupancy < 0.5:
            raise ReconstructionError(f"revive_occupancy is the occupancy a revived voxel starts again at: above 0 and "
                                      f"below 0.5 (the threshold's side of empty), got {o.revive_occupancy}")
        if not 0 <= o.average_last_fraction < 1:
            raise ReconstructionError(f"average_last_fraction is the share of the last steps whose parameters are averaged "
                                      f"into the result: 0 (off) up to below 1, got {o.average_last_fraction}")
        if o.ensemble_fits < 1:
            raise ReconstructionError(f"ensemble_fits is how many fits the result is made from: at least 1 (one fit), "
                                      f"got {o.ensemble_fits}")
        if o.ensemble_combine not in ENSEMBLE_COMBINES:
            raise ReconstructionError(f"ensemble_combine is how the fits make the result: "
                                      f"{' or '.join(repr(c) for c in ENSEMBLE_COMBINES)}, got {o.ensemble_combine!r}")
        if not 0 <= o.coarse_to_fine_fraction < 1:
            raise ReconstructionError(f"coarse_to_fine_fraction is the share of the steps over which the finer levels "
                                      f"fade in: 0 (off) up to below 1, got {o.coarse_to_fine_fraction}")
        if not r.prune_piece_mm > 0 or not 0 <= r.prune_tolerance < 1:
            raise ReconstructionError("prune_piece_mm must be positive and prune_tolerance in [0, 1)")
        if not r.prune_last_min_views_any_motion >= 0:
            raise ReconstructionError(f"prune_last_min_views_any_motion must be 0 (no exception) or a number of views, got "
                                      f"{r.prune_last_min_views_any_motion}")
        if not r.reconnect_max_gap_mm > 0:
            raise ReconstructionError(f"reconnect_max_gap_mm must be a positive length in mm (default 8), got "
                                      f"{r.reconnect_max_gap_mm}; or turn reconnection off with reconnect=false")
        if not r.final_reconnect_max_gap_mm >= 0:
            raise ReconstructionError(f"final_reconnect_max_gap_mm must be 0 (off) or a gap in mm, got {r.final_reconnect_max_gap_mm}")
        if not r.min_fragment_volume_mm3 >= 0:
            raise ReconstructionError(f"min_fragment_volume_mm3 must be 0 (off) or a volume in mm³ below which the detached "
                                      f"pieces are removed, got {r.min_fragment_volume_mm3}")
        if not 0 <= r.reconnect_min_occupancy < 1:
            raise ReconstructionError(
                f"reconnect_min_occupancy must be an occupancy in [0, 1) (default 0: the support and the gap's length "
                f"decide), got {r.reconnect_min_occupancy}")
        if not 0 < r.threshold < 1:
            raise ReconstructionError(f"threshold must be between 0 and 1, got {r.threshold}")
        for name, default in (("one_view_reach_mm", RegionSettings.one_view_reach_mm),
                              ("frames_unseen_reach_mm", RegionSettings.frames_unseen_reach_mm)):
            value = getattr(r, name)  # finite already (every number setting is checked so)
            if value < 0:
                raise ReconstructionError(f"{name} is how far (mm) the support follows a single view beyond the part "
                                          f"every view sees: 0 or more (default {default:g}), got {value}")
        if not 0 <= r.grow_threshold <= r.threshold:
            raise ReconstructionError(f"grow_threshold must be 0 (off) or an occupancy up to threshold ({r.threshold:g}), "
                                      f"got {r.grow_threshold}")
        if r.width_agreement_views not in ("all", "best_pair"):
            raise ReconstructionError(f"width_agreement_views is whose half-widths a voxel's width check compares: 'all' "
                                      f"(every view's) or 'best_pair' (with three views or more, the best-agreeing "
                                      f"pair's), got {r.width_agreement_views!r}")
        if r.width_agreement_measure not in ("centreline", "thickness", "open_ends", "axis"):
            raise ReconstructionError(f"width_agreement_measure is how the masks' half-widths are read: 'centreline', "
                                      f"'thickness', 'open_ends' or 'axis', got {r.width_agreement_measure!r}")
        if not 0 <= r.width_agreement_min_ratio < 1:
            raise ReconstructionError(f"width_agreement_min_ratio must be 0 (off) or an agreement of the views' widths "
                                      f"below 1 (smaller / larger), got {r.width_agreement_min_ratio}")
        if not 0 <= r.width_exclusion_fraction < 1:
            raise ReconstructionError(f"width_exclusion_fraction is the share of the steps after which the pieces the "
                                      f"views' widths disagree on are taken out of the fit: 0 (off) up to below 1, got "
                                      f"{r.width_exclusion_fraction}")
        if r.width_exclusion_repeats < 1:
            raise ReconstructionError(f"width_exclusion_repeats must be at least 1, got {r.width_exclusion_repeats}")
        if run.device not in DEVICES and not str(run.device).startswith("cuda:"):
            raise ReconstructionError(f"device must be auto, cpu or cuda, got {run.device!r}")
        cal = self.calibration
        if (not cal.calibration_range_mm > 0 or not cal.calibration_rotation_range_deg >= 0
                or cal.calibration_candidates < 3 or cal.calibration_steps < CALIBRATION_SCORE_STEPS):
            raise ReconstructionError(
                f"calibration needs calibration_range_mm > 0, calibration_rotation_range_deg ≥ 0, calibration_candidates ≥ 3 "
                f"and calibration_steps ≥ {CALIBRATION_SCORE_STEPS}; got {cal.calibration_range_mm}, "
                f"{cal.calibration_rotation_range_deg}, {cal.calibration_candidates}, {cal.calibration_steps}")
        if not cal.calibration_min_consistency_gain >= 1:
            raise ReconstructionError(
                f"calibration_min_consistency_gain must be at least 1 (default 2: the found motion must halve the views' "
                f"inconsistency; 1 applies whatever is found), got {cal.calibration_min_consistency_gain}")
        if not (math.isfinite(cal.calibration_min_untruncated_gain) and cal.calibration_min_untruncated_gain >= 0):
            raise ReconstructionError(
                "calibration_min_untruncated_gain must be 0 (no check) or more (default 1.5: the motion found must make "
                "the epipolar planes no collimator cuts 1.5× more consistent too), got "
                f"{cal.calibration_min_untruncated_gain}")
        if run.threads is not None and run.threads < 1:
            raise ReconstructionError(f"threads must be at least 1, got {run.threads}")


# --- presets ----------------------------------------------------------------------------------------
#: preset → the settings that differ from the published recipe (the defaults above)
PRESETS: Dict[str, Dict[str, Any]] = {  # the default first: lists offer it first
    "fast": dict(
        # the field only where both masks see vessel (elsewhere the masks already demand 0)
        support="hull",
        # a CPU cannot afford 8 × 256 on every voxel; the hash table holds the spatial detail
        levels=8, log2_table_size=17, width=64, checkpoint_points=0,
        # 400 steps converge only with the table at 1e-2; the MLP at 1e-3 (α = 50 amplifies its
        # output layer's steps), both warmed up so that Adam's first steps do not saturate σ(−α·s)
        steps=400, learning_rate=1e-3, table_learning_rate=1e-2, warmup_steps=20,
        # the finer hash levels faded in over the first half: the fit settles the tree's course before its
        # detail, and leaves it in fewer pieces (bench/RESULTS.md §27c, §28a)
        coarse_to_fine_fraction=0.5,
        dt_downsample=2,
        # two views cannot rule out ghost branches: drop the pieces no mask pixel needs, but only where the
        # component stays one part (a tube's stretch that other tubes cover in both views is not cut out: suites level,
        # the real XA pair in 31 pieces instead of 56 and more of each mask explained, bench/RESULTS.md §78)
        prune=True,
        prune_keep_connected=True,
        # then drop the detached fragments that not every view confirms (ghosts of pixels one view cannot place)
        drop_unconfirmed_fragments=True,
        # and join the rest to the tree across short gaps inside the support (both views show vessel there), then
        # each component still apart in turn, so that a second tree or tube is mended too (§78: the real pair 31 → 19 pieces)
        reconnect=True,
        reconnect_every_component=True,
        # then take in the partial occupancy connected to what was kept: vessels thinner than a voxel
        grow_threshold=0.3,
        # last, drop the pieces whose two views see different widths (where two vessels' rays cross),
        # unless that cuts the tree (bench/RESULTS.md §29b)
        width_agreement_min_ratio=0.7,
        # with three views or more, of the best-agreeing pair of views: a true vessel crossed by another in one view
        # was removed as a ghost (three views, realistic static cases 0–9: clDice higher on 19 of 20; clean, cases 0–4:
        # 7 of 10, +7.4 / +2.1; RESULTS §95e, §96b)
        width_agreement_views="best_pair",
        # and already at 60 % of the steps, so that the rest of the fit explains those pieces' mask pixels
        # elsewhere: a ghost removed at the end leaves its vessel missing, removed here it is often re-placed
        # on its true course (bench/RESULTS.md §30)
        width_exclusion_fraction=0.6,
        # after all the steps above, the detached specks below 16 mm³ that nothing joined to the tree: two in three
        # of them ghosts; clDice level, the realistic and clean suites in 1.4–1.9 pieces instead of 2.0–8.2 (§58)
        min_fragment_volume_mm3=16.0,
        # then, where both views show vessel the result leaves unexplained, the hull of those pixels filled in (width-
        # and length-checked, joined to the tree, never more pieces): the vessels the fit never placed (§97c–d, §98)
        fill_unexplained=True,
        # then pruning once more, where the frames' pose check found the views aligned: growing, joining and the fill
        # add pieces no mask pixel needs (realistic static, two views: LAD +0.9, RCA +0.9, 18 of 20 cases better; three
        # views +0.8 / +1.1 on cases 0–4; RESULTS §99); not where it found motion (the corrected views still disagree:
        # 9 of 10 cases lower, §98e) or could not tell (masks alone: the clean suites and the demo as before)
        prune_last=True,
        prune_last_only_without_motion=True,
        # except with three views or more, where it won with motion and on clean masks too (§99e–g)
        prune_last_min_views_any_motion=3,
        # the result is the mean of the parameters over the last fifth of the steps (after that exclusion), not
        # Adam's last jittering iterate: clDice level, Dice higher and fewer pieces over six suite runs (§37b, §38c)
        average_last_fraction=0.2,
        # where the frames come with the masks, fit the path lengths they show (ghosts add path the frame lacks)
        frame_evidence=True,
        # on the masks' pixels only: the blurred rim beyond them asked for vessel the masks refuse (clDice level
        # to higher, Dice higher over two draws of both static suites, 3D-QCA sections narrower: §62d–e)
        frame_evidence_reach_px=0,
        # and correct the motion between the views that two views observe, read off the same frames
        calibrate_from_frames=True,
    ),
    "paper": {},
}
# `fast`'s method fitted three times from different seeds, the result made from the mean occupancy: 1–2 clDice
# points better than one fit on the realistic and the clean suites (bench/RESULTS.md §51); keeping instead the fit
# that reprojects best (ensemble_combine "best_reprojection") won on clean masks and lost on realistic ones (§75b).
# Three times the fit's time — seconds on a GPU, minutes on a CPU
PRESETS["ensemble"] = {**PRESETS["fast"], "ensemble_fits": 3}
DEFAULT_PRESET = "fast"


def make_settings(preset: str = DEFAULT_PRESET, **overrides: Any) -> Settings:
    """Settings of a preset with any setting overridden by key (None values are ignored); validated."""
    if preset not in PRESETS:
        raise ReconstructionError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    values = dict(PRESETS[preset])
    values.update({k: v for k, v in overrides.items() if v is not None and k != "preset"})
    values["preset"] = preset
    settings = Settings.from_dict(values)
    settings.validate()
    return settings


def settings_from_values(values: Dict[str, Any]) -> Settings:
    """Settings as the jobs and ``reconstruct`` take them in a dict: a ``preset`` (default ``fast``) and the settings it
    changes by key; validated."""
    if not isinstance(values, Mapping):
        raise ReconstructionError(f"the settings are a dict of setting keys and values, e.g. {{'preset': 'fast', "
                                  f"'steps': 200}} ({{}} for the fast preset as it is), got {type(values).__name__}")
    values = dict(values)
    return make_settings(values.pop("preset", DEFAULT_PRESET), **values)


def setting_help(exclude: Iterable[str] = ()) -> str:
    """One line per setting key with its default, for ``--help``; ``exclude``: the keys a command sets by its own flags."""
    defaults = Settings().to_dict()
    excluded = set(exclude)
    lines = []
    for group in GROUPS:
        keys = [k for k, (g, _) in SETTING_KEYS.items() if g == group and k not in excluded]
        lines.append(f"{group}: " + ", ".join(f"{k}={defaults[k]}" for k in keys))
    return "; ".join(lines)


def parse_setting_overrides(items: Optional[Sequence[str]], reserved: Optional[Mapping[str, str]] = None) -> Dict[str, Any]:
    """``["learning_rate=1e-3", "memory_check=false"]`` (command-line ``--set``) → typed overrides.

    Each value is read as its setting's declared type. ``reserved`` maps the settings that the
    caller sets itself to the option to use instead.
    """
    reserved = reserved or {}
    out: Dict[str, Any] = {}
    for item in items or ():
        key, sep, text = str(item).partition("=")
        key = key.strip()
        if not sep or not key:
            raise ReconstructionError(f"--set {item!r}: write KEY=VALUE, e.g. --set learning_rate=1e-3")
        if key in reserved:
            raise ReconstructionError(f"--set {key}=…: {key} is set by this command; {reserved[key]}")
        if key not in SETTING_KEYS:
            known = ", ".join(sorted(set(SETTING_KEYS) - set(reserved) - {"preset"}))
            raise ReconstructionError(f"--set {key}=…: unknown setting {key!r}; known: {known}")
        out[key] = typed_setting_value(key, text.strip(), SETTING_KEYS[key][1])
    return out


#: the seeds a run takes: numpy's legacy seeding (np.random.seed, as the fit seeds it) takes no more
MAX_SEED = 2**32 - 1


def check_seed(seed: int) -> None:
    """Refuse a seed the fit could not use (torch and numpy would fail only in the worker, after the setup)."""
    if not 0 <= seed <= MAX_SEED:
        raise ReconstructionError(f"seed must be a whole number from 0 to {MAX_SEED} (2**32 - 1), got {seed}: choose one "
                                  "in that range")


def checked_setting_value(key: str, value: Any, kind: Any) -> Any:
    """``value`` as a Python value of ``kind`` (bool, int, float, str, or Optional of one), from a script, a job's
    settings or a JSON file; anything else is refused by name. Text is not read as a number or a switch here: a
    text box's "false" would otherwise switch a setting on (``typed_setting_value`` reads ``--set``'s text)."""
    import numbers

    base, optional = _base_type(kind)
    if value is None:
        if optional:
            return None
        raise ReconstructionError(f"setting {key} needs a value ({base.__name__}), got None")
    shown = f"{value!r} ({type(value).__name__})"
    is_bool = isinstance(value, bool) or type(value).__name__ in ("bool", "bool_")  # numpy's too, not importing it
    if base is bool:
        if is_bool:
            return bool(value)
        raise ReconstructionError(f"setting {key} is a switch: give True or False, got {shown}")
    if base is int:
        if is_bool:
            raise ReconstructionError(f"setting {key} takes a whole number, got {shown}")
        if isinstance(value, numbers.Integral):  # exactly: float() of a large one rounds, and overflows past 1e308
            number = int(value)
        elif isinstance(value, numbers.Real) and math.isfinite(float(value)) and float(value) == int(value):
            number = int(value)
        else:
            raise ReconstructionError(f"setting {key} takes a whole number, got {shown}")
        if key == "seed":
            check_seed(number)
        return number
    if base is float:
        if not is_bool and isinstance(value, numbers.Real):
            if not math.isfinite(float(value)):
                raise ReconstructionError(f"setting {key} must be a finite number, got {shown}")
            return float(value)
        raise ReconstructionError(f"setting {key} takes a number, e.g. 1e-3, got {shown}")
    if base is str:
        if isinstance(value, str):
            return value
        raise ReconstructionError(f"setting {key} takes a name (text), got {shown}")
    return value


def _base_type(kind: Any) -> Tuple[Any, bool]:
    """(X, whether None is allowed) of a setting's declared type X or Optional[X]."""
    optional = typing.get_origin(kind) is typing.Union and type(None) in typing.get_args(kind)
    return (next(a for a in typing.get_args(kind) if a is not type(None)) if optional else kind), optional


def typed_setting_value(key: str, text: str, kind: Any) -> Any:
    """The text of ``--set key=text`` as ``kind`` (bool, int, float, str, or Optional of one)."""
    base, optional = _base_type(kind)
    lowered = text.lower()
    if lowered in ("none", "null"):
        if optional:
            return None
        raise ReconstructionError(f"--set {key}={text}: {key} needs a value ({base.__name__})")
    if base is bool:
        if lowered in ("true", "1", "yes", "on"):
            return True
        if lowered in ("false", "0", "no", "off"):
            return False
        raise ReconstructionError(f"--set {key}={text}: {key} takes true or false")
    if base is int:
        try:
            number = float(text)
        except ValueError:
            number = math.nan
        if not (math.isfinite(number) and number == int(number)):
            raise ReconstructionError(f"--set {key}={text}: {key} takes a whole number")
        return int(number)
    if base is float:
        try:
            number = float(text)
        except ValueError:
            raise ReconstructionError(f"--set {key}={text}: {key} takes a number, e.g. 1e-3") from None
        if not math.isfinite(number):
            raise ReconstructionError(f"--set {key}={text}: {key} must be finite")
        return number
    return text.strip("'\"")


# --- protocols --------------------------------------------------------------------------------------
#: a simulated view's mask is its line integral above this path length (mm): fainter shadows
#: are too faint to segment
MASK_THRESHOLD_MM = 0.2

#: the paper's grid and detector (NeCA / SDF-CAR): 128³ voxels of 0.8 mm, 512² pixels of 0.278 mm
PAPER_VOLUME_SHAPE: Tuple[int, int, int] = (128, 128, 128)
PAPER_SPACING_MM = 0.8
PAPER_DETECTOR_SHAPE: Tuple[int, int] = (512, 512)
PAPER_DETECTOR_SPACING_MM = 0.278

#: benchmark protocol → (view pair of ``geometry.VIEW_PAIRS``, target kind)
PROTOCOLS: Dict[str, Tuple[str, str]] = {
    "paper": ("paper", "line_integral"),
    "clinical-lao30-rao30": ("lao30-rao30", "mask"),
    "clinical-lao50cra25-rao50cra25": ("lao50cra25-rao50cra25", "mask"),
    "clinical-lao30-rao30-cra30": ("lao30-rao30-cra30", "mask"),
    "realistic-lao30-rao30": ("lao30-rao30", "mask"),
    "realistic-lao50cra25-rao50cra25": ("lao50cra25-rao50cra25", "mask"),
    "realistic-static-lao30-rao30": ("lao30-rao30", "mask"),
    "realistic-static-lao50cra25-rao50cra25": ("lao50cra25-rao50cra25", "mask"),
    "realistic-lao30-rao30-cra30": ("lao30-rao30-cra30", "mask"),
    "realistic-static-lao30-rao30-cra30": ("lao30-rao30-cra30", "mask"),
    "realistic-display-lao30-rao30": ("lao30-rao30", "mask"),
    "realistic-static-display-lao30-rao30": ("lao30-rao30", "mask"),
    "realistic-static-collimated-lao30-rao30": ("lao30-rao30", "mask"),
}
#: the protocols whose masks are segmented from simulated angiograms (``realistic.py``), with the
#: object motion between the acquisitions; "static" ones have the same images without motion; "display"
#: ones the same frames processed for display (``display_processing.py``, DISP: no path lengths read); "collimated"
#: ones the same scene behind the collimator's shutters
REALISTIC_PROTOCOLS: Dict[str, Dict[str, Any]] = {
    "realistic-lao30-rao30": {"max_shift_mm": 3.0, "max_rotation_deg": 2.0},
    "realistic-lao50cra25-rao50cra25": {"max_shift_mm": 3.0, "max_rotation_deg": 2.0},
    "realistic-static-lao30-rao30": {"max_shift_mm": 0.0, "max_rotation_deg": 0.0},
    "realistic-static-lao50cra25-rao50cra25": {"max_shift_mm": 0.0, "max_rotation_deg": 0.0},
    "realistic-lao30-rao30-cra30": {"max_shift_mm": 3.0, "max_rotation_deg": 2.0},
    "realistic-static-lao30-rao30-cra30": {"max_shift_mm": 0.0, "max_rotation_deg": 0.0},
    "realistic-display-lao30-rao30": {"max_shift_mm": 3.0, "max_rotation_deg": 2.0, "display": True},
    "realistic-static-display-lao30-rao30": {"max_shift_mm": 0.0, "max_rotation_deg": 0.0, "display": True},
    # every frame behind shutters over 15 % of each side: part of the tree is seen by one view only
    "realistic-static-collimated-lao30-rao30": {"max_shift_mm": 0.0, "max_rotation_deg": 0.0, "collimator_fraction": 0.15},
}


# --- metrics ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Metric:
    key: str
    title: str
    unit: str  # "" for ratios in [0, 1]
    higher_is_better: bool
    table_scale: float = 1.0  # the benchmark tables print value × scale …
    table_decimals: int = 3  # … with this many decimals

    @property
    def table_header(self) -> str:
        if self.table_scale == 100.0:
            return f"{self.title} (%)"
        if self.table_scale != 1.0:
            return f"{self.title} (×{1 / self.table_scale:.0e})".replace("e-0", "e-")
        return f"{self.title} ({self.unit})" if self.unit else self.title


METRICS: Dict[str, Metric] = {m.key: m for m in (
    Metric("cldice", "clDice", "", True, 100.0, 2),
    Metric("tprec", "topology precision", "", True, 100.0, 2),
    Metric("tsens", "topology sensitivity", "", True, 100.0, 2),
    Metric("skeleton_dice", "skeleton-Dice", "", True, 100.0, 2),
    Metric("dice", "Dice", "", True, 100.0, 2),
    Metric("iou", "IoU", "", True, 100.0, 2),
    Metric("chamfer_l2_mm", "Chamfer-ℓ2", "mm", False, 1.0, 2),
    Metric("re_error", "reError", "", False, 1.0, 3),
    Metric("re_mse", "reMSE", "", False, 1e4, 2),
    Metric("reprojection_dice", "reprojection Dice", "", True, 100.0, 2),
    Metric("components", "connected components", "", False, 1.0, 0),
    Metric("largest_component_fraction", "largest component", "", True, 100.0, 1),
    Metric("components_label", "connected components of the truth", "", False, 1.0, 0),  # context for components
)}

#: the metrics of a reconstruction against a ground truth, in the order they are reported
GROUND_TRUTH_METRICS: List[str] = ["cldice", "skeleton_dice", "dice", "iou", "chamfer_l2_mm", "re_error", "re_mse",
                                   "components", "largest_component_fraction", "components_label"]
#: the six metrics of the paper's tables
PAPER_METRICS: Tuple[str, ...] = ("cldice", "dice", "iou", "re_error", "chamfer_l2_mm", "re_mse")
