"""Constant sparse linear maps with a fast backward."""

from __future__ import annotations

import warnings

import torch

__all__ = ["sparse_apply", "incidence", "to_csr"]


class _SparseApply(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, op, op_t):
        ctx.op_t = op_t
        return op @ x

    @staticmethod
    def backward(ctx, g):
        return ctx.op_t @ g.contiguous(), None, None  # an expanded (stride-0) g takes a slow path


def sparse_apply(op: torch.Tensor, op_t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """op @ x for a constant sparse CSR op (M, N) and dense x (N, C), with op^T (precomputed) for the
    backward: torch's own CSR backward rebuilds the transpose every call (measured 5x slower)."""
    return _SparseApply.apply(x, op, op_t)


def to_csr(coo: torch.Tensor) -> torch.Tensor:
    with warnings.catch_warnings():  # "CSR support is in beta": we use only CSR @ dense
        warnings.simplefilter("ignore", UserWarning)
        return coo.coalesce().to_sparse_csr()


def incidence(faces: torch.Tensor, n_vertices: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(A, A^T) as CSR: A (V, 3F) sums per-corner values onto vertices, i.e. for per-face values f (F, C)
    repeated per corner, A @ cat([f, f, f]) == the index_add over faces[:, 0], faces[:, 1], faces[:, 2]."""
    f = faces.long()
    rows = torch.cat([f[:, 0], f[:, 1], f[:, 2]])
    cols = torch.arange(3 * len(f))
    a = torch.sparse_coo_tensor(torch.stack([rows, cols]), torch.ones(len(rows)), (n_vertices, 3 * len(f)), check_invariants=False)
    at = torch.sparse_coo_tensor(torch.stack([cols, rows]), torch.ones(len(rows)), (3 * len(f), n_vertices), check_invariants=False)
    return to_csr(a), to_csr(at)
