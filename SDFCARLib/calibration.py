"""Rigid self-calibration: the observable part of each view's object motion, by search.

Why
    Views are acquired seconds apart; table, patient and heart move in between, and the nominal
    C-arm poses then disagree with the images by millimetres. The part of such a motion that moves
    view k's image *across* its epipolar lines with view 1 breaks the tree apart in 3D: the
    branches cannot meet on the visual hull, and a field fitted on the hull explains the masks
    measurably worse (bench/RESULTS.md, section 8: L_occ 2.4× higher at the nominal pose of a 3 mm
    motion, minimal at the true one). Motions that move the image *along* the epipolar lines move
    the tree in depth and leave the masks explained: two views cannot tell them, and they are left alone.

Method
    View 1 is the reference (the result stays in its frame). For view k, with d its viewing
    direction and n_k = d_1 × d_k / |d_1 × d_k|, the shift of its object along n_k is searched (the
    image moves across its epipolar lines) and, when ``calibration_rotation_range_deg`` > 0, then the
    rotation about d_k (the image turns in plane: across the lines by an amount that grows along
    them) and the rotation about m_k = d_k × n_k (the image tilts across the lines by depth); see
    ``search_axes``. Rotations turn about the reconstruction region's centre; they are searched on
    request only, because on masks segmented from images the re-fitted loss does not locate them
    (bench/RESULTS.md, section 12c). Each candidate becomes view k's object
    motion (composed with any the view already carries), the field is re-fitted from scratch on that
    pose's hull for ``calibration_steps`` steps, and the candidate's score is the mean loss of the
    last steps. An even grid of candidates is refined by one parabola (``search_1d``).
    Re-fitting is what makes the motion visible: optimised jointly by gradient with the field, the
    pose does not move (the field re-fits to any pose first; measured, section 8).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from .geometry import CArmView, Geometry, rotation_matrix
from .settings import CALIBRATION_SCORE_STEPS, CalibrationSettings


def epipolar_normal(reference: CArmView, view: CArmView) -> Optional[np.ndarray]:
    """Unit direction whose object translation moves ``view``'s image across its epipolar lines
    with ``reference``; None when the two views look along the same line (no epipolar geometry)."""
    normal = np.cross(reference.detector_direction, view.detector_direction)
    length = float(np.linalg.norm(normal))
    if length < math.sin(math.radians(5.0)):
        return None
    return normal / length


def shifted(view: CArmView, translation_mm: np.ndarray) -> CArmView:
    """``view`` with its object moved further by ``translation_mm`` (reference frame, LPS)."""
    return moved(view, np.zeros(3), translation_mm, np.zeros(3))


def moved(view: CArmView, rotation_deg: np.ndarray, translation_mm: np.ndarray, centre_mm: np.ndarray) -> CArmView:
    """``view`` with its object moved further: rotated by the vector ``rotation_deg`` about ``centre_mm``,
    then translated by ``translation_mm`` (reference frame, LPS), before the motion the view carries."""
    r0 = rotation_matrix(view.object_rotation_deg)
    r_new = rotation_matrix(rotation_deg)
    centre = np.asarray(centre_mm, float)
    # the new motion acts first: x → R0 (Rn (x − c) + c + tn) + t0
    total_translation = r0 @ (centre - r_new @ centre + np.asarray(translation_mm, float)) + np.asarray(view.object_translation_mm, float)
    total_rotation = np.degrees(Rotation.from_matrix(r0 @ r_new).as_rotvec())
    return view.with_object_motion(total_rotation, total_translation)


def search_axes(reference: CArmView, view: CArmView) -> Optional[Dict[str, np.ndarray]]:
    """The three motions of ``view``'s object the calibration searches, as unit vectors (LPS):
    the shift across the epipolar lines with ``reference`` (n), the rotation about ``view``'s viewing
    direction (its image turns in plane) and the rotation about its in-plane axis along the epipolar
    lines (m = d × n: the image tilts across them by depth). None without epipolar geometry."""
    normal = epipolar_normal(reference, view)
    if normal is None:
        return None
    direction = view.detector_direction / np.linalg.norm(view.detector_direction)
    along = np.cross(direction, normal)
    return {"shift": normal, "rotation_in_plane": direction, "rotation_tilt": along / np.linalg.norm(along)}


def parabola_minimum(xs: Sequence[float], ys: Sequence[float]) -> float:
    """The abscissa of the vertex of the parabola through three points; the best x when flat or concave."""
    (x0, x1, x2), (y0, y1, y2) = xs, ys
    denominator = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / denominator
    b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / denominator
    best = float(xs[int(np.argmin(ys))])
    if a <= 0:
        return best
    vertex = -b / (2 * a)
    return float(np.clip(vertex, min(xs), max(xs)))


@dataclass
class Calibration:
    """The corrected geometry and, per view after the first, what was searched and found."""

    geometry: Geometry
    views: List[Dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0
    warnings: List[str] = field(default_factory=list)

    method: str = "search of the observable rigid motion, re-fitted field per candidate"

    def report(self) -> Dict[str, Any]:
        return {"method": self.method, "views": self.views, "seconds": round(self.seconds, 1)}

    def motion_found(self) -> Optional[bool]:
        """True where a motion was found and applied to some view, False where every view after the first was
        searched and moved less than noise alone allows (its entry's ``motion_found`` False), None where that
        cannot be told (a view not searched or not measurable, or a search that does not say)."""
        return combined_motion_found([entry.get("motion_found") for entry in self.views])


def combined_motion_found(said: Sequence[Optional[bool]]) -> Optional[bool]:
    """True where any says a motion was found, False where all (at least one) say none was, None otherwise."""
    if any(found is True for found in said):
        return True
    return False if said and all(found is False for found in said) else None


#: what each searched parameter is called in the report and its unit
_PARAMETERS = (("shift", "mm"), ("rotation_in_plane", "deg"), ("rotation_tilt", "deg"))


def search_1d(loss_at: Callable[[float], float], half_range: float, candidates: int):
    """Minimise ``loss_at`` over [−half_range, half_range]: an even grid of ``candidates`` values, two
    more halfway to the best one's neighbours, one parabola through the best three.
    Returns (value, {candidate: loss}, whether the best lay at the range's end)."""
    grid = np.linspace(-half_range, half_range, candidates)
    step = float(grid[1] - grid[0])  # candidates ≥ 3 (Settings.validate)
    scores = {float(x): loss_at(float(x)) for x in grid}
    best = min(scores, key=scores.get)
    for x in (best - step / 2, best + step / 2):
        if abs(x) <= half_range + 1e-9:
            scores[float(x)] = loss_at(float(x))
    ordered = sorted(scores)
    best = min(scores, key=scores.get)
    i = ordered.index(best)
    if 0 < i < len(ordered) - 1:
        xs = ordered[i - 1:i + 2]
        return parabola_minimum(xs, [scores[x] for x in xs]), scores, False
    return best, scores, True


def pose_score(geometry: Geometry, targets: Sequence[np.ndarray], settings, target_kind: str, cancel=None) -> float:
    """A candidate pose's score: the mean loss of the last ``CALIBRATION_SCORE_STEPS`` steps of a field
    fitted from scratch for ``calibration_steps`` steps (lower: the views agree better)."""
    from .optimiser import fitted_loss

    # every level of the encoding from the first step: a candidate is scored by its last steps' loss, and
    # a short fit still fading its finer levels in scores a coarser field, which blurs the shift's minimum;
    # and nothing taken out of a candidate's field part way (its score is how well the whole field explains the views)
    short = settings.replace(steps=settings.calibration.calibration_steps, prune=False, reconnect=False,
                             coarse_to_fine_fraction=0.0, width_exclusion_fraction=0.0)
    return fitted_loss(geometry, targets, short, target_kind, CALIBRATION_SCORE_STEPS, cancel)


def calibrate(geometry: Geometry, targets: Sequence[np.ndarray], settings, target_kind: str,
              score: Optional[Callable[[Geometry], float]] = None, progress=None, cancel=None) -> Calibration:
    """Search each view's observable rigid motion against view 1 (module docstring).

    ``score(geometry)`` — lower is better — defaults to the loss of a short re-fit; tests pass their own.
    """
    from .optimiser import ReconstructionCancelled, _is_cancelled, _report

    c = settings.calibration
    t0 = time.perf_counter()
    if score is None:
        def score(candidate: Geometry) -> float:
            return pose_score(candidate, targets, settings, target_kind, cancel)

    views = list(geometry.views)
    centre = np.asarray(geometry.volume.center_mm, float)  # rotations turn the object about the region's centre
    found: List[Dict[str, Any]] = []
    warnings: List[str] = []
    half_ranges = {"mm": c.calibration_range_mm, "deg": c.calibration_rotation_range_deg}
    for k in range(1, len(views)):
        axes = search_axes(views[0], views[k])
        if axes is None:
            found.append({"view": k + 1, "skipped": "looks along the same line as view 1"})
            continue
        entry: Dict[str, Any] = {"view": k + 1, "rotation_centre_mm": [round(float(v), 3) for v in centre]}
        for name, unit in _PARAMETERS:
            if half_ranges[unit] <= 0:
                continue
            axis = axes[name]

            def candidate(value: float, axis=axis, unit=unit) -> CArmView:
                zero = np.zeros(3)
                return moved(views[k], value * axis if unit == "deg" else zero, value * axis if unit == "mm" else zero, centre)

            def loss_at(value: float, candidate=candidate, name=name, unit=unit) -> float:
                if _is_cancelled(cancel):
                    raise ReconstructionCancelled("cancelled during the calibration")
                trial = list(views)
                trial[k] = candidate(value)
                loss = float(score(Geometry(geometry.volume, trial)))
                # step/total are the run's (a progress bar shows them; the fit starts after this): the calibration's
                # own progress is calibration_step/calibration_total
                _report(progress, phase="calibrate", step=0, total=settings.optimisation.total_steps,
                        calibration_step=k, calibration_total=len(views) - 1, elapsed_s=time.perf_counter() - t0,
                        eta_s=None, device=str(settings.run.device),
                        message=f"view {k + 1}, {name.replace('_', ' ')} {value:+.2f} {unit} → loss {loss:.5f}")
                return loss

            value, scores, at_edge = search_1d(loss_at, half_ranges[unit], c.calibration_candidates)
            if at_edge:
                # the loss still falls at the end of the range: no minimum was found, and a motion at
                # the edge is more likely a wrong pose fitted to other errors (measured) than a real one
                warnings.append(f"view {k + 1}: the pose correction ({name.replace('_', ' ')}) found no minimum within "
                                f"±{half_ranges[unit]:g} {unit} (lowest loss at {value:+.2f} {unit}); that part was left "
                                "as given. Check the view's angles and distances, or widen the calibration range")
                value = 0.0
            views[k] = candidate(value)
            ordered = sorted(scores)
            entry[name] = {"value": round(value, 3), "unit": unit, "axis_lps": [round(float(v), 4) for v in axis],
                           "candidates": [round(x, 3) for x in ordered], "losses": [round(scores[x], 6) for x in ordered]}
        # what the view's object motion is now, and (for the shift) the keys reports had before rotations
        entry["object_rotation_deg"] = [round(float(v), 4) for v in views[k].object_rotation_deg]
        entry["object_translation_mm"] = [round(float(v), 4) for v in views[k].object_translation_mm]
        if "shift" in entry:
            entry.update(shift_mm=entry["shift"]["value"], direction_lps=entry["shift"]["axis_lps"])
        found.append(entry)
    return Calibration(Geometry(geometry.volume, views), found, time.perf_counter() - t0, warnings)


#: largest motion the frames' consistency may find; beyond it the pose is left as given (with a warning)
FRAME_CALIBRATION_LIMITS = {"deg": 4.0, "mm": 6.0}


def _rounded(value: float, digits: int) -> Optional[float]:
    """``value`` rounded for report.json; None where it is not a number (nothing was measured)."""
    return round(value, digits) if np.isfinite(value) else None


def calibrate_from_frames(geometry: Geometry, line_integrals: Sequence[np.ndarray], progress=None,
                          min_consistency_gain: float = CalibrationSettings.calibration_min_consistency_gain,
                          unseen: Optional[Sequence[Optional[np.ndarray]]] = None,
                          confirm_unseen: Optional[Sequence[Optional[np.ndarray]]] = None,
                          min_untruncated_gain: float = CalibrationSettings.calibration_min_untruncated_gain) -> Calibration:
    """Each view's object motion against view 1 from the epipolar consistency of the frames' vessel
    line integrals (``line_integral_consistency.py``), in seconds: with two views the three motions
    that pair observes; with three or more, all six of each view over every pair of views at once — or, where that
    joint search cannot be used (it ends at the end of its range, or a pair has too few untruncated planes), each
    view's three against one other view, the best-agreeing pair first, starting from view 1 (``estimate_motions``;
    the entry's ``matched_with`` and ``joint_search`` and a warning say which and why).

    A motion is applied only where it divides the inconsistency by ``min_consistency_gain`` or more;
    a smaller gain is what noise in the frames and masks alone allows the search (no motion to find).
    ``unseen``: per view None or a bool image, True where its frame cannot show a vessel (collimator, clipped or
    image edge, ``masks.unseen_pixels``): the epipolar planes through vessels that run into it are not compared.
    ``confirm_unseen`` (the same kind of images): a motion found for a view matched to view 1 alone is applied only
    where it also divides the inconsistency on the planes those vessels leave untruncated by ``min_untruncated_gain``
    (``line_integral_consistency.untruncated_gain``; a turn that hides what a collimator cuts makes them no more
    consistent); 0 or no images: not checked, nor where fewer than ``MIN_UNTRUNCATED_PLANES`` planes are left."""
    from .line_integral_consistency import (ALL_MOTIONS, MIN_UNTRUNCATED_PLANES, OBSERVED_MOTIONS, WEAK_MOTIONS,
                                            estimate_motions, motion_axes, untruncated_gain)
    from .optimiser import _report

    t0 = time.perf_counter()
    views = list(geometry.views)
    centre = np.asarray(geometry.volume.center_mm, float)
    found: List[Dict[str, Any]] = []
    used = [0]
    for k in range(1, len(views)):
        if epipolar_normal(views[0], views[k]) is None:
            found.append({"view": k + 1, "skipped": "looks along the same line as view 1"})
        else:
            used.append(k)
    # a joint search needs every pair to have epipolar planes; otherwise each view is matched to view 1 alone
    jointly = all(epipolar_normal(views[i], views[j]) is not None for i in used[1:] for j in used[1:] if i < j)
    groups = [used] if jointly and len(used) > 1 else [[0, k] for k in used[1:]]  # none when no view can be matched

    def told(step: int, total: int, message: str) -> None:
        # step 0 of the run (the fit comes after; its total is not known here): a progress bar showing step/total
        # would otherwise fill with the search and fall back to 0 when the fit starts
        _report(progress, phase="calibrate", step=0, calibration_step=step, calibration_total=total,
                elapsed_s=time.perf_counter() - t0, eta_s=None, device="cpu", message=message)

    warnings: List[str] = []
    unseen = list(unseen) if unseen is not None else [None] * len(views)
    for group in groups:
        estimates = estimate_motions([views[k] for k in group], [line_integrals[k] for k in group], centre,
                                     FRAME_CALIBRATION_LIMITS["deg"], FRAME_CALIBRATION_LIMITS["mm"], progress=told,
                                     unseen=[unseen[k] for k in group], min_gain=min_consistency_gain)
        fallbacks = {e.joint_fallback for e in estimates if e.joint_fallback}
        for why in sorted(fallbacks):
            warnings.append(f"the frames' pose search over all {len(group)} views at once could not be used: {why}; "
                            "each view was matched to one other view instead, the best-agreeing pair first (report.json: "
                            "calibration → matched_with; a motion two views cannot see stays uncorrected)")
        # a view matched to another corrected view comes after it: its pose is judged against that view's corrected one
        by_view = dict(zip(group[1:], estimates))
        done = {group[0]}
        ordered: List[int] = []
        while len(ordered) < len(by_view):
            ready = [k for k in by_view if k not in done
                     and (by_view[k].jointly or group[by_view[k].reference_view] in done)]
            k = min(ready) if ready else min(set(by_view) - done)
            ordered.append(k)
            done.add(k)
        for k in ordered:
            estimate = by_view[k]
            partner = group[estimate.reference_view]
            searched = ALL_MOTIONS if estimate.jointly else OBSERVED_MOTIONS
            axes = motion_axes(views[partner], views[k], centre)
            entry: Dict[str, Any] = {"view": k + 1, "rotation_centre_mm": [round(float(v), 3) for v in centre],
                                     "matched_with": [i + 1 for i in group if i != k] if estimate.jointly else [partner + 1]}
            if estimate.joint_fallback:
                entry["joint_search"] = f"not used: {estimate.joint_fallback}"
            elif estimate.joint_start:
                entry["joint_search"] = f"started from {estimate.joint_start}"
            for name in searched:
                rotation = bool(np.any(axes[name][:3]))
                entry[name] = {"value": round(estimate.parameters[name], 3), "unit": "deg" if rotation else "mm",
                               "axis_lps": [round(float(v), 4) for v in (axes[name][:3] if rotation else axes[name][3:])]}
            gain = estimate.cost_before / max(estimate.cost_after, 1e-12)
            if not estimate.measured:
                warnings.append(f"view {k + 1}: the vessels run into a collimator or the image's edge on almost every "
                                "epipolar plane through this view and view 1, so the frames cannot show the motion between "
                                "the acquisitions; the view was left as given (the frames' fields of view "
                                "truncate the vessels; bench/RESULTS.md §91)")
                entry.update(left_as_given=True, why_left_as_given=(
                    f"only {estimate.planes_compared} epipolar planes are not truncated by a collimator or the image's "
                    f"edge ({MIN_UNTRUNCATED_PLANES} needed)"))
            elif estimate.at_limit:
                warnings.append(f"view {k + 1}: the pose correction from the frames reached the end of its range "
                                f"({', '.join(n.replace('_', ' ') for n in estimate.at_limit)}); the view was left as given. "
                                "Check the view's angles and distances and that each frame belongs to its view")
                entry.update(left_as_given=True, why_left_as_given="the motion found reached the end of its range")
            elif gain < min_consistency_gain:
                entry.update(left_as_given=True, motion_found=False, why_left_as_given=(
                    f"the motion found made the views only {gain:.2f}× more consistent (at least {min_consistency_gain:g}× "
                    "asked): no more than noise in the frames and masks allows without any motion"))
            else:
                confirmed = None
                if confirm_unseen is not None and min_untruncated_gain > 0 and not estimate.jointly:
                    confirmed = untruncated_gain(views[partner], line_integrals[partner], views[k], line_integrals[k],
                                                 centre, estimate.added, (confirm_unseen[partner], confirm_unseen[k]))
                if confirmed is not None:
                    entry.update(untruncated_consistency_gain=_rounded(confirmed[0], 2), untruncated_planes=confirmed[1])
                    if confirmed[1] < MIN_UNTRUNCATED_PLANES:  # too few to tell: the search's own gain decides
                        entry["untruncated_check"] = (f"not made: only {confirmed[1]} planes are untruncated "
                                                      f"({MIN_UNTRUNCATED_PLANES} needed)")
                        confirmed = None
                if confirmed is not None and confirmed[0] < min_untruncated_gain:
                    entry.update(left_as_given=True, why_left_as_given=(
                        f"the motion found made the views {gain:.2f}× more consistent, but on the epipolar planes no "
                        f"vessel running into a collimator or the image's edge lies on only {confirmed[0]:.2f}× (at least "
                        f"{min_untruncated_gain:g}× asked): it hides what the field of view cuts rather than undoing a motion"))
                else:
                    views[k] = moved(views[k], estimate.added[:3], estimate.added[3:], centre)
                    entry["motion_found"] = True
            entry.update(consistency_before=_rounded(estimate.cost_before, 5), consistency_after=_rounded(estimate.cost_after, 5),
                         consistency_gain=_rounded(gain, 2),
                         truncated_pixels=list(estimate.truncated_pixels), planes_compared=estimate.planes_compared,
                         not_observed=(["a shift of every other view together along view 1's axis (kept near zero)"]
                                       if estimate.jointly else list(WEAK_MOTIONS) + ["shift_along_baseline"]),
                         object_rotation_deg=[round(float(v), 4) for v in views[k].object_rotation_deg],
                         object_translation_mm=[round(float(v), 4) for v in views[k].object_translation_mm])
            found.append(entry)
    found.sort(key=lambda entry: entry["view"])
    return Calibration(Geometry(geometry.volume, views), found, time.perf_counter() - t0, warnings,
                       method="epipolar consistency of the frames' vessel line integrals")


def calibration_lines(report: Dict[str, Any]) -> List[str]:
    """One line per view whose pose a run searched (report.json → ``calibration``, and ``first`` where the frames'
    search ran before the re-fit one): the correction applied, or why the view was left as given. [] where none ran."""
    calibration = report.get("calibration")
    if not isinstance(calibration, dict) or calibration.get("method", "none") == "none":
        return []
    stages = ([calibration["first"]] if isinstance(calibration.get("first"), dict) else []) + [calibration]
    lines = []
    for stage in stages:
        source = "from the frames" if "frames" in str(stage.get("method", "")) else "by re-fitting"
        for entry in stage.get("views") or []:
            if not isinstance(entry, dict):
                continue
            view = entry.get("view", "?")
            if entry.get("skipped"):
                lines.append(f"View {view}: pose not searched {source} ({entry['skipped']}).")
            elif entry.get("left_as_given"):
                lines.append(f"View {view}: pose left as given {source}: {entry.get('why_left_as_given', 'see report.json')}.")
            else:
                rotation = float(np.linalg.norm(entry.get("object_rotation_deg") or [0.0]))
                shift = float(np.linalg.norm(entry.get("object_translation_mm") or [0.0]))
                gains = []
                if isinstance(entry.get("consistency_gain"), (int, float)):
                    gains.append(f"the views {entry['consistency_gain']:.2f}× more consistent")
                if isinstance(entry.get("untruncated_consistency_gain"), (int, float)):
                    gains.append(f"{entry['untruncated_consistency_gain']:.2f}× on the planes no collimator cuts")
                if str(entry.get("joint_search", "")).startswith("not used") and entry.get("matched_with"):
                    gains.append(f"matched to view {entry['matched_with'][0]} alone: the search over all views at once "
                                 "could not be used")
                lines.append(f"View {view}: pose corrected {source}: its object turned {rotation:.2f}° and moved "
                             f"{shift:.2f} mm{' (' + '; '.join(gains) + ')' if gains else ''}.")
    return lines
