"""Fixed sparse linear operators with a precomputed transpose.

The projector (rays × voxels) and the hash encoding of fixed points (features × table rows) are
both linear maps that never change during a reconstruction. Storing the matrix and its transpose
in CSR form makes the forward pass and the gradient one sparse product each, on CPU and CUDA,
instead of re-deriving gather/scatter indices every step.
"""

from __future__ import annotations

import contextlib
import warnings
from typing import Tuple

import torch


@contextlib.contextmanager
def _deliberate_sparse_construction():
    """Silences torch's notes on building sparse tensors the way this module does on purpose."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        # valid by construction (sorted rows, counted offsets), so the invariant check is skipped on
        # purpose; some torch versions (2.11 with CUDA, seen on an H200) warn that it was
        warnings.filterwarnings("ignore", message="Sparse invariant checks are implicitly disabled")
        yield


def index_dtype(device: torch.device, nnz: int, shape: Tuple[int, int]) -> torch.dtype:
    """The CSR index type: 32-bit on CPU where the matrix fits, because MKL's sparse products take
    32-bit indices and torch converts 64-bit ones on every product (a copy of all the column indices,
    a third of the product's time: bench/RESULTS.md §36); 64-bit elsewhere."""
    fits = max(nnz, shape[0] + 1, shape[1]) < 2**31
    return torch.int32 if torch.device(device).type == "cpu" and fits else torch.int64


def _csr(crow: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, shape: Tuple[int, int]) -> torch.Tensor:
    dtype = index_dtype(values.device, int(values.numel()), shape)
    with _deliberate_sparse_construction():
        return torch.sparse_csr_tensor(crow.to(dtype), cols.to(dtype), values, size=shape, check_invariants=False)


def csr_from_sorted(rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, shape: Tuple[int, int]) -> torch.Tensor:
    """CSR matrix from COO entries already sorted by row (no duplicates)."""
    counts = torch.bincount(rows, minlength=shape[0])
    crow = torch.zeros(shape[0] + 1, dtype=torch.int64, device=rows.device)
    torch.cumsum(counts, 0, out=crow[1:])
    return _csr(crow, cols, values, shape)


def _moved(matrix: torch.Tensor, device) -> torch.Tensor:
    return _csr(matrix.crow_indices().to(device), matrix.col_indices().to(device), matrix.values().to(device),
                tuple(matrix.shape))


class _Apply(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, matrix: torch.Tensor, matrix_t: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        ctx.matrix_t = matrix_t
        return torch.mv(matrix, x) if x.dim() == 1 else torch.mm(matrix, x)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        grad = grad.contiguous()
        return (torch.mv(ctx.matrix_t, grad) if grad.dim() == 1 else torch.mm(ctx.matrix_t, grad)), None, None


class SparseOperator:
    """y = A x for x of shape (n,) or (n, k), differentiable in x; A is fixed."""

    def __init__(self, rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, shape: Tuple[int, int],
                 sorted_by_row: bool = False, coalesce: bool = False) -> None:
        rows, cols = rows.long(), cols.long()
        if coalesce:
            with _deliberate_sparse_construction():
                coo = torch.sparse_coo_tensor(torch.stack([rows, cols]), values, shape, check_invariants=False).coalesce()
            rows, cols = coo.indices()
            values = coo.values()
            sorted_by_row = True
        if not sorted_by_row:
            order = torch.argsort(rows, stable=True)
            rows, cols, values = rows[order], cols[order], values[order]
        self.shape = (int(shape[0]), int(shape[1]))
        self.matrix = csr_from_sorted(rows, cols, values, self.shape)
        order = torch.argsort(cols, stable=True)
        self.matrix_t = csr_from_sorted(cols[order], rows[order], values[order], (self.shape[1], self.shape[0]))

    @property
    def nnz(self) -> int:
        return int(self.matrix.values().numel())

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[0] != self.shape[1]:
            raise ValueError(f"operator takes {self.shape[1]} inputs, got {x.shape[0]}")
        return _Apply.apply(x.to(self.matrix.dtype), self.matrix, self.matrix_t)

    def to(self, device) -> "SparseOperator":
        self.matrix = _moved(self.matrix, device)
        self.matrix_t = _moved(self.matrix_t, device)
        return self
