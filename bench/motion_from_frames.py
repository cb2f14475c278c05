"""The heart's motion between the acquisitions, found from the frames' line integrals (``line_integral_consistency``).

    .venv/bin/python bench/motion_from_frames.py --suite rca --cases 10 [--reconstruct]

Realistic protocol with motion (``realistic-lao30-rao30``: view 2's object moved up to 3 mm / 2°,
masks segmented from the simulated angiograms; ``--static``: the same without motion). Per case: the
evidence images of both views (read as `fast` reads them for its calibration, nominal poses), view 2's motion estimated
from them, and, against the simulated motion, each component along ``motion_axes`` (about the
region's centre) and the shift along the baseline, which two views cannot see. With
``--reconstruct``, ``fast`` (with the frames) at the nominal pose, at the estimated pose and at the
true pose (the last with motion only), scored against the truth. Prints the means and the machine.

``--views 3`` (``realistic-lao30-rao30-cra30``, views 2 and 3 moved): each view's motion matched to
view 1 alone (``pairwise``, what ``estimate_motion`` finds) and over every pair at once (``joint``,
``estimate_motions``); per view the error of the whole motion about the region's centre, and its part
along view 1's axis (a common shift there is what three views barely see).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from bench.realistic_cases import add_grid_arguments, protocol_setup  # noqa: E402
from SDFCARLib.geometry import Geometry, rotation_matrix  # noqa: E402
from SDFCARLib.line_integral_consistency import estimate_motion, estimate_motions, motion_axes  # noqa: E402
from SDFCARLib.metrics import depth_aligned_metrics, evaluate  # noqa: E402
from SDFCARLib.optimiser import read_frame_evidence, reconstruct  # noqa: E402
from SDFCARLib.phantoms import lad_tree, rca_tree, voxelize  # noqa: E402
from SDFCARLib.realistic import RealisticOptions, realistic_input  # noqa: E402
from SDFCARLib.settings import REALISTIC_PROTOCOLS, make_settings, parse_setting_overrides  # noqa: E402

PROTOCOL = "realistic-lao30-rao30"
STATIC = "realistic-static-lao30-rao30"  # the same without motion: the estimate should be nil and change nothing
THREE_VIEWS = {False: "realistic-lao30-rao30-cra30", True: "realistic-static-lao30-rao30-cra30"}


def components(rotation_deg, translation_mm, centre, axes):
    """A motion x → Rx + t as the searched motions' sizes about ``centre`` (degrees, mm), plus the
    shift along the baseline, which two views cannot see."""
    rotation = np.asarray(rotation_deg, float)
    translation = np.asarray(translation_mm, float) + rotation_matrix(rotation) @ centre - centre
    baseline = np.cross(axes["shift_across"][3:], axes["shift_in_depth"][3:])
    parts = {name: float((rotation if np.any(axis[:3]) else translation) @ (axis[:3] if np.any(axis[:3]) else axis[3:]))
             for name, axis in axes.items()}
    parts["shift_along_baseline"] = float(translation @ baseline)
    return parts


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", choices=("rca", "lad"), default="rca")
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--cases", type=int, default=4)
    parser.add_argument("--reconstruct", action="store_true", help="also reconstruct at the nominal, found and true poses")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="settings of the reconstructions")
    parser.add_argument("--static", action="store_true", help=f"protocol {STATIC}: no motion")
    parser.add_argument("--blurs", type=float, nargs="+", default=None)
    parser.add_argument("--searched", nargs="+", default=None, help="motions searched (default: the three two views observe)")
    parser.add_argument("--views", type=int, choices=(2, 3), default=2)
    parser.add_argument("--prior", type=float, nargs="+", default=None, help="joint searches with these prior weights")
    add_grid_arguments(parser)
    args = parser.parse_args()
    if args.views == 3:
        return three_views(args)
    motion_options = {k: v for k, v in (("searched", args.searched), ("blurs_mm", args.blurs)) if v is not None}
    protocol = STATIC if args.static else PROTOCOL
    geometry = protocol_setup(args, protocol, f"{args.first}..{args.first + args.cases - 1}")
    overrides = {"calibrate_from_frames": False, **parse_setting_overrides(args.set)}  # the poses are given
    rows = []
    for seed in range(args.first, args.first + args.cases):
        name = f"{args.suite.upper()}-{seed}"
        label = voxelize((rca_tree if args.suite == "rca" else lad_tree)(seed), geometry.volume)
        realistic = realistic_input(label, geometry, seed, RealisticOptions(**REALISTIC_PROTOCOLS[protocol]))
        views = geometry.views
        evidence = frames_evidence(realistic, geometry, overrides)
        centre = np.asarray(geometry.volume.center_mm, float)
        estimate = estimate_motion(views[0], evidence[0], views[1], evidence[1], centre, **motion_options)
        true_view = realistic.true_views[1]
        axes = motion_axes(views[0], views[1], centre)
        true_parts = components(true_view.object_rotation_deg, true_view.object_translation_mm, centre, axes)
        found_parts = components(estimate.rotation_deg, estimate.translation_mm, centre, axes)
        row = {f"error_{k}": abs(found_parts[k] - true_parts[k]) for k in true_parts}
        row["seconds"] = estimate.seconds
        print(f"{name} " + "  ".join(f"{k} {true_parts[k]:+.2f}→{found_parts[k]:+.2f}" for k in true_parts)
              + f" | consistency {estimate.cost_before:.4f} → {estimate.cost_after:.4f} | {estimate.seconds:.1f} s", flush=True)
        if args.reconstruct:
            found_view = views[1].with_object_motion(estimate.rotation_deg, estimate.translation_mm)
            poses = {"nominal": geometry, "found": Geometry(geometry.volume, (views[0], found_view))}
            row.update(reconstruct_at(poses, realistic, label, geometry, args, seed, overrides, name))
        rows.append(row)
    return print_means(rows)


def frames_evidence(realistic, geometry, overrides):
    """The frames' line integrals exactly as ``fast`` (with these settings) reads them for its calibration."""
    settings = make_settings("fast", **dict(overrides, frame_evidence=True))
    return read_frame_evidence(realistic.frames, realistic.masks, geometry, settings, "mask").images


def reconstruct_at(poses, realistic, label, geometry, args, seed, overrides, name):
    """``fast`` reconstructions of the case at each named pose (and, with motion, at the true one), scored
    against the truth (printed)."""
    settings = make_settings("fast", seed=seed, **overrides)
    volume = geometry.volume
    if not args.static:
        poses = dict(poses, true=Geometry(volume, tuple(realistic.true_views)))
    row = {}
    for pose, g in poses.items():
        t0 = time.perf_counter()
        result = reconstruct(g, realistic.masks, settings, "mask", frames=realistic.frames)
        m = evaluate(result.segmentation, label, volume, g.views, realistic.masks)
        aligned = depth_aligned_metrics(result.segmentation, label, volume, g.views[0].detector_direction)
        row.update({f"cldice_{pose}": m["cldice"], f"dice_{pose}": m["dice"], f"pieces_{pose}": m["components"],
                    f"cldice_aligned_{pose}": aligned["cldice_depth_aligned"]})
        print(f"{name} {pose:9s} clDice {m['cldice']:.3f} Dice {m['dice']:.3f} Chamfer {m['chamfer_l2_mm']:.2f} "
              f"pieces {m['components']}/{m.get('components_label')}; along view 1's axis {aligned['depth_offset_mm']:+.2f} mm "
              f"off, clDice there {aligned['cldice_depth_aligned']:.3f} {time.perf_counter() - t0:.0f} s", flush=True)
    return row


def print_means(rows) -> int:
    print("# means: " + "  ".join(f"{k} {np.mean([r[k] for r in rows]):.3f}" for k in rows[0]))
    return 0


def about_centre(rotation_deg, translation_mm, centre):
    rotation = np.asarray(rotation_deg, float)
    return np.concatenate([rotation, np.asarray(translation_mm, float) + rotation_matrix(rotation) @ centre - centre])


def three_views(args) -> int:
    protocol = THREE_VIEWS[args.static]
    geometry = protocol_setup(args, protocol, f"{args.first}..{args.first + args.cases - 1}")
    overrides = {"calibrate_from_frames": False, **parse_setting_overrides(args.set)}  # the poses are given
    centre = np.asarray(geometry.volume.center_mm, float)
    views = geometry.views
    axis = views[0].detector_direction
    priors = args.prior or [None]
    rows = []
    for seed in range(args.first, args.first + args.cases):
        name = f"{args.suite.upper()}-{seed}"
        label = voxelize((rca_tree if args.suite == "rca" else lad_tree)(seed), geometry.volume)
        realistic = realistic_input(label, geometry, seed, RealisticOptions(**REALISTIC_PROTOCOLS[protocol]))
        evidence = frames_evidence(realistic, geometry, overrides)
        truth = [about_centre(v.object_rotation_deg, v.object_translation_mm, centre) for v in realistic.true_views[1:]]
        t0 = time.perf_counter()
        pairwise = [estimate_motion(views[0], evidence[0], views[k], evidence[k], centre) for k in range(1, len(views))]
        found = {"nominal": ([np.zeros(6)] * len(truth), 0.0),
                 "pairwise": ([about_centre(e.rotation_deg, e.translation_mm, centre) for e in pairwise],
                              time.perf_counter() - t0)}
        for prior in priors:
            options = {} if prior is None else {"prior_weight": prior}
            estimates = estimate_motions(views, evidence, centre, **options)
            if estimates[0].joint_fallback:  # the views matched in turn instead (``estimate_motions``)
                print(f"{name} joint search not used: {estimates[0].joint_fallback}", flush=True)
            found["joint" if prior is None else f"joint{prior:g}"] = (
                [about_centre(e.rotation_deg, e.translation_mm, centre) for e in estimates], estimates[0].seconds)
        row = {}
        for method, (motions, seconds) in found.items():
            errors = [m - t for m, t in zip(motions, truth)]
            rotation = max(float(np.linalg.norm(e[:3])) for e in errors)
            translation = max(float(np.linalg.norm(e[3:])) for e in errors)
            along = [float(e[3:] @ axis) for e in errors]
            across = max(float(np.linalg.norm(e[3:] - (e[3:] @ axis) * axis)) for e in errors)
            row.update({f"rot_{method}": rotation, f"mm_{method}": translation, f"across_{method}": across})
            print(f"{name} {method:9s} worst view: rotation error {rotation:.2f}°, translation {translation:.2f} mm "
                  f"({across:.2f} mm across view 1's axis; along it " + " ".join(f"{a:+.2f}" for a in along)
                  + f") {seconds:.1f} s", flush=True)
        if args.reconstruct:
            poses = {method: Geometry(geometry.volume, tuple([views[0]] + [v.with_object_motion(*found_pose(m, centre))
                                                                           for v, m in zip(views[1:], motions)]))
                     for method, (motions, _) in found.items() if not (method == "nominal" and args.static)}
            row.update(reconstruct_at(poses, realistic, label, geometry, args, seed, overrides, name))
        rows.append(row)
    return print_means(rows)


def found_pose(motion_about_centre, centre):
    """(rotation, translation about the origin), as ``CArmView.with_object_motion`` takes them."""
    rotation = np.asarray(motion_about_centre[:3], float)
    return rotation, np.asarray(motion_about_centre[3:], float) - rotation_matrix(rotation) @ centre + centre


if __name__ == "__main__":
    sys.exit(main())
