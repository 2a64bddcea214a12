"""Action sequences as splines over a few knots: what the sampling planners search.

A plan of H control steps is K knot values p_k (K, nu) at control steps t_k (t_0 = 0,
t_{K-1} = H - 1, spread evenly and rounded). The actions at every step are a linear map of
the knots, u = W p with W (H, K), for each interpolation:

- ``zero``: zero-order hold, u_t = p_k for t_k <= t < t_{k+1} (the last knot holds at H - 1);
- ``linear``: straight lines between knots;
- ``cubic``: cubic Hermite segments with finite-difference slopes
  m_k = (p_{k+1} - p_{k-1}) / (t_{k+1} - t_{k-1}) (one-sided at the ends), so the actions
  and their rate change smoothly; they may overshoot the knots (the planner clamps them).

The knot values are the actions at the knot steps, so the previous plan's spline read at
the shifted knot times (`knots_of` of the shifted plan) is its warm start.
"""

from __future__ import annotations

import torch
from torch import Tensor

INTERPOLATIONS = ("zero", "linear", "cubic")


def knot_steps(horizon: int, knots: int) -> Tensor:
    """The control step of each knot: K distinct steps from 0 to H - 1. (K,) long"""
    if knots == 1:
        return torch.zeros(1, dtype=torch.long)
    return torch.round(torch.linspace(0, horizon - 1, knots, dtype=torch.float64)).long()


def interpolation_matrix(horizon: int, steps: Tensor, kind: str) -> Tensor:
    """W (H, K) float64 with u = W p for knot values p (K,) at `steps` (K,)."""
    K = steps.numel()
    t = torch.arange(horizon, dtype=torch.float64)
    tk = steps.to(torch.float64)
    # the segment [t_k, t_{k+1}] of each step (the last step belongs to the last segment)
    seg = (torch.searchsorted(tk, t, right=True) - 1).clamp(0, max(K - 2, 0))
    W = torch.zeros(horizon, K, dtype=torch.float64)
    rows = torch.arange(horizon)
    if K == 1 or kind == "zero":
        hold = (torch.searchsorted(tk, t, right=True) - 1).clamp(0, K - 1)
        W[rows, hold] = 1.0
        return W
    dt = tk[seg + 1] - tk[seg]
    s = (t - tk[seg]) / dt  # (H,) in [0, 1]
    if kind == "linear":
        W[rows, seg] += 1.0 - s
        W[rows, seg + 1] += s
        return W
    slopes = _slope_matrix(tk)  # (K, K): m = S p
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    W[rows, seg] += h00
    W[rows, seg + 1] += h01
    W += (h10 * dt)[:, None] * slopes[seg] + (h11 * dt)[:, None] * slopes[seg + 1]
    return W


def _slope_matrix(tk: Tensor) -> Tensor:
    """S (K, K) with the finite-difference slopes m = S p at the knots (K >= 2)."""
    K = tk.numel()
    S = torch.zeros(K, K, dtype=torch.float64)
    for k in range(K):
        a, b = max(k - 1, 0), min(k + 1, K - 1)
        S[k, a] -= 1.0 / (tk[b] - tk[a])
        S[k, b] += 1.0 / (tk[b] - tk[a])
    return S


class KnotSpline:
    """Plans (H, nu) from knots (K, nu): `actions` maps knots to every step, `knots_of` reads
    a plan's knots. With `knots` None (or H) every step is a knot and both are the identity.

    Args:
        horizon: H, control steps of a plan (>= 1).
        knots: K, 1 <= K <= H (2 or more for linear and cubic); None: every step.
        interpolation: one of `INTERPOLATIONS`.
    """

    def __init__(self, horizon: int, knots: int | None = None, interpolation: str = "linear"):
        if interpolation not in INTERPOLATIONS:
            raise ValueError(
                f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}"
            )
        if knots is not None and not 1 <= knots <= horizon:
            raise ValueError(f"knots must be in [1, horizon={horizon}], got {knots}")
        if knots == 1 and interpolation != "zero":
            raise ValueError(f"{interpolation} interpolation needs knots >= 2, got 1")
        self.horizon, self.interpolation = horizon, interpolation
        self.identity = knots is None or knots == horizon
        self.knots = horizon if knots is None else knots
        self.steps = knot_steps(horizon, self.knots)  # (K,)
        self._basis = interpolation_matrix(horizon, self.steps, interpolation)  # (H, K)
        self._cache: dict[tuple[torch.device, torch.dtype], tuple[Tensor, Tensor]] = {}

    def _on(self, like: Tensor) -> tuple[Tensor, Tensor]:
        key = (like.device, like.dtype)
        if key not in self._cache:
            with torch.inference_mode(False):  # normal tensors, usable in and out of it
                basis = self._basis.to(like.device, like.dtype)
                self._cache[key] = (basis, self.steps.to(like.device))
        return self._cache[key]

    def actions(self, knots: Tensor) -> Tensor:
        """(..., K, nu) -> (..., H, nu)."""
        if self.identity:
            return knots
        basis, _ = self._on(knots)
        return torch.einsum("hk,...ku->...hu", basis, knots)

    def knots_of(self, actions: Tensor) -> Tensor:
        """The plan's values at the knot steps. (..., H, nu) -> (..., K, nu)"""
        if self.identity:
            return actions
        _, steps = self._on(actions)
        return actions.index_select(-2, steps)
