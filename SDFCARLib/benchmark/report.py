"""What a run reports: summary tables (mean ± std per suite tree and mode), their markdown,
the sdfcar-vs-neca ordering lines, ``summary.md``, box plots, and the machine and versions."""

from __future__ import annotations

import json
import math
import os
import platform
from pathlib import Path
from typing import Any, Dict, List, Sequence, Tuple

import numpy as np

from ..io import write_text_atomically
from .config import BenchmarkConfig
from .registry import HULL, PAPER_METRICS, TABLE_METRICS, mode_title
from .store import safe_name


def _float(text: Any) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


def _mean_std(values: Sequence[float]) -> Tuple[float, float, int]:
    finite = np.asarray([v for v in values if math.isfinite(v)], float)
    if finite.size == 0:
        return math.nan, math.nan, 0
    std = float(finite.std(ddof=1)) if finite.size > 1 else 0.0
    return float(finite.mean()), std, int(finite.size)


def _group_title(suite: str, tree: str) -> str:
    kind = suite.split(":", 1)[0]
    names = {"rca": "RCA (procedural trees)", "lad": "LAD (procedural left trees)", "721a": "721A centreline (LAD)"}
    if kind == "folder":
        return f"{'Left coronary tree (LAD)' if tree == 'lad' else 'Right coronary artery (RCA)'} — {suite}"
    return names.get(kind, suite)


def summary_tables(rows: Sequence[Dict[str, str]], modes: Sequence[str]) -> List[Dict[str, Any]]:
    """Per (suite, tree): per method the mean ± std of every table metric, over finished cases."""
    groups: Dict[Tuple[str, str], List[Dict[str, str]]] = {}
    for row in rows:
        groups.setdefault((row["suite"], row["tree"]), []).append(row)
    tables = []
    for (suite, tree), group in groups.items():
        methods = []
        for mode in [HULL] + [m for m in modes if m != HULL]:
            mode_rows = [r for r in group if r["mode"] == mode]
            ok = [r for r in mode_rows if r["status"] == "ok"]
            stats = {key: _mean_std([_float(r.get(key)) * scale for r in ok]) for key, _, scale, _, _ in TABLE_METRICS}
            methods.append({"mode": mode, "ok": len(ok), "failed": len(mode_rows) - len(ok), "stats": stats,
                            "per_case": {r["case"]: r for r in ok}})
        tables.append({"suite": suite, "tree": tree, "title": _group_title(suite, tree), "methods": methods,
                       "cases": sorted({r["case"] for r in group})})
    return tables


def _table_markdown(table: Dict[str, Any]) -> str:
    headers = ["Method"] + [h for _, h, _, _, _ in TABLE_METRICS] + ["cases (ok/failed)"]
    best: Dict[str, float] = {}
    for key, _, _, _, higher in TABLE_METRICS:
        means = [m["stats"][key][0] for m in table["methods"] if math.isfinite(m["stats"][key][0])]
        if means:
            best[key] = max(means) if higher else min(means)
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join(["---"] + ["---:"] * (len(headers) - 1)) + "|"]
    for method in table["methods"]:
        cells = [f"{mode_title(method['mode'])} (`{method['mode']}`)"]
        for key, _, _, decimals, _ in TABLE_METRICS:
            mean, std, n = method["stats"][key]
            if not math.isfinite(mean):
                cells.append("n/a")
                continue
            text = f"{mean:.{decimals}f} ± {std:.{decimals}f}" if n > 1 else f"{mean:.{decimals}f} ± n/a"  # one case: no spread
            if n < method["ok"]:
                text += f" (n={n})"  # some cases undefined, e.g. Chamfer distance of an empty prediction
            is_best = key in best and round(mean, decimals) == round(best[key], decimals)
            cells.append(f"**{text}**" if is_best else text)
        cells.append(f"{method['ok']}/{method['failed']}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def side_by_side_lines(table: Dict[str, Any]) -> List[str]:
    """Each mode against the visual hull on the cases both finished: clDice and Dice as ratios and differences,
    case by case, and the wall time per case of each (one run, one machine: the ratios are comparable)."""
    methods = {m["mode"]: m for m in table["methods"]}
    hull = methods.get(HULL)
    lines = []
    for mode, method in methods.items():
        if mode == HULL or hull is None:
            continue
        cases = [c for c in method["per_case"] if c in hull["per_case"]]
        parts = []
        for key, name in (("cldice", "clDice"), ("dice", "Dice")):
            pairs = [(_float(method["per_case"][c].get(key)), _float(hull["per_case"][c].get(key))) for c in cases]
            pairs = [(x, y) for x, y in pairs if math.isfinite(x) and math.isfinite(y)]
            if not pairs:
                continue
            x, y = (float(np.mean(v)) for v in zip(*pairs))
            ratio = f"×{x / y:.2f}" if y > 0 else "× n/a"
            better = sum(1 for a, b in pairs if a > b)
            parts.append(f"{name} {x:.3f} vs {y:.3f} ({ratio}, {x - y:+.3f}; higher in {better}/{len(pairs)})")
        times = [_float(method["per_case"][c].get("wall_s")) for c in cases]
        times = [t for t in times if math.isfinite(t)]
        if times:
            parts.append(f"wall time {float(np.mean(times)):.1f} s per case")
        if parts:
            lines.append(f"- `{mode}` against the visual hull on {len(cases)} case{'s' if len(cases) != 1 else ''}: "
                         + "; ".join(parts))
    empty = sorted(f"`{c}` × `{m['mode']}`" for m in table["methods"] if m["mode"] != HULL
                   for c, r in m["per_case"].items() if _float(r.get("voxels_predicted")) == 0)
    if empty:
        lines.append(f"- Empty reconstructions (no voxel predicted; their Chamfer is undefined, their 0 components no "
                     f"merit): {', '.join(empty)}")
    return (["Side by side (the same cases, one run):"] + lines) if lines else []


def ordering_lines(table: Dict[str, Any], first: str = "sdfcar", second: str = "neca") -> List[str]:
    """Per paper metric: which of two modes is better on average and case by case."""
    methods = {m["mode"]: m for m in table["methods"]}
    if first not in methods or second not in methods or not methods[first]["ok"] or not methods[second]["ok"]:
        return [f"Ordering {first} vs {second}: not available (both modes need finished cases)."]
    a, b = methods[first], methods[second]
    parts, agree, compared = [], 0, 0
    for key, header, scale, decimals, higher in TABLE_METRICS:
        if key not in PAPER_METRICS:
            continue
        ma, mb = a["stats"][key][0], b["stats"][key][0]
        if not (math.isfinite(ma) and math.isfinite(mb)):
            parts.append(f"{header}: n/a")
            continue
        compared += 1
        better = (ma > mb) if higher else (ma < mb)
        tie = round(ma, decimals) == round(mb, decimals)
        agree += int(better and not tie)
        paired = [(_float(a["per_case"][c].get(key)), _float(b["per_case"][c].get(key)))
                  for c in a["per_case"] if c in b["per_case"]]
        paired = [(x, y) for x, y in paired if math.isfinite(x) and math.isfinite(y)]
        wins = sum(1 for x, y in paired if (x > y if higher else x < y))
        verdict = "tie" if tie else (f"{first} better" if better else f"{second} better")
        parts.append(f"{header}: {verdict} ({ma:.{decimals}f} vs {mb:.{decimals}f}; {first} better in {wins}/{len(paired)} cases)")
    lines = [f"Ordering {first} vs {second} per metric (the paper has {first} better on all six):"]
    lines += [f"- {p}" for p in parts]
    lines.append(f"- The paper's ordering reproduces on {agree} of {compared} metrics" +
                 (" — it reproduces." if compared and agree == compared else " — it does not fully reproduce."))
    return lines


def machine_info() -> Dict[str, Any]:
    """CPU model, cores, RAM and GPU of this process's machine."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as stream:
            for line in stream:
                if line.lower().startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (AttributeError, ValueError, OSError):
        ram = math.nan
    gpus: List[str] = []
    try:
        import torch

        if torch.cuda.is_available():
            gpus = [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]
    except Exception:
        pass
    return {"host": platform.node(), "system": f"{platform.system()} {platform.release()}", "cpu": cpu,
            "cores": os.cpu_count(), "ram_gib": round(ram, 1) if math.isfinite(ram) else None, "gpus": gpus}


def all_versions() -> Dict[str, str]:
    from ..optimiser import versions

    out = dict(versions())
    for name in ("dask", "distributed", "matplotlib"):
        try:
            out[name] = __import__(name).__version__
        except Exception:
            out[name] = "not installed"
    return out


def write_summary(out: Path, config: BenchmarkConfig, rows: Sequence[Dict[str, str]], record: Dict[str, Any]) -> Path:
    tables = summary_tables(rows, config.modes)
    machine = record.get("machine", {})
    versions = record.get("versions", {})
    lines = [
        f"# SDFCAR benchmark — suite `{config.suite}`, protocol `{config.protocol}`, preset `{config.preset}`",
        "",
        "Mean ± sample standard deviation over the finished cases (failed runs excluded and listed below); "
        "best value per column in **bold**. clDice is Shit et al.'s centreline Dice, skeleton-Dice the Dice of the "
        "two skeletons (what the public NeCA/SDF-CAR code reports as clDice); every connected piece is in the skeleton, "
        "also the pieces scikit-image's skeletonize erases whole; see `SDFCARLib/metrics.py`.",
        "",
    ]
    if not tables:
        lines += ["No finished rows yet.", ""]
    for table in tables:
        count = len(table["cases"])
        lines += [f"## {table['title']}", "", f"{count} case{'s' if count != 1 else ''}.", "", _table_markdown(table), ""]
        side = side_by_side_lines(table)
        lines += side + ([""] if side else [])
        lines += ordering_lines(table) + [""]
    failed = [r for r in rows if r["status"] != "ok"]
    if failed:
        lines += ["## Failed runs", ""]
        lines += [f"- `{r['case']}` × `{r['mode']}`: {r['error']} (traceback: `{r.get('traceback_file', '')}`)" for r in failed]
        lines.append("")
    seeds = record.get("seeds", [])
    gpu = ", ".join(machine.get("gpus") or []) or "none"
    identity = config.identity()
    lines += [
        "## Reproduce", "", "```", config.command_line(), "```", "",
        f"- configuration `{config.config_id()}`: " + json.dumps({k: v for k, v in identity.items() if k != "settings"}, sort_keys=True),
        "- optimiser settings (besides mode and seed): " + ", ".join(f"{k}={v}" for k, v in identity["settings"].items()),
        f"- seeds (per case, tree and optimiser): {', '.join(map(str, seeds))}",
        "- versions: " + ", ".join(f"{k} {v}" for k, v in versions.items()),
        f"- machine (this process): {machine.get('cpu')}, {machine.get('cores')} cores, {machine.get('ram_gib')} GiB RAM, GPU: {gpu}",
        f"- cluster: {record.get('cluster', {}).get('description', 'n/a')}",
        "- devices that ran the reconstructions: " + (", ".join(sorted({r.get('device', '') for r in rows if r.get('device')})) or "n/a"),
        f"- date: {record.get('finished') or record.get('started')}",
        "",
    ]
    path = out / "summary.md"
    write_text_atomically(path, "\n".join(lines))
    return path


def write_box_plots(out: Path, rows: Sequence[Dict[str, str]], modes: Sequence[str]) -> List[Path]:
    """One PNG per (suite tree, metric): a box per method over the finished cases."""
    # The Agg canvas directly, not pyplot: no global backend switch in the caller's process (Slicer).
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    folder = out / "figures"
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for table in summary_tables(rows, modes):
        group = safe_name(table["tree"] if table["suite"].split(":")[0] != "721a" else "721a")
        for key, header, scale, _, _ in TABLE_METRICS:
            data, labels = [], []
            for method in table["methods"]:
                values = [_float(r.get(key)) * scale for r in method["per_case"].values()]
                values = [v for v in values if math.isfinite(v)]
                if values:
                    data.append(values)
                    labels.append(method["mode"])
            if not data:
                continue
            figure = Figure(figsize=(1.2 + 1.1 * len(data), 3.2))
            FigureCanvasAgg(figure)
            axes = figure.add_subplot()
            axes.boxplot(data)
            axes.set_xticks(range(1, len(labels) + 1))
            axes.set_xticklabels(labels, rotation=20)
            axes.set_ylabel(header)
            axes.set_title(f"{table['title']}: {header}", fontsize=9)
            figure.tight_layout()
            path = folder / f"box_{group}_{key}.png"
            figure.savefig(path, dpi=100)
            written.append(path)
    return written
