"""What the epipolar check says before a run (``consistency.view_agreement``, ``agreement_warnings``), per case.

    .venv/bin/python bench/view_agreement.py --protocol realistic-static-collimated-lao30-rao30 --suite rca --cases 10
    .venv/bin/python bench/view_agreement.py --protocol realistic-static-lao50cra25-rao50cra25 --suite lad --cases 10 \\
        --masks '{"collimator_fraction": 0.15}' --fault 2 secondary_deg -25

Per case and view: the consistency (centreline with a partner in the other view), the share seen by that view only
(stretches without a partner that continue a vessel into another view's unseen part: collimator, clipped, off the
detector) and the views hiding it; with the frames' unseen parts read as a run reads them (``masks.unseen_pixels``).
``--fault VIEW FIELD VALUE`` gives one view a wrong value (e.g. a flipped secondary angle) after the simulation, to
see whether a wrong geometry still gets the geometry checks named. Then the tally over the cases: how many get the
bare geometry warning, the one-view message with the geometry checks, and the one-view message alone (a case counts
under each its views' messages fall in). No fit runs.

``--truth`` scores the centreline pixels the check marks as seen by one view only (those ``qa_view<n>.png`` draws in
reddish purple) against the truth: a truth voxel is seen by a view when its centre projects onto a pixel of that view's
detector its frame leaves open (``masks.unseen_pixels``); a marked pixel is right when a voxel that another view does
not see projects within 2 pixels of it (what the mark claims: whether this view's own frame shows it at its soft edge
is the mask's business), and the truth's one-view centreline is the mask's centreline within 2 pixels of voxels this
view sees and another does not, and beyond 2 pixels of any voxel every view sees (overlaps left out).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402
from skimage.morphology import skeletonize  # noqa: E402

from SDFCARLib.benchmark.report import machine_info  # noqa: E402
from SDFCARLib.consistency import GEOMETRY_CHECKS, ConsistencyOptions, agreement_warnings, view_agreement  # noqa: E402
from SDFCARLib.geometry import Geometry  # noqa: E402
from SDFCARLib.masks import unseen_pixels  # noqa: E402
from suite_cases import add_case_arguments, prepared_cases  # noqa: E402


NEAR_PX = 2


def _nearest_pixels(view, points: np.ndarray):
    """(rows, cols) of the pixel each point projects onto, and which points project onto the detector at all."""
    rows, cols, _ = view.project(points)
    r, c = np.rint(rows), np.rint(cols)
    inside = np.isfinite(r) & np.isfinite(c) & (r >= 0) & (r < view.detector_shape[0]) & (c >= 0) & (c < view.detector_shape[1])
    return np.where(inside, r, 0).astype(int), np.where(inside, c, 0).astype(int), inside


def _projected_image(view, points: np.ndarray) -> np.ndarray:
    r, c, inside = _nearest_pixels(view, points)
    image = np.zeros(view.detector_shape, dtype=bool)
    image[r[inside], c[inside]] = True
    return image


def _seen(view, points: np.ndarray, unseen: np.ndarray) -> np.ndarray:
    r, c, inside = _nearest_pixels(view, points)
    return inside & ~unseen[r, c]


def truth_scores(case, views, unseen, masks, agreements):
    """Per view (marked pixels, share of them right, truth one-view centreline pixels, share of those marked)."""
    points = case.geometry.volume.voxel_centers(np.flatnonzero(np.asarray(case.label, bool)))
    seen = np.stack([_seen(v, points, u) for v, u in zip(views, unseen)])
    near = lambda image: ndimage.distance_transform_edt(~image) <= NEAR_PX if image.any() else image  # noqa: E731
    out = []
    for k, (view, mask, agreement) in enumerate(zip(views, masks, agreements)):
        hidden_elsewhere = ~np.all(np.delete(seen, k, axis=0), axis=0)
        near_hidden = near(_projected_image(view, points[hidden_elsewhere]))
        near_alone = near(_projected_image(view, points[seen[k] & hidden_elsewhere]))
        near_every = near(_projected_image(view, points[np.all(seen, axis=0)]))
        truth = skeletonize(mask) & near_alone & ~near_every
        found = agreement.one_view_image(view.detector_shape)
        right = (found & near_hidden).sum() / found.sum() if found.any() else float("nan")
        recall = (found & truth).sum() / truth.sum() if truth.any() else float("nan")
        out.append((int(found.sum()), right, int(truth.sum()), recall))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_case_arguments(parser)
    parser.add_argument("--fault", nargs=3, metavar=("VIEW", "FIELD", "VALUE"),
                        help="give view VIEW (from 1) the value VALUE of CArmView field FIELD after the simulation")
    parser.add_argument("--options", default="{}", help="JSON: consistency.ConsistencyOptions fields over the defaults")
    parser.add_argument("--truth", action="store_true",
                        help="score the pixels marked as seen by one view only against the truth (see above)")
    args = parser.parse_args()
    overrides = json.loads(args.masks)
    options = ConsistencyOptions(**json.loads(args.options))
    print(f"machine: {machine_info()}; "
          f"{args.protocol} {args.suite} cases 0–{args.cases - 1}, masks {overrides or 'as the protocol'}, "
          f"fault {args.fault or 'none'}, options {json.loads(args.options) or 'the defaults'}", flush=True)
    tally = {"geometry": 0, "one view + geometry checks": 0, "one view alone": 0, "nothing": 0}
    marked_total = right_total = truth_total = found_total = 0  # pixels over every case and view (--truth)
    for spec, case in prepared_cases(args):
        views = list(case.geometry.views)
        unseen = [unseen_pixels(f, v.pixel_spacing_mm, v.magnification) for f, v in zip(case.frames, views)]
        if args.fault:
            n, field, value = int(args.fault[0]), args.fault[1], float(args.fault[2])
            views[n - 1] = dataclasses.replace(views[n - 1], **{field: value})
        t0 = time.perf_counter()
        agreements = view_agreement(Geometry(case.geometry.volume, tuple(views)),
                                    [np.asarray(m, bool) for m in case.masks], unseen, options)
        seconds = time.perf_counter() - t0
        warnings = agreement_warnings(agreements, options)
        kinds = {("one view + geometry checks" if "cannot show them" in w else
                  "one view alone" if "cannot show it" in w else "geometry") for w in warnings
                 if GEOMETRY_CHECKS in w or "cannot show" in w}
        for kind in kinds or {"nothing"}:  # a case counts in every kind one of its views' messages is
            tally[kind] += 1
        kind = ", ".join(sorted(kinds)) or "nothing"
        per_view = "  ".join(f"view {n}: consistency {a.consistency:.3f}, one view only {a.one_view_share:.3f}"
                             f"{' (hidden by view ' + ', '.join(map(str, a.hidden_by)) + ')' if a.hidden_by else ''}"
                             for n, a in enumerate(agreements, start=1))
        print(f"{spec.name}: {per_view}; {kind}; {seconds:.1f} s", flush=True)
        if args.truth:
            scores = truth_scores(case, views, unseen, [np.asarray(m, bool) for m in case.masks], agreements)
            for f, r, t, c in scores:
                marked_total += f
                right_total += round(f * r) if f else 0
                truth_total += t
                found_total += round(t * c) if t else 0
            print("    truth: " + "  ".join(f"view {n}: marked {f} px, {100 * r:.0f} % right; one-view centreline {t} px, "
                                            f"{100 * c:.0f} % marked" for n, (f, r, t, c) in enumerate(scores, start=1)),
                  flush=True)
    print("tally: " + ", ".join(f"{k} {v}" for k, v in tally.items()))
    if args.truth:
        print(f"truth, every case and view: marked {marked_total} px, {right_total} right "
              f"({100 * right_total / max(marked_total, 1):.0f} %); one-view centreline {truth_total} px, {found_total} "
              f"marked ({100 * found_total / max(truth_total, 1):.0f} %)")


if __name__ == "__main__":
    main()
