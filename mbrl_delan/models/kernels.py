"""The model's maths in the forms a compiled rollout runs fastest, chosen while compiling.

Each function computes the same value eagerly and compiled; under `torch.compile` (the
acceleration layer, `mbrl_delan.accelerate`) it takes a form that fuses into neighbouring
elementwise kernels: broadcast products for small matrix products, one exponential and a
polynomial for softplus and its slope, substitution written out for small triangular solves.
This module and the acceleration layer are the only places that ask
`torch.compiler.is_compiling()`.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

SMALL_SOLVE = 6  # compiled forward dynamics solve M x = b by unrolled substitution up to this n

# Under compilation a product with at most this many inputs is written as broadcast
# products, which fuse into the neighbouring elementwise kernels instead of calling a matmul
# on a sliver of a matrix (an output this small is best left to the matmul: as a reduction
# it ran 3x slower).
SMALL_DIM = 4

# eager, `matvec` over chunks of the batch whose broadcast product holds at most this many
# elements (4 MB in float32: it stays in cache)
PRODUCT_CHUNK = 1 << 20


# log(1 + e) / e on e in [0, 1], degree 8 (Chebyshev fit, increasing powers): e p(e) is within
# 1.3e-7 of log(1 + e) in float32 evaluation, about float32's own rounding of values near 0.7.
LOG1P_UNIT_COEFFS = (
    0.999999971, -0.499995015, 0.333192713, -0.248443699, 0.191114311,
    -0.136747697, 0.078361668, -0.0295885074, 0.0052534578,
)  # fmt: skip


def log1p_unit(e: Tensor) -> Tensor:
    """log(1 + e) for e in [0, 1] as e p(e), a polynomial (Horner: 9 multiply-adds).

    For float32 and lower: within 1.3e-7 of log1p, and compiled it fuses into the
    neighbouring kernel at a fraction of a vectorised log1p's cost (the softplus of a
    compiled DeLaN step spent a quarter of its time in log1p). float64 keeps `torch.log1p`.
    """
    if e.dtype == torch.float64:
        return torch.log1p(e)
    acc = e * LOG1P_UNIT_COEFFS[-1] + LOG1P_UNIT_COEFFS[-2]
    for c in reversed(LOG1P_UNIT_COEFFS[:-2]):
        acc = acc * e + c
    return e * acc


def activate(name: str, z: Tensor) -> tuple[Tensor, Tensor]:
    """Activation value and its derivative at z."""
    if name == "softplus":
        if torch.compiler.is_compiling():
            # one exp and one polynomial for both (3 transcendentals otherwise), stable for
            # any z: softplus(z) = max(z, 0) + log(1 + e), sigmoid from the same e = exp(-|z|)
            e = torch.exp(-z.abs())
            inv = 1.0 / (1.0 + e)
            return z.clamp(min=0) + log1p_unit(e), torch.where(z >= 0, inv, e * inv)
        return F.softplus(z), torch.sigmoid(z)
    y = torch.tanh(z)
    return y, 1.0 - y * y


def linear(x: Tensor, weight: Tensor, bias: Tensor | None = None) -> Tensor:
    """x W^T (+ b): (..., k), (m, k) -> (..., m). Small k under compilation: broadcast
    products that fuse into the next elementwise kernel (same value)."""
    if not (torch.compiler.is_compiling() and 0 < weight.shape[-1] <= SMALL_DIM):
        return F.linear(x, weight, bias)  # k = 0 too (no joint held still: an empty sum)
    out = _broadcast_products(x, weight, dim=1)
    return out if bias is None else out + bias


def column_major(layer: nn.Linear) -> None:
    """Store the weight (m, k) column by column, same values: compiled, `linear` with a small
    k reads each column as one vector (row-major, the stride-k reads kept the products
    scalar). `.to()`, `load_state_dict` and optimizers keep the layout."""
    trainable = layer.weight.requires_grad
    layer.weight = nn.Parameter(layer.weight.detach().t().contiguous().t(), requires_grad=trainable)


def linear_t(x: Tensor, weight: Tensor) -> Tensor:
    """x W: (..., m), (m, k) -> (..., k), the product with the transpose that a backward
    pass through `linear` needs; small m under compilation as broadcast products. (No `.T`
    view of a parameter: a compiled `while_loop` refuses two of its inputs aliasing.)"""
    if not (torch.compiler.is_compiling() and weight.shape[0] <= SMALL_DIM):
        return x @ weight
    return _broadcast_products(x, weight, dim=0)


def matvec(A: Tensor, x: Tensor) -> Tensor:
    """A x for a batch of matrices: (..., m, k), (..., k) -> (..., m).

    A broadcast product and a sum (`_product_sum`), eager and compiled: a batched
    matrix-vector product (`bmm` with one column) and its backward, an outer product as `bmm`
    with k = 1, ran 5.6x slower on a CPU (humanoid_CMU's 62 x 62 factor, batch 256, forward
    and backward).
    """
    return _product_sum(A, x.unsqueeze(-2), -1)


def matvec_t(A: Tensor, x: Tensor) -> Tensor:
    """A^T x for a batch of matrices without transposing A: (..., m, k), (..., m) -> (..., k)."""
    return _product_sum(A, x.unsqueeze(-1), -2)


def _product_sum(A: Tensor, v: Tensor, dim: int) -> Tensor:
    """(A * v).sum(dim), A (..., m, k) and v broadcast to it. Eager, a product of more than
    `PRODUCT_CHUNK` elements runs over chunks of the batch: one temporary of 63 MB (batch
    4,096 of 62 x 62) took 3x a `bmm`'s time, chunks of 4 MB less than half of it."""
    lead = A.shape[:-2]
    if torch.compiler.is_compiling() or A.numel() <= PRODUCT_CHUNK or v.shape[:-2] != lead:
        return (A * v).sum(dim)
    A_flat, v_flat = A.flatten(0, -3), v.flatten(0, -3)  # (B, m, k), (B, 1, k) or (B, m, 1)
    per = max(1, PRODUCT_CHUNK // A_flat[0].numel())
    parts = [(a * u).sum(dim) for a, u in zip(A_flat.split(per), v_flat.split(per), strict=True)]
    return torch.cat(parts).unflatten(0, lead)


def _broadcast_products(x: Tensor, weight: Tensor, dim: int) -> Tensor:
    """sum_i x[..., i] * weight.select(dim, i): (..., k), weight with k along `dim` -> (...,
    the other dim). Elementwise, so the compiler fuses it with its neighbours."""
    out = x[..., 0:1] * weight.select(dim, 0)
    for i in range(1, weight.shape[dim]):
        out = out + x[..., i : i + 1] * weight.select(dim, i)
    return out


def cholesky_solve(L: Tensor, b: Tensor) -> Tensor:
    """x with L L^T x = b, L lower triangular: (..., n, n), (..., n) -> (..., n).

    Compiled with n <= `SMALL_SOLVE`: `unrolled_cholesky_solve`.

    On CUDA by two triangular solves (cuBLAS): a batched `torch.cholesky_solve` runs MAGMA
    there, which allocates device memory per call, so a CUDA graph cannot capture it.
    """
    if torch.compiler.is_compiling() and L.shape[-1] <= SMALL_SOLVE:
        return unrolled_cholesky_solve(L, b)
    rhs = b.unsqueeze(-1)  # (..., n, 1)
    if not L.is_cuda:
        return torch.cholesky_solve(rhs, L).squeeze(-1)
    y = torch.linalg.solve_triangular(L, rhs, upper=False)
    return torch.linalg.solve_triangular(L.transpose(-1, -2), y, upper=True).squeeze(-1)


def unrolled_cholesky_solve(L: Tensor, b: Tensor) -> Tensor:
    """x with L L^T x = b by substitution written out per entry: (..., n, n), (..., n) -> (..., n).

    For small n under compilation, where it fuses into elementwise kernels (a batched
    LAPACK call costs about 10 us per 1,000 matrices of any size).
    """
    n = L.shape[-1]
    y: list[Tensor] = []
    for i in range(n):  # L y = b
        acc = b[..., i]
        for j in range(i):
            acc = acc - L[..., i, j] * y[j]
        y.append(acc / L[..., i, i])
    x: list[Tensor] = [y[0]] * n
    for i in reversed(range(n)):  # L^T x = y
        acc = y[i]
        for j in range(i + 1, n):
            acc = acc - L[..., j, i] * x[j]
        x[i] = acc / L[..., i, i]
    return torch.stack(x, dim=-1)
