"""An MLP that carries one tangent forward and one cotangent back, by hand.

DeLaN needs the network's derivative along the velocity (a jvp) and a gradient with respect
to q (a vjp). Writing both out per layer keeps the cost at a few network passes whatever
the number of DoF, needs no autograd at planning time (so it runs under
`torch.inference_mode`), and stays differentiable by ordinary autograd for training.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.nn import functional as F

ACTIVATIONS = ("softplus", "tanh")


# Under compilation a product with at most this many inputs is written as broadcast
# products, which fuse into the neighbouring elementwise kernels instead of calling a matmul
# on a sliver of a matrix (an output this small is best left to the matmul: as a reduction
# it ran 3x slower).
SMALL_DIM = 4


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


def _activate(name: str, z: Tensor) -> tuple[Tensor, Tensor]:
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
    if not (torch.compiler.is_compiling() and weight.shape[-1] <= SMALL_DIM):
        return F.linear(x, weight, bias)
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


def _broadcast_products(x: Tensor, weight: Tensor, dim: int) -> Tensor:
    """sum_i x[..., i] * weight.select(dim, i): (..., k), weight with k along `dim` -> (...,
    the other dim). Elementwise, so the compiler fuses it with its neighbours."""
    out = x[..., 0:1] * weight.select(dim, 0)
    for i in range(1, weight.shape[dim]):
        out = out + x[..., i : i + 1] * weight.select(dim, i)
    return out


@dataclass
class MLPPass:
    """The values kept from a forward pass for the backward (vjp) pass."""

    out: Tensor  # (..., out)
    d_out: Tensor | None  # (..., out) tangent of the output, when a tangent was given
    slopes: list[Tensor]  # activation derivatives per hidden layer, (..., hidden)


class TangentMLP(nn.Module):
    """x -> out through `layers` hidden layers of width `hidden`."""

    def __init__(
        self, n_in: int, n_out: int, hidden: int, layers: int, activation: str = "softplus"
    ) -> None:
        super().__init__()
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {ACTIVATIONS}, got {activation!r}")
        if layers < 1 or hidden < 1:
            raise ValueError(f"need layers >= 1 and hidden >= 1, got {layers=} {hidden=}")
        sizes = [n_in] + [hidden] * layers
        self.hidden = nn.ModuleList(
            nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:], strict=True)
        )
        for layer in self.hidden:
            if layer.in_features <= SMALL_DIM:
                column_major(layer)
        self.head = nn.Linear(hidden, n_out)
        self.activation = activation

    def body(self, x: Tensor, dx: Tensor | None = None) -> MLPPass:
        """The hidden layers only: `out` is the last hidden activation (..., hidden)."""
        slopes = []
        for layer in self.hidden:
            x, slope = _activate(self.activation, linear(x, layer.weight, layer.bias))
            if dx is not None:
                dx = slope * linear(dx, layer.weight)
            slopes.append(slope)
        return MLPPass(out=x, d_out=dx, slopes=slopes)

    def body_vjp(self, fwd: MLPPass, cotangent: Tensor) -> Tensor:
        """Cotangent on the last hidden activation (..., hidden) -> on the input (..., n_in)."""
        g = cotangent
        for layer, slope in zip(reversed(self.hidden), reversed(fwd.slopes), strict=True):
            g = linear_t(g * slope, layer.weight)
        return g

    def forward(self, x: Tensor, dx: Tensor | None = None) -> MLPPass:
        """x: (..., n_in); dx: optional tangent (..., n_in)."""
        body = self.body(x, dx)
        head = self.head
        d_out = None if body.d_out is None else linear(body.d_out, head.weight)
        out = linear(body.out, head.weight, head.bias)
        return MLPPass(out=out, d_out=d_out, slopes=body.slopes)

    def vjp(self, fwd: MLPPass, cotangent: Tensor) -> Tensor:
        """(d out / d x)^T cotangent: (..., n_out) -> (..., n_in)."""
        return self.body_vjp(fwd, linear_t(cotangent, self.head.weight))
