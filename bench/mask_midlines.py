"""Do the segmented masks' midlines carry the 3D centreline's wander of the recon tubes? (RESULTS §33a)

For the ten tubes of ``bench/qca.py``'s recon suite (the same tubes, directions and segmented masks:
``qca.RECON_TUBES``, ``qca.tube_direction``, ``qca.segmented_masks``, the static realistic protocol),
measure per view how far each mask's midline lies from the projected true axis (perpendicular to it,
every 0.5 mm, the lesion and 3 mm at either end left out, and samples the view foreshortens below 30 %),
and the 3D offset that the two views' offsets imply by triangulation (the least displacement
perpendicular to the axis that moves both projections by them). Clean masks (rendered from the truth,
``--masks clean``) are the control: their offsets are the measurement's own floor (nearest-pixel edges).
A self-check moves the clean tube by a known 0.4 mm and must read it back.

    .venv/bin/python bench/mask_midlines.py --max-foreshortening-pct 15      # the tubes of RESULTS §31c/§32d
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

import qca  # noqa: E402
from SDFCARLib.analysis.diameter import plane_basis  # noqa: E402
from SDFCARLib.analysis.mask_centreline import detector_jacobian  # noqa: E402
from SDFCARLib.analysis.phantoms import branch_arc_length_mm, render_mask, stenosed_tube  # noqa: E402
from SDFCARLib.masks import MaskError  # noqa: E402
from SDFCARLib.phantoms import Branch, CentrelineTree  # noqa: E402

VIEWS = qca.VIEWS
STEP_MM, END_MM, MIN_FS = 0.5, 3.0, 0.3


def proj(view, p):
    r, c, d = view.project(np.asarray(p, float))
    return np.stack([r, c], axis=-1), d


def jacobian(view, p):
    """d(row, col)/dp in pixels, 2x3 (the product's detector-mm Jacobian over the pixel spacing)."""
    return detector_jacobian(view, np.asarray(p, float)[None])[0] / np.asarray(view.pixel_spacing_mm, float)[:, None]


def axis_samples(ph):
    b = ph.tree.branches[0]
    s = branch_arc_length_mm(b)
    t = ph.truth
    arc = np.arange(END_MM, s[-1] - END_MM + 1e-9, STEP_MM)
    lo, hi = t["lesion_start_mm"], t["lesion_start_mm"] + t["lesion_length_mm"]
    arc = arc[(arc < lo) | (arc > hi)]
    P = np.stack([np.interp(arc, s, b.points[:, a]) for a in range(3)], 1)
    h = 0.05
    T = np.stack([np.interp(arc + h, s, b.points[:, a]) - np.interp(arc - h, s, b.points[:, a]) for a in range(3)], 1)
    T /= np.linalg.norm(T, axis=1, keepdims=True)
    R = np.interp(arc, s, b.radii)
    seg = np.r_[0, np.cumsum(np.diff(arc) > STEP_MM + 1e-6)]  # contiguous pieces (before / after the lesion)
    return arc, P, T, R, seg


def measure_view(mask, view, P, T, R, step_px=0.1):
    """Signed midline offset (px, along the 2D normal n), width (px), normal n, valid flag, per sample."""
    H, W = mask.shape
    uv, depth = proj(view, P)
    h = 0.05
    d2 = (proj(view, P + h * T)[0] - proj(view, P - h * T)[0])
    ps = view.pixel_spacing_mm[0]
    iso = view.isocenter_pixel_spacing_mm[0]
    fs = np.linalg.norm(d2, axis=1) * iso / (2 * h)  # projected step / 3D step, at the isocentre scale
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    nrm = np.stack([-d2[:, 1], d2[:, 0]], 1)
    rad_px = R * view.sid_mm / depth / ps  # projected true radius (px)
    off = np.full(len(P), np.nan)
    wid = np.full(len(P), np.nan)
    for i in range(len(P)):
        if fs[i] < MIN_FS:
            continue
        L = 3 * rad_px[i] + 5
        t = np.arange(-L, L + step_px / 2, step_px)
        t -= t[np.argmin(np.abs(t))]  # exact 0 on the grid
        rr = np.rint(uv[i, 0] + t * nrm[i, 0]).astype(int)
        cc = np.rint(uv[i, 1] + t * nrm[i, 1]).astype(int)
        ok = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
        v = np.zeros(len(t), bool)
        v[ok] = mask[rr[ok], cc[ok]]
        if not v.any():
            continue
        # runs of True
        dv = np.diff(np.r_[0, v.astype(int), 0])
        starts, ends = np.flatnonzero(dv == 1), np.flatnonzero(dv == -1) - 1
        k0 = np.argmin(np.abs(t))
        inside = np.flatnonzero((starts <= k0) & (ends >= k0))
        if inside.size:
            j = inside[0]
        else:
            dist = np.minimum(np.abs(t[starts]), np.abs(t[ends]))
            j = int(np.argmin(dist))
        if starts[j] == 0 or ends[j] == len(t) - 1:
            continue  # run reaches the walk's end: no edge found
        lo, hi = t[starts[j]] - step_px / 2, t[ends[j]] + step_px / 2
        off[i] = 0.5 * (lo + hi)
        wid[i] = hi - lo
    return dict(off_px=off, wid_px=wid, nrm=nrm, fs=fs, rad_px=rad_px, iso=iso, ps=ps, depth=depth)


def acf_length(x, seg):
    """Along-axis 1/e length (mm) of the demeaned offset, pairs taken within one contiguous piece."""
    ok = np.isfinite(x)
    if ok.sum() < 5:
        return np.nan
    x = x - np.nanmean(x)
    var = np.nanmean(x[ok] ** 2)
    if var == 0:
        return np.nan
    for k in range(1, len(x)):
        a, b = x[:-k], x[k:]
        same = (seg[:-k] == seg[k:]) & np.isfinite(a) & np.isfinite(b)
        if same.sum() < 3:
            return np.nan  # never dropped below 1/e within the data
        if np.mean(a[same] * b[same]) / var < 1 / np.e:
            return k * STEP_MM
    return np.nan


def boxcar(x, seg, width_mm=2.0):
    n = int(round(width_mm / STEP_MM))
    out = np.full_like(x, np.nan)
    for s in np.unique(seg):
        idx = np.flatnonzero(seg == s)
        for j, i in enumerate(idx):
            w = idx[max(0, j - n // 2): j + n // 2 + 1]
            v = x[w]
            v = v[np.all(np.isfinite(v), axis=1)] if v.ndim == 2 else v[np.isfinite(v)]
            if len(v) and np.all(np.isfinite(x[i])):
                out[i] = v.mean(axis=0)
    return out


def triangulate(P, T, meas, views=VIEWS):
    """Least 3D displacement ⊥ axis whose projections move by the views' signed normal offsets (NaN where a
    view has none)."""
    D = np.full((len(P), 3), np.nan)
    for i in range(len(P)):
        o = np.array([m["off_px"][i] for m in meas])
        if not np.all(np.isfinite(o)):
            continue
        E = np.stack([a[0] for a in plane_basis(T[i][None])], 1)
        A = np.stack([m["nrm"][i] @ jacobian(v, P[i]) @ E for m, v in zip(meas, views)])
        x, *_ = np.linalg.lstsq(A, o, rcond=1e-6)
        D[i] = E @ x
    return D


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-foreshortening-pct", type=float, default=None, help="as bench/qca.py's (the tubes' directions)")
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)  # nan means of the views/cases without a measurement
    t_start = time.perf_counter()
    rows = []

    def say(s=""):
        print(s, flush=True)

    say("per view: mean|off| (mm @ isocentre), mean signed, SD, ACF 1/e length (mm), mean width err (mm), n valid; "
        "3D: mean |d| (mm), |mean d|, mean |d| after 2 mm boxcar of the 2D offsets")
    for n, (name, kw) in enumerate(qca.RECON_TUBES):
        direction = qca.tube_direction(n, args.max_foreshortening_pct)
        ph = stenosed_tube(length_mm=40.0, direction=direction, **kw)
        fsh = [round(v, 1) for v in qca.axis_foreshortening_pct(direction)]
        arc, P, T, R, seg = axis_samples(ph)
        t0 = time.perf_counter()
        sources = {}
        try:
            rz = qca.segmented_masks(ph.tree, n)  # (masks, dice, frames, motion); static protocol
            sources["seg"] = rz[0]
            dice = rz[1]
        except MaskError as exc:  # MaskError: the suite would skip this case too
            say(f"{name}: segmented masks failed: {exc}")
            dice = None
        sources["clean"] = [render_mask(ph.tree, v) for v in VIEWS]
        t_masks = time.perf_counter() - t0
        row = dict(case=name, fs=fsh, dice=dice)
        say(f"\n## case {n} {name} axis foreshortening {fsh} %, seg Dice {dice}, masks {t_masks:.1f}s, samples {len(P)}")
        for src_name, masks in sources.items():
            meas = [measure_view(m, v, P, T, R) for m, v in zip(masks, VIEWS)]
            for k, m in enumerate(meas):
                off_mm = m["off_px"] * m["iso"]
                werr = (m["wid_px"] - 2 * m["rad_px"]) * m["iso"]
                row[f"{src_name}_off{k}"] = np.nanmean(np.abs(off_mm))
                row[f"{src_name}_werr{k}"] = np.nanmean(werr)
                say(f"  {src_name:5s} view{k + 1}: mean|off| {np.nanmean(np.abs(off_mm)):.3f}  signed {np.nanmean(off_mm):+.3f}  "
                    f"SD {np.nanstd(off_mm):.3f}  ACF {acf_length(off_mm, seg):.1f} mm  width err {np.nanmean(werr):+.3f}  "
                    f"|werr| {np.nanmean(np.abs(werr)):.3f}  n {np.isfinite(off_mm).sum()}/{len(P)}")
            D = triangulate(P, T, meas)
            d = np.linalg.norm(D, axis=1)
            sm = [dict(m, off_px=boxcar(m["off_px"], seg)) for m in meas]
            ds = np.linalg.norm(triangulate(P, T, sm), axis=1)
            row[f"{src_name}_3d"] = np.nanmean(d)
            row[f"{src_name}_3ds"] = np.nanmean(ds)
            row[f"{src_name}_3dbias"] = np.linalg.norm(np.nanmean(D, axis=0))
            row[f"{src_name}_werr"] = np.nanmean([row[f"{src_name}_werr0"], row[f"{src_name}_werr1"]])
            say(f"  {src_name:5s} 3D: mean|d| {np.nanmean(d):.3f}  median {np.nanmedian(d):.3f}  max {np.nanmax(d):.3f}  "
                f"|mean d| {row[f'{src_name}_3dbias']:.3f}  smoothed mean|d| {np.nanmean(ds):.3f}  ACF {acf_length(d, seg):.1f} mm  "
                f"n {np.isfinite(d).sum()}")
        rows.append(row)

    say("\n| # | tube (axis FS % v1/v2) | off v1 seg/clean | off v2 seg/clean | 3D seg/clean | 3D seg smoothed | 3D bias seg | width err seg/clean |")
    say("|---|---|---|---|---|---|---|---|")
    g = lambda r, k: r.get(k, np.nan)  # noqa: E731
    for n, r in enumerate(rows):
        say(f"| {n} | {r['case']} ({r['fs'][0]:.0f}/{r['fs'][1]:.0f}) | {g(r, 'seg_off0'):.3f}/{r['clean_off0']:.3f} | "
            f"{g(r, 'seg_off1'):.3f}/{r['clean_off1']:.3f} | {g(r, 'seg_3d'):.3f}/{r['clean_3d']:.3f} | {g(r, 'seg_3ds'):.3f} | "
            f"{g(r, 'seg_3dbias'):.3f} | {g(r, 'seg_werr'):+.3f}/{r['clean_werr']:+.3f} |")
    for label, sel in (("all", rows), ("con (straight)", [r for r in rows if r["case"].endswith("con")]),
                       ("ecc (bent)", [r for r in rows if r["case"].endswith("ecc")])):
        m = lambda k: np.nanmean([g(r, k) for r in sel])  # noqa: E731
        say(f"| mean {label} | | {m('seg_off0'):.3f}/{m('clean_off0'):.3f} | {m('seg_off1'):.3f}/{m('clean_off1'):.3f} | "
            f"{m('seg_3d'):.3f}/{m('clean_3d'):.3f} | {m('seg_3ds'):.3f} | {m('seg_3dbias'):.3f} | {m('seg_werr'):+.3f}/{m('clean_werr'):+.3f} |")
    # self-test: the clean masks of case 0 moved rigidly by 0.4 mm perpendicular to its axis, measured against the
    # unmoved axis, must give a 3D offset of 0.4 mm (checks the signs, the Jacobian and the px -> mm scale)
    ph = stenosed_tube(length_mm=40.0, direction=qca.tube_direction(0, None), **qca.RECON_TUBES[0][1])
    arc, P, T, R, seg = axis_samples(ph)
    b = ph.tree.branches[0]
    for u in (np.cross(T[0], [0, 0, 1.0]), np.cross(T[0], np.cross(T[0], [0, 0, 1.0]))):
        shift = 0.4 * u / np.linalg.norm(u)
        moved = CentrelineTree([Branch(b.points + shift, b.radii, "vessel")], "moved")
        meas = [measure_view(render_mask(moved, v), v, P, T, R) for v in VIEWS]
        D = triangulate(P, T, meas)
        say(f"self-test: true shift {np.round(shift, 3)} (0.400 mm) -> measured mean d {np.round(np.nanmean(D, 0), 3)}, "
            f"mean|d| {np.nanmean(np.linalg.norm(D, axis=1)):.3f} mm")
    say(f"\n# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; max foreshortening "
        f"{args.max_foreshortening_pct}; {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
