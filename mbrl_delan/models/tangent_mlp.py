"""An MLP that carries one tangent forward and one cotangent back, by hand.

DeLaN needs the network's derivative along the velocity (a jvp) and a gradient with respect
to q (a vjp). Writing both out per layer keeps the cost at a few network passes whatever
the number of DoF, needs no autograd at planning time (so it runs under
`torch.inference_mode`), and stays differentiable by ordinary autograd for training.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor, nn

from mbrl_delan.models.kernels import SMALL_DIM, activate, column_major, linear, linear_t

ACTIVATIONS = ("softplus", "tanh")


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
            x, slope = activate(self.activation, linear(x, layer.weight, layer.bias))
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
