"""Reading and writing SDFCAR's files: detector images, volumes, segmentations and surfaces.

Conventions (see ``geometry.py``)
    Detector images are returned as 2D arrays ``(rows, cols)`` with row 0 at the top, as they
    are stored in PNG, TIFF and in NRRD (whose fastest axis is the image's column axis).
    Volumes are returned as arrays ``[i, j, k]`` with i along LPS x, j along y, k along z, and
    a ``VolumeGrid`` with their own spacing and position. Files in another anatomical frame
    (NIfTI is RAS-based; NRRD may say RAS or LAS) are converted to LPS; axes stored flipped
    or permuted are flipped/transposed into the +x, +y, +z order. Rotated (oblique) volumes
    are refused: SDFCAR's grids are axis-aligned and resampling is the user's choice to make.

Written files
    NRRD volumes use space ``left-posterior-superior``, space directions diag(spacing) and
    space origin = centre of voxel (0, 0, 0), gzip-compressed. Segmentations are Slicer
    ``.seg.nrrd`` files (one segment, label value 1, with the ``Segment0_*`` and
    ``Segmentation_*`` fields Slicer's ``vtkMRMLSegmentationStorageNode`` writes and reads).
    Surfaces are legacy VTK polydata in LPS millimetres with ``SPACE=LPS`` in the header line,
    the marker Slicer's ``vtkMRMLModelStorageNode`` reads to convert them to RAS.

Every problem with an input raises ``InputError`` (a ``ValueError``) whose message names the
file, what is wrong and how to fix it.
"""

from __future__ import annotations

import errno
import json
import math
import os
import tempfile
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable, List, Optional, Sequence, Tuple, Union

import numpy as np

from .geometry import VolumeGrid
from .masks import MaskError, binarise_mask

PathLike = Union[str, Path]

IMAGE_FORMATS = "PNG (.png), TIFF (.tif, .tiff), NRRD (.nrrd, .nhdr) or NumPy (.npy)"
VOLUME_FORMATS = "NRRD (.nrrd, .nhdr, .seg.nrrd) or NIfTI (.nii, .nii.gz)"
CENTRELINE_FORMATS = "VTK polydata (.vtk, .vtp)"

#: Largest off-axis component of a unit axis direction still taken as axis-aligned: 1e-3 rad
#: moves a point 0.1 mm over 100 mm, well below a voxel.
AXIS_TOLERANCE = 1e-3

# NRRD anatomical spaces → sign flips that take their coordinates to LPS.
_SPACE_TO_LPS = {
    "left-posterior-superior": (1.0, 1.0, 1.0),
    "lps": (1.0, 1.0, 1.0),
    "right-anterior-superior": (-1.0, -1.0, 1.0),
    "ras": (-1.0, -1.0, 1.0),
    "left-anterior-superior": (1.0, -1.0, 1.0),
    "las": (1.0, -1.0, 1.0),
}

# What Slicer writes for a new segment (a generic "Tissue" terminology entry).
_SLICER_DEFAULT_TAGS = (
    "TerminologyEntry:Segmentation category and type - 3D Slicer General Anatomy list"
    "~SCT^85756007^Tissue~SCT^85756007^Tissue~^^~Anatomic codes - DICOM master list~^^~^^|"
)


class InputError(ValueError):
    """An input file is missing, unreadable or unsuitable; the message says which and why."""


# --- helpers ------------------------------------------------------------------------------------
def _suffix(path: Path) -> str:
    name = path.name.lower()
    for double in (".seg.nrrd", ".nii.gz"):
        if name.endswith(double):
            return double
    return path.suffix.lower()


def _existing_file(path: PathLike, what: str) -> Path:
    path = Path(path)
    if not path.exists():
        raise InputError(f"{what} file not found: {path}; check the path")
    if not path.is_file():
        raise InputError(f"{what} path {path} is not a file")
    return path


def _read_nrrd(path: Path, index_order: str):
    import nrrd

    try:
        return nrrd.read(str(path), index_order=index_order)
    except Exception as exc:  # pynrrd raises several types for malformed files
        raise InputError(f"cannot read {path} as NRRD: {exc}") from exc


# --- detector images ----------------------------------------------------------------------------
def _single_channel(data: np.ndarray, path: Path) -> np.ndarray:
    """Grey image from grey, grey+alpha, RGB or RGBA data whose colour channels are equal."""
    if data.ndim != 3 or data.shape[-1] not in (2, 3, 4):
        return data
    channels = data.shape[-1]
    colour = data[..., :3] if channels >= 3 else data[..., :1]
    if channels in (2, 4):
        alpha = data[..., -1]
        if np.any(alpha != alpha.flat[0]):
            raise InputError(
                f"{path} has a transparency (alpha) channel that varies; save the mask as a "
                "greyscale image without transparency")
    if np.any(colour != colour[..., :1]):
        raise InputError(
            f"{path} is a colour image with differing red/green/blue channels; save the mask or "
            "frame as a single-channel greyscale image")
    return colour[..., 0]


def read_image(path: PathLike, what: str = "image") -> np.ndarray:
    """A 2D detector image ``(rows, cols)`` (row 0 = top) from PNG, TIFF, NRRD or .npy.

    Colour images are accepted when their colour channels are equal (and an alpha channel, if
    any, is constant); a 3D NRRD/TIFF is accepted when one of its axes has length 1.
    """
    path = _existing_file(path, what)
    suffix = _suffix(path)
    if suffix == ".png":
        import imageio.v3 as iio

        try:
            data = np.asarray(iio.imread(path, plugin="pillow"))
        except Exception as exc:
            raise InputError(f"cannot read {path} as a PNG image: {exc}") from exc
    elif suffix in (".tif", ".tiff"):
        import tifffile

        try:
            data = np.asarray(tifffile.imread(path))
        except Exception as exc:
            raise InputError(f"cannot read {path} as a TIFF image: {exc}") from exc
    elif suffix in (".nrrd", ".nhdr"):
        # C order puts NRRD's fastest axis (image columns) last: (rows, cols).
        data, _ = _read_nrrd(path, index_order="C")
    elif suffix == ".npy":  # as the job folders store the views' images
        try:
            data = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise InputError(f"cannot read {path} as a NumPy image: {exc}") from exc
    else:
        raise InputError(f"{path}: unsupported {what} format {suffix or '(no extension)'!r}; use {IMAGE_FORMATS}")
    if data.ndim > 2:
        data = np.squeeze(data)  # e.g. a 3D NRRD or TIFF with one frame
    data = _single_channel(data, path)
    if data.ndim != 2:
        raise InputError(
            f"{path} holds {data.ndim}-D data of shape {data.shape}; a {what} must be a single 2D image "
            "(one frame of the detector)")
    if data.dtype == bool:
        return data
    if not np.issubdtype(data.dtype, np.number):
        raise InputError(f"{path} holds non-numeric data ({data.dtype}); a {what} must hold numbers")
    return data


def _check_shape(data: np.ndarray, path: Path, detector_shape: Optional[Sequence[int]], what: str) -> None:
    if detector_shape is not None and tuple(data.shape) != tuple(int(s) for s in detector_shape):
        expected = tuple(int(s) for s in detector_shape)
        if tuple(data.shape) == expected[::-1]:
            raise InputError(f"{path}: {what} shape {tuple(data.shape)} (rows, cols) is the detector shape {expected} "
                             "with rows and columns swapped: transpose the image (it was saved columns first)")
        raise InputError(
            f"{path}: {what} shape {tuple(data.shape)} (rows, cols) differs from the detector shape "
            f"{expected} in the geometry; use the {what} of that view or fix detector_shape in GEOM.json")


def read_mask(path: PathLike, detector_shape: Optional[Sequence[int]] = None, what: str = "mask",
              label: Optional[float] = None) -> np.ndarray:
    """A binary vessel mask (bool ``(rows, cols)``) by the package's one mask rule (``masks.binarise_mask``).

    ``label``: the vessel label of a label image (default: the image must be binary).
    """
    path = Path(path)
    data = read_image(path, what)
    _check_shape(data, path, detector_shape, what)
    try:
        return binarise_mask(data, detector_shape, label, source=f"{path}")
    except MaskError as exc:
        raise InputError(str(exc)) from None


def read_line_integral(path: PathLike, detector_shape: Optional[Sequence[int]] = None) -> np.ndarray:
    """A line-integral image (float32 mm, ``(rows, cols)``): finite, non-negative, not all zero."""
    path = Path(path)
    data = read_image(path, "line-integral image")
    _check_shape(data, path, detector_shape, "line-integral image")
    data = data.astype(np.float32)
    if not np.all(np.isfinite(data)):
        raise InputError(f"{path}: the line-integral image contains NaN or infinite values; fix the image")
    if data.min() < 0:
        raise InputError(f"{path}: line integrals are path lengths (mm) and cannot be negative (minimum {data.min():.3g})")
    if not data.any():
        raise InputError(f"{path}: the line-integral image is all zero; there is no vessel in this view")
    values = np.unique(data)
    # path lengths through a tree vary along and across every vessel; one value, at a mask's foreground level, is a mask
    if values.size == 2 and values[1] in (1.0, 255.0, 65535.0):
        raise InputError(f"{path} holds only the values {values[0]:g} and {values[1]:g}: a mask, not line integrals (path "
                         "lengths in mm); give it as a mask (--mask) instead")
    return data


def write_mask_png(path: PathLike, mask: np.ndarray) -> Path:
    """Write a binary mask as an 8-bit greyscale PNG (0 / 255), maximally compressed."""
    import imageio.v3 as iio

    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"a mask must be 2D (rows, cols), got shape {mask.shape}")
    path = Path(path)
    iio.imwrite(path, np.where(mask != 0, 255, 0).astype(np.uint8), extension=".png", compress_level=9)
    return path


def write_image_nrrd(path: PathLike, image: np.ndarray, pixel_spacing_mm: Optional[Sequence[float]] = None,
                     content: str = "") -> Path:
    """Write a 2D float image ``(rows, cols)`` as a gzip NRRD (e.g. a line integral in mm)."""
    import nrrd

    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 2:
        raise ValueError(f"an image must be 2D (rows, cols), got shape {image.shape}")
    header: "OrderedDict[str, object]" = OrderedDict(encoding="gzip", kinds=["domain", "domain"])
    if pixel_spacing_mm is not None:
        # Header lists are in file order: fastest axis (columns) first.
        header["spacings"] = [float(pixel_spacing_mm[1]), float(pixel_spacing_mm[0])]
    if content:
        header["content"] = content
    nrrd.write(str(path), image, header, index_order="C")
    return Path(path)


# --- volumes ------------------------------------------------------------------------------------
def _axis_aligned(data: np.ndarray, axes: np.ndarray, origin: np.ndarray, path: Path) -> Tuple[np.ndarray, VolumeGrid]:
    """Reorder ``data`` (file axes) so that its axes run along +x, +y, +z of LPS.

    ``axes[:, a]`` is the LPS step (mm) of one voxel along file axis a; ``origin`` the LPS
    position of file voxel (0, 0, 0).
    """
    axes = np.asarray(axes, float)
    origin = np.asarray(origin, float)
    if not np.all(np.isfinite(axes)) or not np.all(np.isfinite(origin)):
        raise InputError(f"{path}: the voxel-to-world matrix or origin is not finite; fix the file's header")
    lengths = np.linalg.norm(axes, axis=0)
    if np.any(lengths <= 0):
        raise InputError(f"{path}: a voxel spacing is zero; fix the file's spacing")
    unit = axes / lengths
    world_axis = np.argmax(np.abs(unit), axis=0)
    off_axis = np.sqrt(np.maximum(0.0, 1.0 - np.max(np.abs(unit), axis=0) ** 2))
    if np.any(off_axis > AXIS_TOLERANCE) or len(set(world_axis.tolist())) != 3:
        angle = math.degrees(math.asin(min(1.0, float(off_axis.max()))))
        raise InputError(
            f"{path}: the volume is rotated (oblique) relative to the patient axes (by up to {angle:.2f}°); "
            "SDFCAR needs an axis-aligned volume — resample it onto an axis-aligned grid first "
            "(e.g. Slicer's 'Resample Scalar/Vector/DWI Volume' or 'Crop Volume' with 'Isotropic spacing')")
    # New axis w holds file axis perm[w]; a negative direction becomes a flip.
    perm = [int(np.flatnonzero(world_axis == w)[0]) for w in range(3)]
    signs = np.array([np.sign(unit[w, perm[w]]) for w in range(3)])
    shape_file = np.asarray(data.shape)
    for a in range(3):
        if np.sign(unit[world_axis[a], a]) < 0:
            origin = origin + (shape_file[a] - 1) * axes[:, a]
    data = np.transpose(data, perm)
    flips = tuple(w for w in range(3) if signs[w] < 0)
    if flips:
        data = np.flip(data, axis=flips)
    spacing = tuple(float(lengths[perm[w]]) for w in range(3))
    shape = tuple(int(s) for s in data.shape)
    center = origin + (np.asarray(shape) - 1) / 2.0 * np.asarray(spacing)
    return np.ascontiguousarray(data), VolumeGrid(shape, spacing, tuple(float(c) for c in center))


def _nrrd_volume(path: Path, collapse_layers: bool) -> Tuple[np.ndarray, VolumeGrid]:
    data, header = _read_nrrd(path, index_order="F")  # data[i, j, k]: file axes, fastest first
    directions = header.get("space directions")
    if directions is None:
        raise InputError(
            f"{path} has no 'space directions' ({'only spacings' if 'spacings' in header else 'nor spacings'}); "
            "SDFCAR needs to know where the volume lies: save it with its spacing and origin "
            "(e.g. from Slicer), space 'left-posterior-superior'")
    directions = np.asarray(directions, dtype=float)
    # Non-spatial axes (a segmentation's layers, vector components) have 'none' directions.
    spatial = np.all(np.isfinite(directions), axis=1)
    if collapse_layers and data.ndim == 4 and spatial.sum() == 3 and not spatial[0]:
        data = np.any(data != 0, axis=0)
        directions = directions[1:]
    elif data.ndim != 3 or not np.all(spatial):
        raise InputError(f"{path} holds {data.ndim}-D data of shape {data.shape}; a volume must be 3D")
    units = [str(u).strip().lower() for u in header.get("space units", [])]
    if any(u not in ("mm", "millimeter", "millimeters", "millimetre", "millimetres") for u in units):
        raise InputError(f"{path}: its space units are {units}, not mm; SDFCAR places volumes in mm: save it in mm "
                         "(e.g. resample or rescale it in Slicer)")
    space = str(header.get("space", "left-posterior-superior")).lower()
    if space not in _SPACE_TO_LPS:
        raise InputError(
            f"{path}: space {header.get('space')!r} is not an anatomical frame SDFCAR can place; "
            "use 'left-posterior-superior' (LPS) or 'right-anterior-superior' (RAS)")
    flip = np.asarray(_SPACE_TO_LPS[space])
    origin = np.asarray(header.get("space origin", np.zeros(3)), dtype=float)
    if origin.shape != (3,):
        raise InputError(f"{path}: 'space origin' must have 3 components, got {origin.tolist()}")
    axes = (directions * flip[None, :]).T  # columns: LPS step per file axis
    return _axis_aligned(data, axes, origin * flip, path)


def _nifti_volume(path: Path) -> Tuple[np.ndarray, VolumeGrid]:
    import nibabel

    try:
        image = nibabel.load(str(path))
        data = np.asanyarray(image.dataobj)
    except Exception as exc:
        raise InputError(f"cannot read {path} as NIfTI: {exc}") from exc
    while data.ndim > 3 and data.shape[-1] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise InputError(f"{path} holds {data.ndim}-D data of shape {data.shape}; a volume must be 3D")
    unit = image.header.get_xyzt_units()[0] if hasattr(image.header, "get_xyzt_units") else "unknown"
    scale = {"mm": 1.0, "meter": 1000.0, "micron": 1e-3}.get(unit, 1.0)  # "unknown" (unset): taken as mm, as is usual
    affine = np.diag([-scale, -scale, scale, 1.0]) @ np.asarray(image.affine, float)  # NIfTI world is RAS
    return _axis_aligned(np.asarray(data), affine[:3, :3], affine[:3, 3], path)


def read_volume(path: PathLike, what: str = "volume") -> Tuple[np.ndarray, VolumeGrid]:
    """A 3D volume ``[i, j, k]`` (LPS axis order) and its grid, from NRRD or NIfTI."""
    path = _existing_file(path, what)
    suffix = _suffix(path)
    if suffix in (".nrrd", ".nhdr", ".seg.nrrd"):
        return _nrrd_volume(path, collapse_layers=False)
    if suffix in (".nii", ".nii.gz"):
        return _nifti_volume(path)
    raise InputError(f"{path}: unsupported {what} format {suffix or '(no extension)'!r}; use {VOLUME_FORMATS}")


def label_file_warnings(path: PathLike, what: str = "label") -> List[str]:
    """What ``read_label`` takes from the file at ``path`` that a user may not expect, read from its header:
    the segments of a segmentation merged into one vessel label, and a NIfTI file whose two placements
    (sform and qform) disagree. Empty for files it cannot read (``read_label`` names what is wrong)."""
    path = Path(path)
    suffix = _suffix(path)
    warnings = []
    if suffix in (".nrrd", ".nhdr", ".seg.nrrd"):
        import nrrd

        try:
            header = nrrd.read_header(str(path))
        except Exception:
            return []
        names = [str(header[f"Segment{n}_Name"]) for n in range(len(header)) if f"Segment{n}_Name" in header]
        if len(names) > 1:
            warnings.append(f"{path.name}: its {len(names)} segments ({', '.join(names)}) are merged into one {what}: "
                            "every segment counts as vessel (export the vessel segment alone to score only it)")
    elif suffix in (".nii", ".nii.gz"):
        import nibabel

        try:
            header = nibabel.load(str(path)).header
            sform, qform = header.get_sform(coded=True)[0], header.get_qform(coded=True)[0]
        except Exception:
            return []
        if sform is not None and qform is not None:
            corners = np.array([[i, j, k, 1.0] for i in (0, 1) for j in (0, 1) for k in (0, 1)]) \
                * np.r_[np.asarray(header.get_data_shape()[:3], float) - 1, 1.0]
            disagreement_mm = float(np.max(np.linalg.norm(corners @ (sform - qform)[:3].T, axis=1)))
            if disagreement_mm > 0.01:
                warnings.append(f"{path.name}: its sform and qform place the volume up to {disagreement_mm:.2f} mm apart; "
                                "SDFCAR places it by the sform (as nibabel does); a tool that reads the qform puts it "
                                "elsewhere: check where the volume lies, and save it with one placement")
    return warnings


def read_label(path: PathLike, grid: Optional[VolumeGrid] = None, threshold: Optional[float] = None,
               what: str = "label") -> Tuple[np.ndarray, VolumeGrid]:
    """A binary vessel volume (bool ``[i, j, k]``) and its grid.

    Accepts a labelmap or segmentation volume (NRRD, ``.seg.nrrd`` with any number of segments
    or layers, NIfTI; non-zero = vessel), a continuous volume with ``threshold`` (value >=
    threshold = vessel), or a centreline with radii (``.vtk``/``.vtp``), which is voxelised on
    ``grid``.
    """
    path = _existing_file(path, what)
    suffix = _suffix(path)
    if suffix in (".vtk", ".vtp"):
        if grid is None:
            raise InputError(f"{path}: a centreline {what} needs a volume grid to be voxelised on; give the geometry")
        from .phantoms import load_centreline_vtk, voxelize

        try:
            tree = load_centreline_vtk(path)
        except (ValueError, OSError) as exc:
            raise InputError(f"cannot read {path} as a centreline: {exc}") from exc
        label = voxelize(tree, grid)
        if not label.any():
            raise InputError(f"{path}: the centreline's tubes do not reach the volume grid; check volume.center_mm")
        return label, grid
    if suffix in (".nrrd", ".nhdr", ".seg.nrrd"):
        data, label_grid = _nrrd_volume(path, collapse_layers=True)
    elif suffix in (".nii", ".nii.gz"):
        data, label_grid = _nifti_volume(path)
    else:
        raise InputError(f"{path}: unsupported {what} format {suffix or '(no extension)'!r}; use {VOLUME_FORMATS} or {CENTRELINE_FORMATS}")
    if data.dtype != bool and np.issubdtype(data.dtype, np.floating):
        if not np.all(np.isfinite(data)):
            raise InputError(f"{path}: the {what} contains NaN or infinite values; fix the volume")
        if threshold is None:
            values = np.unique(data[data != 0])
            if values.size > 1:
                raise InputError(
                    f"{path} holds continuous values ({values.min():.3g} … {values.max():.3g}), not a labelmap; "
                    "give a threshold (e.g. --threshold 0.5 for an occupancy volume) or a segmentation")
    if threshold is not None:
        label = np.asarray(data, float) >= float(threshold)
    else:
        label = np.asarray(data) != 0
    return label, label_grid


def describe_grid(grid: VolumeGrid) -> str:
    return (f"shape {list(grid.shape)}, spacing {[round(s, 4) for s in grid.spacing_mm]} mm, "
            f"origin {[round(float(o), 3) for o in grid.origin]} mm")


def align_to_grid(volume: np.ndarray, volume_grid: VolumeGrid, grid: VolumeGrid, what: str = "prediction") -> np.ndarray:
    """``volume`` on ``grid``: unchanged on an equal grid, padded/cropped on a shifted one.

    Grids with equal spacing whose origins differ by whole voxels (e.g. a segmentation Slicer
    saved cropped to its extent) are aligned by padding with zeros and cropping; cropping must
    not drop any non-zero voxel. Any other difference is an error: resampling is left to the user.
    """
    spacing_a, spacing_b = np.asarray(volume_grid.spacing_mm), np.asarray(grid.spacing_mm)
    if not np.allclose(spacing_a, spacing_b, rtol=1e-5, atol=1e-6):
        raise InputError(
            f"the {what} and the reference lie on different grids ({what}: {describe_grid(volume_grid)}; "
            f"reference: {describe_grid(grid)}); resample the {what} onto the reference grid first")
    offset = (volume_grid.origin - grid.origin) / spacing_b
    whole = np.rint(offset)
    if np.any(np.abs(offset - whole) > 1e-3):
        raise InputError(
            f"the {what}'s voxels are shifted by a fraction of a voxel from the reference grid "
            f"({what}: {describe_grid(volume_grid)}; reference: {describe_grid(grid)}); resample it onto the reference grid first")
    whole = whole.astype(int)
    if np.all(whole == 0) and tuple(volume.shape) == tuple(grid.shape):
        return volume
    out = np.zeros(grid.shape, dtype=volume.dtype)
    src = [slice(max(0, -o), min(n_src, n_dst - o)) for o, n_src, n_dst in zip(whole, volume.shape, grid.shape)]
    dst = [slice(max(0, o), max(0, o) + (s.stop - s.start)) for o, s in zip(whole, src)]
    if all(s.stop > s.start for s in src):
        out[tuple(dst)] = volume[tuple(src)]
    if np.count_nonzero(out) != np.count_nonzero(volume):
        raise InputError(
            f"the {what} reaches outside the reference grid ({what}: {describe_grid(volume_grid)}; "
            f"reference: {describe_grid(grid)}); use volumes of the same reconstruction grid")
    return out


def _grid_header(grid: VolumeGrid) -> "OrderedDict[str, object]":
    # pynrrd sets "type" and "sizes" from the array itself.
    return OrderedDict([
        ("dimension", 3),
        ("space", "left-posterior-superior"),
        ("space directions", np.diag(np.asarray(grid.spacing_mm, float))),
        ("kinds", ["domain", "domain", "domain"]),
        ("encoding", "gzip"),
        ("space origin", np.asarray(grid.origin, float)),
    ])


def _check_volume(array: np.ndarray, grid: VolumeGrid) -> None:
    if tuple(np.shape(array)) != tuple(grid.shape):
        raise ValueError(f"volume shape {tuple(np.shape(array))} does not match the grid shape {tuple(grid.shape)}")


def write_volume_nrrd(path: PathLike, array: np.ndarray, grid: VolumeGrid) -> Path:
    """Write ``array [i, j, k]`` on ``grid`` as gzip NRRD in LPS: bool/uint8 as uint8, else float32."""
    import nrrd

    _check_volume(array, grid)
    array = np.asarray(array)
    data = array.astype(np.uint8) if array.dtype in (np.bool_, np.uint8) else array.astype(np.float32)
    nrrd.write(str(path), data, _grid_header(grid), index_order="F")
    return Path(path)


def _extent(mask: np.ndarray) -> str:
    """The segment's voxel extent "i0 i1 j0 j1 k0 k1" (Slicer's "0 -1 0 -1 0 -1" when empty)."""
    if not mask.any():
        return "0 -1 0 -1 0 -1"
    bounds = []
    for axis in range(3):
        present = np.flatnonzero(np.any(mask, axis=tuple(a for a in range(3) if a != axis)))
        bounds += [int(present[0]), int(present[-1])]
    return " ".join(str(b) for b in bounds)


def write_segmentation_nrrd(path: PathLike, mask: np.ndarray, grid: VolumeGrid, name: str = "Coronary tree",
                            color: Sequence[float] = (0.9, 0.2, 0.2)) -> Path:
    """Write a binary mask as a Slicer segmentation (``.seg.nrrd``): one segment, label value 1."""
    import nrrd

    _check_volume(mask, grid)
    mask = np.asarray(mask) != 0
    if len(color) != 3 or not all(0.0 <= float(c) <= 1.0 for c in color):
        raise ValueError(f"color must be three numbers in [0, 1], got {list(color)}")
    header = _grid_header(grid)
    header.update([
        ("Segment0_Color", " ".join(f"{float(c):g}" for c in color)),
        ("Segment0_ColorAutoGenerated", "0"),
        ("Segment0_Extent", _extent(mask)),
        ("Segment0_ID", "Segment_1"),
        ("Segment0_LabelValue", "1"),
        ("Segment0_Layer", "0"),
        ("Segment0_Name", str(name)),
        ("Segment0_NameAutoGenerated", "0"),
        ("Segment0_Tags", _SLICER_DEFAULT_TAGS),
        ("Segmentation_ContainedRepresentationNames", "Binary labelmap|"),
        ("Segmentation_ConversionParameters", ""),
        ("Segmentation_MasterRepresentation", "Binary labelmap"),
        # The file holds the whole reconstruction grid, so its voxel (0, 0, 0) is the grid's.
        ("Segmentation_ReferenceImageExtentOffset", "0 0 0"),
    ])
    nrrd.write(str(path), mask.astype(np.uint8), header, index_order="F")
    return Path(path)


# --- surfaces -----------------------------------------------------------------------------------
def write_surface_vtk(path: PathLike, vertices_lps: np.ndarray, faces: np.ndarray) -> Path:
    """Write a triangle mesh (LPS mm) as legacy VTK polydata that Slicer places in RAS correctly."""
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray

    vertices = np.asarray(vertices_lps, dtype=np.float32).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError("faces refer to vertices that do not exist")
    points = vtk.vtkPoints()
    points.SetData(numpy_to_vtk(vertices, deep=True))
    cells = vtk.vtkCellArray()
    if faces.size:
        offsets = np.arange(0, 3 * len(faces) + 1, 3, dtype=np.int64)
        cells.SetData(numpy_to_vtkIdTypeArray(offsets, deep=True), numpy_to_vtkIdTypeArray(faces.reshape(-1), deep=True))
    poly = vtk.vtkPolyData()
    poly.SetPoints(points)
    poly.SetPolys(cells)
    writer = vtk.vtkPolyDataWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(poly)
    writer.SetHeader("SDFCAR output. SPACE=LPS")  # Slicer reads "SPACE=LPS" and flips to RAS
    writer.SetFileTypeToBinary()
    writer.SetFileVersion(42)  # format 4.2, as Slicer writes: readable by older VTK/Slicer too
    if not writer.Write():
        raise OSError(f"could not write the surface mesh to {path}")
    return Path(path)


def read_surface_vtk(path: PathLike) -> Tuple[np.ndarray, np.ndarray]:
    """Vertices (N, 3) and triangle faces (M, 3) of a legacy VTK polydata file, as stored."""
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    path = _existing_file(path, "surface")
    reader = vtk.vtkPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    poly = reader.GetOutput()
    if poly is None:
        raise InputError(f"cannot read {path} as VTK polydata")
    vertices = vtk_to_numpy(poly.GetPoints().GetData()).astype(float) if poly.GetPoints() else np.zeros((0, 3))
    connectivity = vtk_to_numpy(poly.GetPolys().GetConnectivityArray()) if poly.GetNumberOfPolys() else np.zeros(0, int)
    return vertices, connectivity.reshape(-1, 3).astype(np.int64)


# --- JSON and atomic files ---------------------------------------------------------------------------------
def json_compatible(value: Any) -> Any:
    """Strict-JSON version of ``value``: numpy types to Python, NaN/inf to None, paths and other
    objects (e.g. DICOM values) to str."""
    if isinstance(value, dict):
        return {str(k): json_compatible(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_compatible(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_compatible(value.tolist())
    if isinstance(value, np.generic):
        return json_compatible(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (str, int, bool)) or value is None:
        return value
    return str(value)


def process_umask() -> int:
    """The process's file-mode creation mask (os.umask can only be read by setting it)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: PathLike, write: Callable[[Path], Any]) -> Path:
    """Call ``write(temporary_path)`` and move the file into place: a failure leaves ``path`` as it was."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "a folder of that name exists; give a file name", str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=str(path.parent))
    os.close(handle)
    try:
        write(Path(tmp))
        # mkstemp makes the file private (0600): give it the mode the file had, or a new file's
        os.chmod(tmp, path.stat().st_mode & 0o7777 if path.exists() else 0o666 & ~process_umask())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def write_text_atomically(path: PathLike, text: str) -> Path:
    return atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def write_json(path: PathLike, data: Any) -> Path:
    """Strict JSON (``json_compatible``), indented, written atomically."""
    return write_text_atomically(path, json.dumps(json_compatible(data), indent=2, allow_nan=False) + "\n")
