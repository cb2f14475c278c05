"""Image model and losses: how a rendered line integral is compared with a view's target.

Image model
    The projector renders line integrals L (mm of vessel along each ray). A binary vessel mask is
    compared with the *silhouette* S = 1 − exp(−L / τ): 0 where no vessel is crossed, rising
    with the path length and saturating at 1, like the opacity of contrast agent. τ
    (``silhouette_length_mm``, default 0.3 mm) is set near the path length at which a simulated
    or segmented mask switches on (0.2 mm): a ray through 1 mm of vessel gives S = 0.96, and
    thick overlaps are not over-penalised. S has a non-zero gradient everywhere, also at L = 0.
    With line-integral targets (the NeCA/SDF-CAR simulation protocol) the occupancy term compares
    L / L_ref with the target / L_ref, L_ref the target's maximum, and the geometric term uses the
    silhouettes of both. Where the frames are given with the masks (``frame_evidence``), the
    occupancy term compares L / L_ref with the path lengths read off the frames (``evidence.py``)
    and the geometric term keeps the masks (``frame_target``).

L_occ
    Mean over the image of (target − image)², Eq. (3) of the paper, averaged over views.

L_excess (``frame_excess_factor`` > 0, off by default)
    With the frames: L_occ fits the masks, and ``excess_path_loss`` charges each ray only the path length
    it crosses beyond factor × the frame's + a tolerance, so the frames' blurred profile caps ghosts
    without shaping the lumen.

L_bin (``lambda_binary``, off by default)
    ``partial_occupancy_loss``: the share of the occupancy's mass that is neither 0 nor 1.

L_geo
    Mean over the image of (SDT(target silhouette) − SDT(S))², Eq. (2), averaged over views. SDT
    is the signed 2D distance (distance to the vessel outside it minus distance to the background
    inside it), computed with the differentiable cascaded-convolution distance transform of Pham
    et al. (2021), the operator of ``kornia.contrib.distance_transform``, the same for target and
    rendering, so a perfect rendering has zero loss. Unlike the public SDF-CAR code, the rendering
    is not thresholded before the transform, so L_geo has a gradient:

    * pixels with S > 0.5 (``threshold``) are the vessel sources of the outside distance and keep
      their value, so a weak source counts as slightly farther away (−h·log S); pixels with
      S ≤ 0.5 are the background sources of the inside distance likewise. The gradient of
      kornia's transform reaches the pixels next to a source, i.e. the silhouette's border, and
      pushes it towards the target's border in proportion to the target's distance there;
    * an image without any vessel pixel reads as "far from any vessel" (kornia answers 0 for a
      sourceless image, which would make an empty rendering a spurious minimum);
    * distances are in mm at the isocenter, clipped to ±``truncation_mm`` (5 mm) and divided by
      it, so L_geo and L_occ have the same order of magnitude and far pixels do not dominate.
      Beyond the truncation both distances are +1, so the transform runs only on a fixed crop
      around the target and the traced rays — the same loss, less work;
    * the transform may run on a ``downsample``-times max-pooled image (thin vessels survive
      max-pooling), which costs the square less.
    * ``tolerance_mm`` > 0 (off by default) soft-thresholds each pixel's difference of the two
      distances by that much, so a border within it of the target's costs nothing.

Why not kornia's function itself (``cascaded_distance``)
    Distances grow by kernel_size // 2 pixels per round; kornia runs the cascade
    max(H, W) / (kernel_size // 2) times and autograd keeps every round: tens of GB for a few 512² images, most of the paper preset's
    memory (bench/RESULTS.md, section 3) — and a cost linear in the image size per round. Distances beyond the
    truncation are clipped anyway, and the cascade sets a pixel's distance in the round its
    neighbourhood first reaches a source, never later — so stopping after
    ceil(truncation / (kernel_size // 2)) + 1 rounds gives the same clipped values and gradients
    (tested against kornia) at a few per cent of the memory and time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np
import torch
import torch.nn.functional as F


def silhouette(line_integral: torch.Tensor, length_mm: float) -> torch.Tensor:
    return 1.0 - torch.exp(-line_integral / length_mm)


def gaussian_blur(image: torch.Tensor, sigma_px: Tuple[float, float]) -> torch.Tensor:
    """``image`` (H, W) convolved with a normalised Gaussian of σ (rows, columns) pixels, zero outside
    the image, cut at 3σ; σ 0 along an axis leaves it as it is. Two 1D convolutions of torch itself: kornia's
    blur would serve too, but kornia is a test dependency only, and Slicer's Python does not bundle it."""
    out = image[None, None]
    for axis, sigma in enumerate(sigma_px):
        if sigma <= 0:
            continue
        radius = max(int(math.ceil(3.0 * sigma)), 1)
        x = torch.arange(-radius, radius + 1, dtype=image.dtype, device=image.device)
        kernel = torch.exp(-0.5 * (x / sigma) ** 2)
        kernel = (kernel / kernel.sum()).reshape((1, 1, -1, 1) if axis == 0 else (1, 1, 1, -1))
        out = F.conv2d(out, kernel, padding=(radius, 0) if axis == 0 else (0, radius))
    return out[0, 0]


def occupancy_loss(image: torch.Tensor, target: torch.Tensor, weight: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Mean squared difference over the image, each pixel weighed by ``weight`` (H, W) where given."""
    squared = (target - image) ** 2
    return torch.mean(squared if weight is None else weight * squared)


def excess_path_loss(rendered: torch.Tensor, target: torch.Tensor, factor: float, tolerance: float,
                     weight: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Mean over the image of max(rendered − factor·target − tolerance, 0)²: only what a ray crosses beyond
    the target's allowance costs (all in the target's units, L / L_ref for the frames' path lengths), each pixel
    weighed by ``weight`` (H, W) where given."""
    squared = torch.relu(rendered - factor * target - tolerance) ** 2
    return torch.mean(squared if weight is None else weight * squared)


def partial_occupancy_loss(occupancy: torch.Tensor) -> torch.Tensor:
    """Σ o(1 − o) / Σ o, the mass-weighted mean of 1 − o: 0 for a binary field, near 1 for a faint
    haze. Two views leave a vessel's depth open: the fit can spread it thinly along the rays, which a
    threshold breaks; this term asks each voxel to be vessel or not."""
    return torch.sum(occupancy * (1.0 - occupancy)) / torch.clamp(torch.sum(occupancy), min=1.0)


@dataclass(frozen=True)
class DistanceSettings:
    downsample: int = 1
    threshold: float = 0.5
    truncation_mm: float = 5.0
    kernel_size: int = 3
    tolerance_mm: float = 0.0  # a border this close to the target's costs nothing (``GeometricLoss``)


#: the soft-minimum temperature of the cascade (kornia's default for distance_transform)
CASCADE_H = 0.35


def _correlate(padded: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Valid correlation of (B, 1, H, W) with a small (1, 1, k, k) kernel.

    On CPU as k² shifted, weighted sums: mkldnn's one-channel convolution takes about twice as long
    (bench/RESULTS.md §36); on other devices one convolution, which launches one kernel instead of k².
    """
    if padded.device.type != "cpu":
        return F.conv2d(padded, kernel)
    size = kernel.shape[-1]
    height, width = padded.shape[2] - size + 1, padded.shape[3] - size + 1
    weights = kernel[0, 0].tolist()
    out = padded[:, :, :height, :width] * weights[0][0]
    for i in range(size):
        for j in range(size):
            if i or j:
                out.add_(padded[:, :, i:i + height, j:j + width], alpha=weights[i][j])
    return out


class _SymmetricFilter(torch.autograd.Function):
    """Valid correlation with a fixed kernel that equals itself rotated by 180°.

    Its input gradient is the same correlation of the output gradient zero-padded by kernel size
    − 1. Written out because the CPU (mkldnn) backward of a one-channel convolution took several
    times its forward (bench/RESULTS.md §3), which made it the largest cost of L_geo; both directions
    now go through ``_correlate``.
    """

    @staticmethod
    def forward(ctx, padded: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        ctx.kernel = kernel
        return _correlate(padded, kernel)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        width = ctx.kernel.shape[-1] - 1  # the "full" correlation: zero margins of kernel size − 1
        return _correlate(F.pad(grad, (width, width, width, width)), ctx.kernel), None


def cascaded_distance(sources: torch.Tensor, kernel_size: int = 3, max_distance_px: Optional[float] = None,
                      h: float = CASCADE_H) -> torch.Tensor:
    """Distance in pixels (B, 1, H, W) from every pixel to the nearest source, differentiable.

    ``sources`` in [0, 1]: 1 is a source, 0 background, a value in between a weaker source that
    reads as slightly farther away. Each round convolves the reached front with the kernel
    exp(−r / h) (replicated border) and gives every pixel whose response lies in (0, 1) the
    distance round · (kernel_size // 2) − h · log(response); that pixel then joins the front.
    Pixels inside a source (response ≥ 1 from the start) keep 0, as in kornia. With
    ``max_distance_px`` the cascade stops once every distance below it is final, and pixels not
    reached by then are +inf; the values below ``max_distance_px`` equal the full cascade's.
    """
    if sources.dim() != 4 or sources.shape[1] != 1:
        raise ValueError(f"sources must have shape (B, 1, H, W), got {tuple(sources.shape)}")
    if kernel_size < 3 or kernel_size % 2 == 0:
        raise ValueError("kernel_size must be an odd integer of at least 3")
    half = kernel_size // 2
    rounds = math.ceil(max(sources.shape[2], sources.shape[3]) / half)
    if max_distance_px is not None:
        # A pixel reached in round i has a distance of at least i · half.
        rounds = min(rounds, math.ceil(max_distance_px / half) + 1)
    offsets = torch.arange(-half, half + 1, dtype=sources.dtype, device=sources.device)
    kernel = torch.exp(-torch.sqrt(offsets[:, None] ** 2 + offsets[None, :] ** 2) / h)[None, None]
    front = sources.clamp(0.0, 1.0)
    distance = torch.zeros_like(front)
    reached = front > 0  # sources are decided in round 0: a distance, or 0 if inside a source
    one = torch.ones_like(front)
    for round_index in range(rounds):
        response = _SymmetricFilter.apply(F.pad(front, (half, half, half, half), mode="replicate"), kernel)
        positive = response > 0
        step = -h * torch.log(torch.where(positive, response, one))
        new = positive & (step > 0)
        distance = distance + torch.where(new, round_index * half + step, torch.zeros_like(step))
        front = torch.where(new, one, front)
        reached = reached | new
    return torch.where(reached, distance, torch.full_like(distance, float("inf")))


def signed_distance(images: torch.Tensor, step_mm: torch.Tensor, settings: DistanceSettings) -> torch.Tensor:
    """Truncated, normalised signed distance of silhouettes (B, 1, H, W) → (B, 1, H, W) in [−1, 1].

    ``step_mm`` (B,) is each image's pixel size in mm at the isocenter (after any pooling).
    """
    zero = torch.zeros_like(images)
    vessel = torch.where(images > settings.threshold, images, zero)
    background = torch.where(images <= settings.threshold, 1.0 - images, zero)
    sources = torch.cat([vessel, background], dim=0)
    max_distance_px = settings.truncation_mm / float(step_mm.min())
    distance = cascaded_distance(sources, settings.kernel_size, max_distance_px)
    b = images.shape[0]
    step = step_mm.to(images.dtype)[:, None, None, None]
    signed = (distance[:b] - distance[b:]) * step
    return torch.clamp(signed / settings.truncation_mm, -1.0, 1.0)


def pooled(image: torch.Tensor, factor: int) -> torch.Tensor:
    """(H, W) → (1, 1, ceil(H/f), ceil(W/f)) by max-pooling, which keeps thin vessels."""
    x = image[None, None]
    return F.max_pool2d(x, kernel_size=factor, stride=factor, ceil_mode=True) if factor > 1 else x


class GeometricLoss:
    """L_geo of all views (module docstring), with the targets' transforms computed once.

    Args:
        target_silhouettes: per view (H, W) in [0, 1].
        pixel_mm: per view, pixel size at the isocenter.
        traced_pixels: per view, flat indices of the pixels whose rendering can be non-zero
            (``ConeBeamProjector.pixels``), or None for all.
        known_pixels: per view None, or (H, W) 1 where the target is known and 0 where it is not (a part of the
            detector the view could not see): renderings and targets are blanked there before their distances
            are taken, and those pixels add nothing to the loss.
    """

    def __init__(self, target_silhouettes: Sequence[torch.Tensor], pixel_mm: Sequence[float],
                 traced_pixels: Sequence[Optional[np.ndarray]], settings: DistanceSettings,
                 known_pixels: Optional[Sequence[Optional[torch.Tensor]]] = None) -> None:
        self.settings = settings
        f = settings.downsample
        self.crops: List[Tuple[int, int, int, int]] = []
        self.full_sizes: List[int] = []
        for sil, pixels, px in zip(target_silhouettes, traced_pixels, pixel_mm):
            h, w = (math.ceil(n / f) for n in sil.shape)
            self.full_sizes.append(h * w)
            region = pooled(sil, f)[0, 0] > 0
            if pixels is None:
                region[:] = True
            else:
                traced = torch.zeros(sil.numel(), dtype=torch.float32, device=sil.device)
                traced[torch.as_tensor(pixels, device=sil.device)] = 1.0
                region |= pooled(traced.reshape(sil.shape), f)[0, 0] > 0
            rows = torch.nonzero(region.any(dim=1)).squeeze(1)
            cols = torch.nonzero(region.any(dim=0)).squeeze(1)
            margin = int(math.ceil(settings.truncation_mm / (px * f))) + 2
            self.crops.append((max(int(rows.min()) - margin, 0), min(int(rows.max()) + margin + 1, h),
                               max(int(cols.min()) - margin, 0), min(int(cols.max()) + margin + 1, w)))
        self.height = max(r1 - r0 for r0, r1, _, _ in self.crops)
        self.width = max(c1 - c0 for _, _, c0, c1 in self.crops)
        device = target_silhouettes[0].device
        self.step_mm = torch.tensor([px * f for px in pixel_mm], device=device)
        # the renderings are blanked where the view could not see, as its mask is: what the fit puts there changes
        # no distance the view can check
        self.known = [None if k is None else k.to(torch.float32) for k in
                      (known_pixels if known_pixels is not None else [None] * len(self.crops))]
        # Pixels that padding adds to bring crops to a common size are excluded from the sum.
        self.weights = torch.zeros(len(self.crops), 1, self.height, self.width, device=device)
        for n, (r0, r1, c0, c1) in enumerate(self.crops):
            self.weights[n, 0, : r1 - r0, : c1 - c0] = 1.0 / self.full_sizes[n]
            known = self.known[n]
            if known is not None:  # a pooled pixel counts only where every pixel it pools is known (min-pooling)
                known_pooled = -pooled(-known, settings.downsample)[0, 0, r0:r1, c0:c1]
                self.weights[n, 0, : r1 - r0, : c1 - c0] *= known_pooled
        with torch.no_grad():
            targets = [s if k is None else s * k for s, k in zip(target_silhouettes, self.known)]
            self.target = signed_distance(self._batch(targets), self.step_mm, settings)

    def _batch(self, silhouettes: Sequence[torch.Tensor]) -> torch.Tensor:
        parts = []
        for sil, (r0, r1, c0, c1) in zip(silhouettes, self.crops):
            crop = pooled(sil, self.settings.downsample)[:, :, r0:r1, c0:c1]
            parts.append(F.pad(crop, (0, self.width - (c1 - c0), 0, self.height - (r1 - r0))))
        return torch.cat(parts, dim=0)

    def __call__(self, silhouettes: Sequence[torch.Tensor]) -> torch.Tensor:
        """L_geo averaged over views for rendered silhouettes (H, W) per view."""
        silhouettes = [s if k is None else s * k for s, k in zip(silhouettes, self.known)]
        sdt = signed_distance(self._batch(silhouettes), self.step_mm, self.settings)
        difference = sdt - self.target
        if self.settings.tolerance_mm > 0:
            # A segmented mask's border is known to about a pixel: a distance that differs by less costs nothing.
            difference = F.softshrink(difference, self.settings.tolerance_mm / self.settings.truncation_mm)
        return torch.sum(self.weights * difference ** 2) / len(self.crops)


@dataclass
class ViewTarget:
    """What one view's rendering is compared with in L_occ, and how it is rendered."""

    image: torch.Tensor  # (H, W): mask in {0, 1}, or line integral / L_ref
    silhouette: torch.Tensor  # (H, W) in [0, 1]
    kind: str  # "mask" | "line_integral"
    reference_mm: float  # L_ref for line-integral targets (1 for masks)
    silhouette_length_mm: float  # τ
    # frames' path lengths carry the detector's blur: the rendering is blurred alike (σ rows, columns px) for L_occ
    blur_sigma_px: Tuple[float, float] = (0.0, 0.0)
    # (H, W) weights of the pixels in L_occ (``thin_weights.py``), None: every pixel alike
    pixel_weight: Optional[torch.Tensor] = None
    # (H, W) 1 where the view could show a vessel, 0 where it could not (collimated, clipped: ``masks.unseen_pixels``),
    # so that its 0 there is no evidence and adds nothing to the loss; None: every pixel known
    known: Optional[torch.Tensor] = None

    def occupancy_weight(self) -> Optional[torch.Tensor]:
        """Each pixel's weight in L_occ: ``pixel_weight`` on the known pixels, 0 on the unknown (None: all 1)."""
        if self.known is None:
            return self.pixel_weight
        return self.known if self.pixel_weight is None else self.pixel_weight * self.known

    def silhouette_of(self, line_integral: torch.Tensor) -> torch.Tensor:
        return silhouette(line_integral, self.silhouette_length_mm)

    def rendered(self, line_integral: torch.Tensor) -> torch.Tensor:
        """The rendering in this target's image model (silhouette for masks, L / L_ref otherwise)."""
        if self.kind == "mask":
            return self.silhouette_of(line_integral)
        if any(self.blur_sigma_px):
            line_integral = gaussian_blur(line_integral, self.blur_sigma_px)
        return line_integral / self.reference_mm


def frame_target(line_integral_mm: torch.Tensor, mask_target: ViewTarget,
                 blur_sigma_px: Tuple[float, float] = (0.0, 0.0)) -> ViewTarget:
    """A mask's view with L_occ on path lengths read off its frame (``evidence.py``): L / L_ref against
    the evidence / L_ref; the silhouette for L_geo stays the mask.

    L_ref is the median evidence over the mask's vessel pixels, so a typical vessel pixel reads 1
    as it does in a mask and λ_occ keeps its meaning: scaled by the maximum instead (as for
    simulated line integrals), a thin vessel's pixels weighed a few per cent of a mask pixel and
    were lost (bench/RESULTS.md §15). ``blur_sigma_px``: the detector's blur, which the frame's path
    lengths carry and a rendering does not; L_occ then compares the rendering blurred by it."""
    values = line_integral_mm[(line_integral_mm > 0) & (mask_target.silhouette > 0)]
    if values.numel() == 0:
        raise ValueError("the frame shows no vessel inside the mask: no evidence to fit")
    reference = float(torch.median(values.float()))
    image = (line_integral_mm.to(torch.float32) / reference)
    return ViewTarget(image, mask_target.silhouette, "line_integral", reference, mask_target.silhouette_length_mm,
                      (float(blur_sigma_px[0]), float(blur_sigma_px[1])))


def make_target(data: torch.Tensor, kind: str, silhouette_length_mm: float) -> ViewTarget:
    """The target of one view: a binary mask, or line integrals (mm) normalised by their maximum."""
    if kind == "mask":
        image = (data > 0).to(torch.float32)
        return ViewTarget(image, image, kind, 1.0, silhouette_length_mm)
    if kind == "line_integral":
        reference = float(data.max())
        if reference <= 0:
            raise ValueError("a line-integral target is all zero: no vessel to reconstruct")
        data = data.to(torch.float32)
        return ViewTarget(data / reference, silhouette(data, silhouette_length_mm), kind, reference, silhouette_length_mm)
    raise ValueError(f"target kind must be 'mask' or 'line_integral', got {kind!r}")
