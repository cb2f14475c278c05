"""Writing a reconstruction's results into a folder, all at once or not at all.

Files (all in physical LPS millimetres, see ``geometry.py``)
    ``occupancy.nrrd``          float32 occupancy in [0, 1] on the reconstruction grid
    ``field.nrrd``              float32 raw field (SDF value s, or the occupancy logit)
    ``segmentation.seg.nrrd``   Slicer segmentation of occupancy >= threshold (one segment)
    ``surface.vtk``             marching-cubes surface of the occupancy at the threshold (0.5),
                                i.e. the field's zero level set; ``SPACE=LPS`` header
    ``report.json``             the reconstruction's report, the files, the surface size,
                                warnings, metrics against a ground truth when one is given and
                                those of the visual-hull baseline (NaN written as null)
    ``qa_view<n>.png``          per view, the mask against the result's projection (``qa.py``):
                                both, result only, mask only, the largest blobs outlined, a legend
    ``scene.mrml``              a Slicer scene with the segmentation and the surface, when
                                slicer-core is installed (``mrml.py``); otherwise the report says
                                why it was skipped

Atomicity
    Everything is written into a temporary folder beside the destination and moved in only when
    every file succeeded; existing files are replaced only with ``overwrite=True``, and a failure
    at any point leaves the destination as it was.
"""

from __future__ import annotations

import datetime
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np

from .geometry import VolumeGrid
from .io import process_umask, write_json, write_segmentation_nrrd, write_surface_vtk, write_volume_nrrd
from .qa import qa_file_name, qa_title, write_qa_png
from .settings import MASK_THRESHOLD_MM, PRESETS, make_settings

PathLike = Union[str, Path]

RESULT_FILES = {
    "occupancy": "occupancy.nrrd",
    "field": "field.nrrd",
    "segmentation": "segmentation.seg.nrrd",
    "surface": "surface.vtk",
    "scene": "scene.mrml",
    "report": "report.json",
}

_BACKUP = ".replaced"


def result_file_names(view_count: int) -> List[str]:
    """Every file a result folder of ``view_count`` views may hold: ``RESULT_FILES`` and the QA overlays."""
    return list(RESULT_FILES.values()) + [qa_file_name(n) for n in range(1, view_count + 1)]


class OutputError(ValueError):
    """The output folder cannot take the results; the message says why and what to do."""


# --- the output folder --------------------------------------------------------------------------
def check_destination(out_dir: PathLike, names: Sequence[str], overwrite: bool = False) -> None:
    """Refuse a destination that is a file, or that holds any of ``names`` unless ``overwrite``."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"output path {out_dir} exists and is not a folder; choose a folder for the results")
    # the results are staged beside the folder and the missing folders made: found now, not after minutes of work
    nearest = next(p for p in (out_dir.absolute(), *out_dir.absolute().parents) if p.exists())
    if not nearest.is_dir():
        raise OutputError(f"output path {out_dir} lies inside {nearest}, which is a file, not a folder; choose a folder "
                          "for the results")
    try:  # a real trial: permissions alone do not tell (root on a read-only or virtual file system)
        os.rmdir(tempfile.mkdtemp(prefix=".sdfcar-write-check-", dir=str(nearest)))
    except OSError as exc:
        made = "written to" if nearest == out_dir.absolute() else "made there"
        raise OutputError(f"cannot write in {nearest} ({exc.strerror or exc}): the output folder {out_dir} cannot be "
                          f"{made}; choose a folder you can write to") from None
    if overwrite or not out_dir.is_dir():
        return
    existing = [n for n in names if (out_dir / n).exists()]
    if existing:
        raise OutputError(
            f"{out_dir} already holds {', '.join(existing)}; choose another output folder or pass --overwrite "
            "(overwrite=True) to replace them")


@contextmanager
def staged_directory(out_dir: PathLike, names: Sequence[str], overwrite: bool = False) -> Iterator[Path]:
    """A temporary folder whose files replace ``out_dir``'s when the ``with`` block succeeds.

    ``names`` are the files the block may write: they are checked before anything is written,
    and with ``overwrite`` any of them left in ``out_dir`` from an earlier run (and not written
    this time) is removed so that the folder does not mix two runs.
    """
    out_dir = Path(out_dir).absolute()
    check_destination(out_dir, names, overwrite)
    created: List[Path] = []
    for parent in reversed(out_dir.parents):
        if not parent.exists():
            parent.mkdir()
            created.append(parent)
    succeeded = False
    staging: Optional[Path] = None
    try:
        staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.sdfcar-", dir=str(out_dir.parent)))
        yield staging
        _commit(staging, out_dir, names, overwrite)
        succeeded = True
    finally:
        if staging is not None and staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
        if not succeeded:
            for parent in reversed(created):
                try:
                    parent.rmdir()
                except OSError:
                    pass


def _commit(staging: Path, out_dir: Path, names: Sequence[str], overwrite: bool) -> None:
    produced = sorted(p.name for p in staging.iterdir())
    if not out_dir.exists():
        # mkdtemp made the folder private (0700); give it the permissions of a normal folder.
        os.chmod(staging, 0o777 & ~process_umask())
        os.rename(staging, out_dir)
        return
    check_destination(out_dir, produced, overwrite)  # the folder may have changed meanwhile
    replaced = [n for n in sorted(set(names) | set(produced)) if (out_dir / n).exists()]
    backup = staging / _BACKUP
    moved_out: List[str] = []
    moved_in: List[str] = []
    try:
        if replaced:
            backup.mkdir()
            for n in replaced:
                os.replace(out_dir / n, backup / n)
                moved_out.append(n)
        for n in produced:
            os.replace(staging / n, out_dir / n)
            moved_in.append(n)
    except BaseException:
        for n in moved_in:
            os.replace(out_dir / n, staging / n)
        for n in moved_out:
            os.replace(backup / n, out_dir / n)
        raise


def previous_analyses(out_dir: PathLike) -> List[str]:
    """The names of the folders in ``out_dir`` that hold an analysis SDFCAR wrote (analysis/, analysis-2/ …:
    analysis.json and only the files ``analyse`` writes); a folder holding anything else is the user's."""
    import re

    from .analysis.outputs import ANALYSIS_FILES

    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        return []
    found = []
    for folder in sorted(out_dir.iterdir()):
        if not (folder.is_dir() and re.fullmatch(r"analysis(-\d+)?", folder.name) and (folder / "analysis.json").is_file()):
            continue
        if all(f.is_file() and (f.name in ANALYSIS_FILES or re.fullmatch(r"profile_branch\d+\.csv", f.name))
               for f in folder.iterdir()):
            found.append(folder.name)
    return found


# --- pieces -------------------------------------------------------------------------------------
def surface_mesh(volume: np.ndarray, grid: VolumeGrid, level: float = 0.5) -> Tuple[np.ndarray, np.ndarray]:
    """Marching-cubes surface of ``volume`` at ``level``: vertices (N, 3) in LPS mm, faces (M, 3).

    The volume is padded with one voxel of zeros so that vessels touching the grid's border get
    closed surfaces; every vertex stays inside the grid's bounding box. Returns empty arrays when
    the volume never reaches ``level``.
    """
    from skimage.measure import marching_cubes

    volume = np.asarray(volume, dtype=np.float32)
    if volume.shape != tuple(grid.shape):
        raise ValueError(f"volume shape {volume.shape} does not match the grid shape {tuple(grid.shape)}")
    if not (volume.size and float(volume.max()) > level):
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    padded = np.pad(volume, 1, mode="constant", constant_values=min(0.0, float(volume.min())))
    spacing = np.asarray(grid.spacing_mm, float)
    vertices, faces, _, _ = marching_cubes(padded, level=level, spacing=tuple(spacing))
    # Padded index p is grid index p - 1.
    return vertices + grid.origin - spacing, faces.astype(np.int64)


def ground_truth_metrics(prediction: np.ndarray, label: np.ndarray, grid: VolumeGrid, views=None,
                         masks: Optional[Sequence[np.ndarray]] = None) -> Dict[str, Any]:
    """Metrics of ``prediction`` and of the masks' visual hull against ``label`` (``metrics.py``).

    With ``views``, projection metrics are added and, when ``masks`` is None, the masks are the
    label's own simulated ones (line integral > 0.2 mm), as in the simulation protocol.
    """
    from .hull import visual_hull
    from .metrics import evaluate
    from .phantoms import simulate_views

    label = np.asarray(label).astype(bool)
    if label.shape != tuple(grid.shape):
        raise ValueError(
            f"the ground truth has shape {label.shape} but the reconstruction grid is {tuple(grid.shape)}; "
            "give a ground truth on the reconstruction grid")
    out: Dict[str, Any] = {"prediction": evaluate(prediction, label, grid, views, masks)}
    if views:
        if masks is None and label.any():
            _, masks = simulate_views(label, grid, views, MASK_THRESHOLD_MM)
        if masks is not None:
            hull = visual_hull([np.asarray(m, bool) for m in masks], views, grid)
            out["visual_hull"] = evaluate(hull, label, grid, views, masks)
    return out


def _write_scene(staging: Path, name: str, result, attributes: Dict[str, str]) -> Dict[str, Any]:
    try:
        from .mrml import write_result_scene
    except (ImportError, AttributeError) as exc:
        return {"written": False, "reason": f"the MRML bridge is not available ({exc})"}
    try:
        path = write_result_scene(
            staging, name, result.geometry, staging / RESULT_FILES["segmentation"], staging / RESULT_FILES["surface"], attributes)
    except (ImportError, AttributeError) as exc:
        return {"written": False, "reason": f"slicer-core is not available ({exc}); install it with "
                                            "pip install 'SDFCARLib[headless]' to get scene.mrml"}
    if Path(path).resolve() != (staging / RESULT_FILES["scene"]).resolve():
        raise RuntimeError(f"write_result_scene wrote {path}, expected {RESULT_FILES['scene']} in the output folder")
    return {"written": True}


def _empty_result_hint(settings) -> str:
    """What to try after an empty result: a fit cut short names its steps against its preset's."""
    steps, warmup = settings.optimisation.steps, settings.optimisation.warmup_steps
    preset = settings.run.preset
    preset_steps = make_settings(preset).optimisation.steps if preset in PRESETS else None
    if steps <= 2 * warmup or (preset_steps and steps < preset_steps / 4):
        fix = f"leave --steps out to run the {preset} preset's {preset_steps}, or give more" if preset_steps else \
            "give more --steps"
        return f"the fit ran only {steps} steps ({min(warmup, steps)} of them warming the learning rates up): {fix}"
    return "try another seed (--seed) or check the masks (their overlays, and report.json's reprojection QA)"


def write_reconstruction(
    result,
    out_dir: PathLike,
    name: Optional[str] = None,
    label: Optional[np.ndarray] = None,
    overwrite: bool = False,
    masks: Optional[Sequence[np.ndarray]] = None,
    extra: Optional[Dict[str, Any]] = None,
) -> Dict[str, Path]:
    """Write ``result`` (an ``optimiser.Reconstruction``) into ``out_dir``; return the files' paths.

    ``label``: optional ground truth (bool ``[i, j, k]`` on the reconstruction grid) for metrics;
    ``masks``: the views' vessel masks for the visual-hull baseline (default: the label's
    simulated masks); ``extra``: more entries for report.json (e.g. the input files).
    Problems that do not stop the writing (an empty segmentation, no slicer-core for the
    scene) are listed under ``warnings`` in report.json. With ``overwrite`` the analyses of the
    previous result (``analysis/``, ``analysis-2/`` …, as ``analyse`` writes them) are replaced too:
    they describe a result that is gone. The user's own files and folders stay.
    """
    out_dir = Path(out_dir)
    grid = result.geometry.volume
    name = name or out_dir.name or "SDFCAR"
    level = float(result.settings.region.threshold)
    report: Dict[str, Any] = dict(result.report)
    report_warnings: List[str] = list(report.get("warnings", []))
    qa_masks = list(getattr(result, "qa_masks", []))
    names = result_file_names(len(result.geometry.views))
    qa_names = names[len(RESULT_FILES):]
    if overwrite:
        names = names + previous_analyses(out_dir)
    qa_numbers = report.get("reprojection_qa") or []
    with staged_directory(out_dir, names, overwrite) as staging:
        write_volume_nrrd(staging / RESULT_FILES["occupancy"], result.occupancy, grid)
        write_volume_nrrd(staging / RESULT_FILES["field"], result.field, grid)
        write_segmentation_nrrd(staging / RESULT_FILES["segmentation"], result.segmentation, grid, name=name)
        vertices, faces = surface_mesh(result.occupancy, grid, level)
        if len(faces) == 0:
            report_warnings.append(
                f"the segmentation is empty (no voxel reaches occupancy {level:g}): surface.vtk holds no triangles; "
                + _empty_result_hint(result.settings))
        try:
            write_surface_vtk(staging / RESULT_FILES["surface"], vertices, faces)
        except ImportError as exc:  # vtk comes with Slicer or slicer-core, not with the core install
            report_warnings.append(f"surface.vtk was not written: the 'vtk' package is missing ({exc}); "
                                   "install it with pip install 'SDFCARLib[headless]'")
        attributes = {
            "SDFCAR.method": str(report.get("method", "")),
            "SDFCAR.mode": result.settings.run.mode,
            "SDFCAR.preset": result.settings.run.preset,
            "SDFCAR.seed": str(result.settings.run.seed),
            "SDFCAR.geometryDigest": result.geometry.digest(),
            "SDFCAR.coordinateSystem": "LPS",
        }
        one_view = list(getattr(result, "one_view_pixels", []))
        for n, (projected, mask) in enumerate(qa_masks, start=1):
            title = qa_title(n, qa_numbers[n - 1]) if n <= len(qa_numbers) else f"view {n}"
            write_qa_png(staging / qa_file_name(n), None, projected, mask, title,
                         one_view[n - 1] if n <= len(one_view) else None)
        scene = _write_scene(staging, name, result, attributes)
        if not scene["written"]:
            report_warnings.append(f"scene.mrml was not written: {scene['reason']}")
        report.update({
            "name": name,
            "written_at": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
            "coordinate_system": "LPS",
            "files": {**{key: file for key, file in RESULT_FILES.items() if (staging / file).exists() or key == "report"},
                      **{Path(file).stem: file for file in qa_names if (staging / file).exists()}},
            "surface": {"vertices": int(len(vertices)), "triangles": int(len(faces)), "level": level},
            "scene": scene,
        })
        if label is not None:
            report["metrics"] = ground_truth_metrics(result.segmentation, label, grid, result.geometry.views, masks)
        report.update(extra or {})
        report["warnings"] = report_warnings
        write_json(staging / RESULT_FILES["report"], report)
        written = {key: file for key, file in RESULT_FILES.items() if (staging / file).exists()}
        written.update({Path(file).stem: file for file in qa_names if (staging / file).exists()})
    return {key: out_dir / file for key, file in written.items()}
