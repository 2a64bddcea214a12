"""Fixed-step integrators over (q, qd) with the action held for the whole step.

Positions advance through `integrate_pos`, so the same code serves every joint type.
"""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

from mbrl_delan.systems.posarith import integrate_pos
from mbrl_delan.systems.system import JointLayout, State

Acceleration = Callable[[Tensor, Tensor], Tensor]  # (q (..., nq), qd (..., nv)) -> qdd (..., nv)
INTEGRATORS = ("euler", "rk4")


def semi_implicit_euler(
    layout: JointLayout, accel: Acceleration, q: Tensor, qd: Tensor, dt: float
) -> State:
    """qd' = qd + dt * qdd(q, qd); q' = q (+) dt * qd'."""
    qd_next = qd + dt * accel(q, qd)
    return State(q=integrate_pos(layout, q, qd_next, dt), qd=qd_next)


def rk4(layout: JointLayout, accel: Acceleration, q: Tensor, qd: Tensor, dt: float) -> State:
    """Classical RK4 on (q, qd); stage positions are built with integrate_pos."""
    a1 = accel(q, qd)
    v2 = qd + 0.5 * dt * a1
    a2 = accel(integrate_pos(layout, q, qd, 0.5 * dt), v2)
    v3 = qd + 0.5 * dt * a2
    a3 = accel(integrate_pos(layout, q, v2, 0.5 * dt), v3)
    v4 = qd + dt * a3
    a4 = accel(integrate_pos(layout, q, v3, dt), v4)
    velocity = (qd + 2.0 * v2 + 2.0 * v3 + v4) / 6.0
    return State(
        q=integrate_pos(layout, q, velocity, dt),
        qd=qd + dt * (a1 + 2.0 * a2 + 2.0 * a3 + a4) / 6.0,
    )


def integrate(
    layout: JointLayout,
    accel: Acceleration,
    q: Tensor,
    qd: Tensor,
    dt: float,
    method: str = "rk4",
    substeps: int = 1,
) -> State:
    """Advance (q, qd) by dt in `substeps` equal steps of `method` ('euler' or 'rk4')."""
    if method not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {method!r}")
    if substeps < 1:
        raise ValueError(f"substeps must be >= 1, got {substeps}")
    step = rk4 if method == "rk4" else semi_implicit_euler
    h = dt / substeps
    state = State(q=q, qd=qd)
    for _ in range(substeps):
        state = step(layout, accel, state.q, state.qd, h)
    return state
