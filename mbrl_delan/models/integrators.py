"""Fixed-step integrators over (q, qd) with the action held for the whole step.

Positions advance through `integrate_pos`, so the same code serves every joint type.
"""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

from mbrl_delan.systems.posarith import integrate_pos
from mbrl_delan.systems.system import JointLayout, State

Acceleration = Callable[[Tensor, Tensor], Tensor]  # (q (..., nq), qd (..., nv)) -> qdd (..., nv)
# (q (..., nq), qd (..., nv)) -> qd within the model's velocity range (..., nv)
VelocityLimit = Callable[[Tensor, Tensor], Tensor]
INTEGRATORS = ("euler", "rk4")


def _unlimited(q: Tensor, qd: Tensor) -> Tensor:
    return qd


def semi_implicit_euler(
    layout: JointLayout,
    accel: Acceleration,
    q: Tensor,
    qd: Tensor,
    dt: float,
    limit: VelocityLimit = _unlimited,
) -> State:
    """qd' = limit(qd + dt * qdd(q, qd)); q' = q (+) dt * qd'."""
    qd_next = limit(q, qd + dt * accel(q, qd))
    return State(q=integrate_pos(layout, q, qd_next, dt), qd=qd_next)


def rk4(
    layout: JointLayout,
    accel: Acceleration,
    q: Tensor,
    qd: Tensor,
    dt: float,
    limit: VelocityLimit = _unlimited,
) -> State:
    """Classical RK4 on (q, qd); stage positions are built with integrate_pos, from stage
    velocities within `limit`."""
    a1 = accel(q, qd)
    v2 = limit(q, qd + 0.5 * dt * a1)
    a2 = accel(integrate_pos(layout, q, qd, 0.5 * dt), v2)
    v3 = limit(q, qd + 0.5 * dt * a2)
    a3 = accel(integrate_pos(layout, q, v2, 0.5 * dt), v3)
    v4 = limit(q, qd + dt * a3)
    a4 = accel(integrate_pos(layout, q, v3, dt), v4)
    velocity = limit(q, (qd + 2.0 * v2 + 2.0 * v3 + v4) / 6.0)
    q_next = integrate_pos(layout, q, velocity, dt)
    return State(q=q_next, qd=limit(q_next, qd + dt * (a1 + 2.0 * a2 + 2.0 * a3 + a4) / 6.0))


def integrate(
    layout: JointLayout,
    accel: Acceleration,
    q: Tensor,
    qd: Tensor,
    dt: float,
    method: str = "rk4",
    substeps: int = 1,
    limit: VelocityLimit = _unlimited,
) -> State:
    """Advance (q, qd) by dt in `substeps` equal steps of `method` ('euler' or 'rk4'); the
    velocities that move the positions are kept within `limit` (none by default)."""
    if method not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {method!r}")
    if substeps < 1:
        raise ValueError(f"substeps must be >= 1, got {substeps}")
    step = rk4 if method == "rk4" else semi_implicit_euler
    h = dt / substeps
    state = State(q=q, qd=qd)
    for _ in range(substeps):
        state = step(layout, accel, state.q, state.qd, h, limit)
    return state
