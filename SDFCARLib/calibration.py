"""Rigid self-calibration: the shift of each view's object across its epipolar lines, by search.

Why
    Views are acquired seconds apart; table, patient and heart move in between, and the nominal
    C-arm poses then disagree with the images by millimetres. The component of such a motion that
    moves view k's image *across* its epipolar lines with view 1 breaks the tree apart in 3D: the
    branches cannot meet on the visual hull, and a field fitted on the hull explains the masks
    measurably worse (bench/RESULTS.md, section 8: L_occ 2.4× higher at the nominal pose of a 3 mm
    motion, minimal at the true one). Shifts *along* the epipolar lines move the tree in depth
    and leave the masks explained: two views cannot tell them, and they are left alone.

Method
    View 1 is the reference (the result stays in its frame). For view k the searched direction is
    n_k = d_1 × d_k / |d_1 × d_k| (d the views' detector directions): a translation of the object
    along n_k moves view k's image perpendicular to its epipolar lines with view 1. Each candidate
    shift t·n_k becomes view k's object motion (composed with any the view already carries), the
    field is re-fitted from scratch on that pose's hull for ``calibration_steps`` steps, and the
    candidate's score is the mean loss of the last steps. A coarse grid of candidates over
    ±``calibration_range_mm`` is refined by one parabola through the best and its neighbours.
    Re-fitting is what makes the motion visible: optimised jointly by gradient with the field, the
    pose does not move (the field re-fits to any pose first; measured, section 8).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence

import numpy as np

from .geometry import CArmView, Geometry, rotation_matrix
from .settings import CALIBRATION_SCORE_STEPS


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
    r0 = rotation_matrix(view.object_rotation_deg)
    # the new motion acts first: x → R0 (x + t) + t0
    total = r0 @ np.asarray(translation_mm, float) + np.asarray(view.object_translation_mm, float)
    return view.with_object_motion(view.object_rotation_deg, total)


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

    def report(self) -> Dict[str, Any]:
        return {"method": "shift across the epipolar lines, re-fitted field per candidate",
                "views": self.views, "seconds": round(self.seconds, 1)}


def calibrate(geometry: Geometry, targets: Sequence[np.ndarray], settings, target_kind: str,
              score: Optional[Callable[[Geometry], float]] = None, progress=None, cancel=None) -> Calibration:
    """Search each view's shift across its epipolar lines with view 1 (module docstring).

    ``score(geometry)`` — lower is better — defaults to the loss of a short re-fit; tests pass their own.
    """
    from .optimiser import ReconstructionCancelled, _is_cancelled, _report, fitted_loss

    c = settings.calibration
    t0 = time.perf_counter()
    if score is None:
        short = settings.replace(steps=c.calibration_steps, prune=False, reconnect=False)

        def score(candidate: Geometry) -> float:
            return fitted_loss(candidate, targets, short, target_kind, CALIBRATION_SCORE_STEPS, cancel)

    views = list(geometry.views)
    found: List[Dict[str, Any]] = []
    warnings: List[str] = []
    grid_mm = np.linspace(-c.calibration_range_mm, c.calibration_range_mm, c.calibration_candidates)
    step_mm = float(grid_mm[1] - grid_mm[0])  # calibration_candidates ≥ 3 (Settings.validate)
    for k in range(1, len(views)):
        normal = epipolar_normal(views[0], views[k])
        if normal is None:
            found.append({"view": k + 1, "skipped": "looks along the same line as view 1"})
            continue

        def loss_at(t_mm: float) -> float:
            if _is_cancelled(cancel):
                raise ReconstructionCancelled("cancelled during the calibration")
            trial = list(views)
            trial[k] = shifted(views[k], t_mm * normal)
            value = float(score(Geometry(geometry.volume, trial)))
            _report(progress, phase="calibrate", step=k, total=len(views) - 1, elapsed_s=time.perf_counter() - t0,
                    eta_s=None, device=str(settings.run.device), message=f"view {k + 1}: {t_mm:+.2f} mm → loss {value:.5f}")
            return value

        scores = {float(t): loss_at(float(t)) for t in grid_mm}
        best = min(scores, key=scores.get)
        # refine between the best candidate's neighbours (half the grid step on each side)
        for t in (best - step_mm / 2, best + step_mm / 2):
            if abs(t) <= c.calibration_range_mm + 1e-9:
                scores[float(t)] = loss_at(float(t))
        ordered = sorted(scores)
        best = min(scores, key=scores.get)
        i = ordered.index(best)
        if 0 < i < len(ordered) - 1:
            xs = ordered[i - 1:i + 2]
            refined = parabola_minimum(xs, [scores[x] for x in xs])
        else:
            # the loss still falls at the end of the range: no minimum was found, and a shift at the
            # edge is more likely a wrong pose fitted to other errors (measured) than a real one
            refined = 0.0
            warnings.append(f"view {k + 1}: the pose correction found no minimum within ±{c.calibration_range_mm:g} mm "
                            f"(lowest loss at {best:+.1f} mm); the view was left as given. Check its angles and "
                            "distances, or widen calibration_range_mm")
        views[k] = shifted(views[k], refined * normal)
        found.append({"view": k + 1, "direction_lps": [round(float(v), 4) for v in normal],
                      "shift_mm": round(refined, 3), "translation_mm": [round(float(v), 3) for v in refined * normal],
                      "candidates_mm": [round(x, 3) for x in ordered],
                      "losses": [round(scores[x], 6) for x in ordered],
                      "loss_nominal": round(scores.get(0.0, float("nan")), 6)})
    return Calibration(Geometry(geometry.volume, views), found, time.perf_counter() - t0, warnings)
