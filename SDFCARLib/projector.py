"""Differentiable cone-beam projector: line integrals (mm) of a voxel volume along detector rays.

Method
    Joseph's method: each ray is sampled once per voxel slice along its dominant axis, the volume
    is interpolated bilinearly inside the slice, and each sample is weighted by the ray length
    per slice (mm). The voxel values are read as a trilinear-like continuous function that is 0
    outside the grid, so an all-ones volume integrates to the ray's chord through the grid's
    bounding box. The operator is linear; it is stored as a sparse CSR matrix (rays × voxels)
    together with its transpose, so the forward pass and the gradient are one sparse mat-vec each
    on CPU and CUDA alike.

Support
    A projector may be built for a subset of voxels (``voxels``: flat indices into the grid); the
    other voxels are taken as empty, and only the rays that can meet the subset are stored. This is
    how the fast presets skip the empty space outside the visual hull (``hull.py``).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from scipy import ndimage

from .geometry import CArmView, VolumeGrid
from .sparse import SparseOperator


def footprint_radius_px(view: CArmView, grid: VolumeGrid) -> float:
    """Upper bound (pixels) of how far from a voxel centre's projection that voxel's shadow reaches."""
    half_diagonal = 0.5 * float(np.linalg.norm(grid.spacing_mm))
    lo, hi = grid.bounds()
    nearest_to_source = view.sod_mm - float(np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi))))
    max_magnification = view.sid_mm / max(nearest_to_source, 1e-6)
    return half_diagonal * max_magnification / min(view.pixel_spacing_mm) + 1.0


def pixels_reached(view: CArmView, grid: VolumeGrid, voxels: np.ndarray) -> np.ndarray:
    """Flat pixel indices whose rays can pass through (the interpolation support of) ``voxels``."""

    rows, cols = view.detector_shape
    r, c, _ = view.project(grid.voxel_centers(voxels))
    hit = np.zeros((rows, cols), dtype=bool)
    ri, ci = np.rint(r).astype(np.int64), np.rint(c).astype(np.int64)
    inside = (ri >= 0) & (ri < rows) & (ci >= 0) & (ci < cols)
    hit[ri[inside], ci[inside]] = True
    # Interpolation reaches one voxel further than the voxel itself: two footprints' worth.
    radius = int(np.ceil(2 * footprint_radius_px(view, grid)))
    yy, xx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    hit = ndimage.binary_dilation(hit, structure=(yy**2 + xx**2) <= radius**2)
    return np.flatnonzero(hit)


#: rays traced at a time: each holds (slices × 4) entries in float64 and int64, so 2048 rays keep the
#: trace's temporaries near 10 MB; 8192 took twice as long to build (bench/RESULTS.md §36)
RAYS_PER_CHUNK = 2048


class ConeBeamProjector:
    """Line integrals (mm) through a volume for the rays of one view (see module docstring).

    Args:
        view, grid: the acquisition and the voxel grid.
        voxels: optional sorted flat indices (C order of ``[i, j, k]``) of the voxels that may be
            non-zero; inputs are then the values of these voxels only, shape (len(voxels),).
            Default: every voxel, input shape (grid.num_voxels,).
        pixels: optional flat pixel indices of the rays to trace (default: every pixel when
            ``voxels`` is None, else every pixel whose ray can meet ``voxels``).
    """

    def __init__(
        self,
        view: CArmView,
        grid: VolumeGrid,
        voxels: Optional[np.ndarray] = None,
        pixels: Optional[np.ndarray] = None,
        device: str = "cpu",
        dtype: torch.dtype = torch.float32,
        rays_per_chunk: int = RAYS_PER_CHUNK,
    ) -> None:
        self.view = view
        self.grid = grid
        self.device = torch.device(device)
        self.dtype = dtype
        if voxels is not None:
            voxels = np.asarray(voxels, dtype=np.int64)
            if voxels.ndim != 1 or (voxels.size and (voxels.min() < 0 or voxels.max() >= grid.num_voxels)):
                raise ValueError("voxels must be a 1-D array of flat voxel indices inside the grid")
            if voxels.size > 1 and np.any(np.diff(voxels) <= 0):
                raise ValueError("voxels must be sorted and unique")
        self.voxels = voxels
        self.num_inputs = grid.num_voxels if voxels is None else int(voxels.size)
        if pixels is None:
            rows, cols = view.detector_shape
            pixels = np.arange(rows * cols) if voxels is None else pixels_reached(view, grid, voxels)
        self.pixels = np.asarray(pixels, dtype=np.int64)
        self._pixels_t = torch.as_tensor(self.pixels, device=self.device)
        self.operator = self._build(rays_per_chunk)

    @property
    def nnz(self) -> int:
        return self.operator.nnz

    def _build(self, rays_per_chunk: int) -> SparseOperator:
        grid, view, dev = self.grid, self.view, self.device
        shape = torch.tensor(grid.shape, device=dev)
        spacing = torch.tensor(grid.spacing_mm, dtype=torch.float64, device=dev)
        if self.voxels is None:
            lookup = None
        else:
            lookup = torch.full((grid.num_voxels,), -1, dtype=torch.int64, device=dev)
            lookup[torch.as_tensor(self.voxels, device=dev)] = torch.arange(self.voxels.size, device=dev)
        source_ijk = torch.as_tensor(grid.world_to_index(view.source_position), device=dev)
        cols_px = view.detector_shape[1]
        all_rows, all_cols, all_vals = [], [], []
        for start in range(0, self.pixels.size, rays_per_chunk):
            chunk = self.pixels[start : start + rays_per_chunk]
            target = grid.world_to_index(view.pixel_to_world(chunk // cols_px, chunk % cols_px))
            step = torch.as_tensor(target, device=dev) - source_ijk  # index-space source → pixel
            ray_rows, voxel, weight = self._trace(source_ijk, step, shape, spacing)
            if lookup is not None:
                voxel = lookup[voxel]
                keep = voxel >= 0
                ray_rows, voxel, weight = ray_rows[keep], voxel[keep], weight[keep]
            all_rows.append(ray_rows + start)
            all_cols.append(voxel)
            all_vals.append(weight)
        rows = torch.cat(all_rows) if all_rows else torch.zeros(0, dtype=torch.int64, device=dev)
        cols = torch.cat(all_cols) if all_cols else torch.zeros(0, dtype=torch.int64, device=dev)
        vals = (torch.cat(all_vals) if all_vals else torch.zeros(0, device=dev)).to(self.dtype)
        return SparseOperator(rows, cols, vals, (int(self.pixels.size), self.num_inputs), sorted_by_row=True)

    @staticmethod
    def _trace(source: torch.Tensor, step: torch.Tensor, shape: torch.Tensor, spacing: torch.Tensor):
        """Joseph sampling of rays ``source + t * step`` (index space); entries sorted by ray."""
        n_rays = step.shape[0]
        dominant = step.abs().argmax(dim=1)
        n_max = int(shape.max())
        # Fixed stride per ray (slices × 4 corners) keeps the entries ordered by ray.
        voxel = torch.zeros((n_rays, n_max, 4), dtype=torch.int64, device=step.device)
        weight = torch.zeros((n_rays, n_max, 4), dtype=torch.float64, device=step.device)
        strides = torch.tensor([int(shape[1] * shape[2]), int(shape[2]), 1], device=step.device)
        mm_per_unit = torch.linalg.norm(step * spacing, dim=1)
        for axis in range(3):
            sel = torch.nonzero(dominant == axis).squeeze(1)
            if sel.numel() == 0:
                continue
            p_axis, q_axis = [a for a in range(3) if a != axis]
            n_slices = int(shape[axis])
            s = step[sel]
            slices = torch.arange(n_slices, dtype=torch.float64, device=step.device)
            t = (slices[None, :] - source[axis]) / s[:, axis : axis + 1]  # (R, N)
            p = source[p_axis] + t * s[:, p_axis : p_axis + 1]
            q = source[q_axis] + t * s[:, q_axis : q_axis + 1]
            p0, q0 = torch.floor(p), torch.floor(q)
            fp, fq = p - p0, q - q0
            p0, q0 = p0.long(), q0.long()
            ds = (mm_per_unit[sel] / s[:, axis].abs())[:, None]  # mm of ray per slice
            between = ((t > 0) & (t < 1)).to(torch.float64)  # only between source and detector
            corner_w = torch.stack([(1 - fp) * (1 - fq), fp * (1 - fq), (1 - fp) * fq, fp * fq], dim=-1)
            pi = torch.stack([p0, p0 + 1, p0, p0 + 1], dim=-1)
            qi = torch.stack([q0, q0, q0 + 1, q0 + 1], dim=-1)
            valid = (pi >= 0) & (pi < shape[p_axis]) & (qi >= 0) & (qi < shape[q_axis])
            w = corner_w * (ds * between)[..., None] * valid
            n_idx = torch.arange(n_slices, device=step.device)[None, :, None]
            flat = n_idx * strides[axis] + pi.clamp(0, int(shape[p_axis]) - 1) * strides[p_axis] + qi.clamp(0, int(shape[q_axis]) - 1) * strides[q_axis]
            voxel[sel, :n_slices] = flat
            weight[sel, :n_slices] = w
        ray = torch.arange(n_rays, device=step.device)[:, None, None].expand_as(voxel)
        keep = weight > 0
        return ray[keep], voxel[keep], weight[keep]

    # --- application -----------------------------------------------------------------------------
    def line_integrals(self, values: torch.Tensor) -> torch.Tensor:
        """Line integrals (mm) along the projector's rays; ``values`` shape (num_inputs,)."""
        if values.shape != (self.num_inputs,):
            raise ValueError(f"expected values of shape ({self.num_inputs},), got {tuple(values.shape)}")
        return self.operator(values)

    def scatter(self, per_ray: torch.Tensor) -> torch.Tensor:
        """Place per-ray values into a full detector image (rows, cols); untraced pixels are 0."""
        rows, cols = self.view.detector_shape
        image = torch.zeros(rows * cols, dtype=per_ray.dtype, device=per_ray.device)
        image = image.index_put((self._pixels_t,), per_ray)
        return image.reshape(rows, cols)

    def render(self, values: torch.Tensor) -> torch.Tensor:
        """Line-integral image (rows, cols) in mm of the voxel ``values``."""
        return self.scatter(self.line_integrals(values))

    def covers(self, voxels: np.ndarray) -> bool:
        """Whether every one of the flat voxel indices ``voxels`` is an input of this projector."""
        voxels = np.asarray(voxels, dtype=np.int64)
        return self.voxels is None or bool(np.isin(voxels, self.voxels, assume_unique=True).all())

    def group_integrals(self, groups: np.ndarray, count: int):
        """Line integral (mm) of each voxel group 1..``count`` along every ray that meets one.

        ``groups``: a label per grid voxel (flat, 0 = in no group; the projector's non-input voxels
        must be 0). Returns the (rays × count) integrals in float64, those rays' flat pixel indices,
        and which groups the view sees at all. Summed from the operator's entries in the groups'
        voxels only, so a projector of a large support serves a small segmentation without
        tracing its rays again.
        """
        matrix = self.operator.matrix
        crow = matrix.crow_indices().cpu().numpy()
        row = np.repeat(np.arange(crow.size - 1), np.diff(crow))
        columns = matrix.col_indices().cpu().numpy()
        label = np.asarray(groups).reshape(-1)[columns if self.voxels is None else self.voxels[columns]]
        keep = label > 0
        row, label, value = row[keep], label[keep] - 1, matrix.values().cpu().numpy()[keep].astype(np.float64)
        hit, local = np.unique(row, return_inverse=True)
        integrals = np.bincount(local * count + label, weights=value, minlength=hit.size * count).reshape(hit.size, count)
        return integrals, self.pixels[hit], np.bincount(label, weights=value, minlength=count) > 0

    def to(self, device: str) -> "ConeBeamProjector":
        self.device = torch.device(device)
        self.operator.to(self.device)
        self._pixels_t = self._pixels_t.to(self.device)
        return self


def project_volume(volume: np.ndarray, view: CArmView, grid: VolumeGrid, device: str = "cpu") -> np.ndarray:
    """Line-integral image (mm) of a dense volume (array ``[i, j, k]`` of ``grid.shape``).

    Only the non-zero voxels are traced, so sparse label volumes project quickly.
    """
    volume = np.asarray(volume)
    if volume.shape != tuple(grid.shape):
        raise ValueError(f"volume shape {volume.shape} does not match the grid shape {tuple(grid.shape)}")
    support = np.flatnonzero(volume.reshape(-1))
    rows, cols = view.detector_shape
    if support.size == 0:
        return np.zeros((rows, cols), dtype=np.float32)
    projector = ConeBeamProjector(view, grid, voxels=support, device=device, dtype=torch.float64)
    values = torch.as_tensor(volume.reshape(-1)[support].astype(np.float64), device=device)
    with torch.no_grad():
        return projector.render(values).cpu().numpy().astype(np.float32)
