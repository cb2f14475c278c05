"""The fixed sparse operator against its dense matrix: y = A x, and the gradient Aᵀ g."""

import warnings

import numpy as np
import pytest
import torch

from SDFCARLib.sparse import SparseOperator


def _entries(seed=0, rows=7, cols=5, nnz=12):
    rng = np.random.default_rng(seed)
    r = torch.as_tensor(rng.integers(0, rows, nnz))
    c = torch.as_tensor(rng.integers(0, cols, nnz))
    v = torch.as_tensor(rng.random(nnz))
    return r, c, v, (rows, cols)


def _dense(r, c, v, shape):
    dense = torch.zeros(shape, dtype=v.dtype)
    dense.index_put_((r, c), v, accumulate=True)  # duplicates add, as the coalesced operator does
    return dense


@pytest.mark.parametrize("columns", [None, 3])
def test_product_and_gradient_equal_the_dense_matrix(columns):
    r, c, v, shape = _entries()
    dense = _dense(r, c, v, shape)
    operator = SparseOperator(r, c, v, shape, coalesce=True)
    x = torch.rand((shape[1],) if columns is None else (shape[1], columns), dtype=v.dtype, requires_grad=True)
    y = operator(x)
    torch.testing.assert_close(y, dense @ x.detach())
    g = torch.rand_like(y)
    (y * g).sum().backward()
    torch.testing.assert_close(x.grad, dense.T @ g)


def test_unsorted_entries_without_duplicates_give_the_same_operator():
    r, c, v, shape = _entries(nnz=30)
    keep = np.unique((r * shape[1] + c).numpy(), return_index=True)[1]  # one entry per position
    r, c, v = r[keep], c[keep], v[keep]
    order = torch.randperm(len(r), generator=torch.Generator().manual_seed(1))
    operator = SparseOperator(r[order], c[order], v[order], shape)
    x = torch.rand(shape[1], dtype=v.dtype)
    torch.testing.assert_close(operator(x), _dense(r, c, v, shape) @ x)
    assert operator.nnz == len(r)


def test_wrong_input_length_is_refused():
    r, c, v, shape = _entries()
    with pytest.raises(ValueError, match="takes 5 inputs, got 4"):
        SparseOperator(r, c, v, shape, coalesce=True)(torch.zeros(4, dtype=v.dtype))


def test_torch_notes_on_the_deliberately_unchecked_construction_do_not_reach_the_user(monkeypatch):
    # torch 2.11 with CUDA (seen on an H200) warns on every CSR matrix built without the invariant check
    real_csr, real_coo = torch.sparse_csr_tensor, torch.sparse_coo_tensor

    def noisy(real):
        def build(*args, **kwargs):
            warnings.warn("Sparse invariant checks are implicitly disabled. Memory errors ...", UserWarning)
            warnings.warn("Sparse CSR tensor support is in beta at the moment", UserWarning)
            return real(*args, **kwargs)
        return build

    monkeypatch.setattr(torch, "sparse_csr_tensor", noisy(real_csr))
    monkeypatch.setattr(torch, "sparse_coo_tensor", noisy(real_coo))
    r, c, v, shape = _entries()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        operator = SparseOperator(r, c, v, shape, coalesce=True)
    torch.testing.assert_close(operator(torch.ones(shape[1], dtype=v.dtype)), _dense(r, c, v, shape).sum(1))


def test_cpu_matrices_take_32_bit_indices_where_they_fit_and_give_the_same_products():
    from SDFCARLib.sparse import index_dtype

    assert index_dtype(torch.device("cpu"), 10, (5, 7)) == torch.int32
    assert index_dtype(torch.device("cpu"), 2**31, (5, 7)) == torch.int64  # more entries than int32 counts
    assert index_dtype(torch.device("cpu"), 10, (5, 2**31)) == torch.int64
    assert index_dtype(torch.device("meta"), 10, (5, 7)) == torch.int64  # off the CPU: 64-bit, as before
    r, c, v, shape = _entries(nnz=30)
    operator = SparseOperator(r, c, v, shape, coalesce=True).to("cpu")
    assert operator.matrix.col_indices().dtype == torch.int32 and operator.matrix_t.crow_indices().dtype == torch.int32
    x = torch.rand(shape[1], 3, dtype=v.dtype, requires_grad=True)
    y = operator(x)
    torch.testing.assert_close(y, _dense(r, c, v, shape) @ x.detach())
    y.sum().backward()
    torch.testing.assert_close(x.grad, _dense(r, c, v, shape).T @ torch.ones_like(y))
