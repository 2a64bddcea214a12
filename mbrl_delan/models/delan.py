"""Deep Lagrangian Network: inverse and forward dynamics with Lagrangian structure.

    tau = M(q) qdd + c(q, qd) + g(q) + d(q, qd)

- M(q) = L L^T with L lower-triangular and a positive diagonal (softplus + shift): M is
  symmetric positive definite for every input and every weight.
- g(q) = dV/dq from a potential-energy network V(q).
- c(q, qd) = Mdot qd - 1/2 d/dq (qd^T M qd). With w = L^T qd and Ldot the derivative of L
  along qd, Mdot qd = Ldot w + L (Ldot^T qd) and 1/2 d/dq (qd^T M qd) = (dL/dq)^T [qd w^T]:
  one tangent pass and one cotangent pass through the L network, whatever the DoF count.
- d(q, qd) = D qd + F tanh(qd / v_c): viscous and Coulomb friction with D, F >= 0, so
  qd^T d >= 0 always (dissipative).
- Forward dynamics qdd = M^-1 (B a - c - g - d) by two triangular solves with L.

The mass and potential parts are swappable fields (`CholeskyField`, `PotentialField`), so
the same equations run on networks and, in tests, on closed-form models of known systems.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn
from torch.nn import functional as F

from mbrl_delan import keys
from mbrl_delan.models.base import LossOutput, WorldModel
from mbrl_delan.models.features import QFeatures
from mbrl_delan.models.integrators import INTEGRATORS, integrate
from mbrl_delan.models.tangent_mlp import TangentMLP
from mbrl_delan.systems.posarith import differentiate_pos
from mbrl_delan.systems.system import JointLayout, State

LOSSES = ("forward", "inverse", "both")


@dataclass
class CholeskyJet:
    """L(q), its derivative along qd, and the pullback of a cotangent on L to velocity space."""

    L: Tensor  # (..., n, n) lower-triangular, positive diagonal
    L_dot: Tensor  # (..., n, n) dL/dt = dL/dq [qd]
    pullback: Callable[[Tensor], Tensor]  # cotangent on L (..., n, n) -> (..., n)


@dataclass
class PotentialJet:
    potential_energy: Tensor  # (...)
    gravity: Tensor  # dV/dq, (..., n)


@dataclass
class LagrangianTerms:
    """Every term of the equations of motion at (q, qd)."""

    mass_matrix: Tensor  # (..., n, n)
    cholesky: Tensor  # (..., n, n)
    coriolis: Tensor  # c(q, qd), (..., n)
    gravity: Tensor  # g(q), (..., n)
    dissipation: Tensor  # d(q, qd), (..., n)
    kinetic_energy: Tensor  # 1/2 qd^T M qd, (...)
    potential_energy: Tensor  # V(q), (...)

    @property
    def bias(self) -> Tensor:
        """c + g + d: the generalized force needed at zero acceleration. (..., n)"""
        return self.coriolis + self.gravity + self.dissipation


class CholeskyField(nn.Module, abc.ABC):
    @abc.abstractmethod
    def jet(self, q: Tensor, qd: Tensor) -> CholeskyJet: ...


class PotentialField(nn.Module, abc.ABC):
    @abc.abstractmethod
    def jet(self, q: Tensor) -> PotentialJet: ...


class CholeskyNetwork(CholeskyField):
    """L(q) from an MLP on features of q: n diagonal entries (softplus + shift) and n(n-1)/2 below."""

    def __init__(
        self, features: QFeatures, n: int, hidden: int, layers: int, activation: str,
        diag_shift: float,
    ) -> None:
        super().__init__()
        if diag_shift <= 0:
            raise ValueError(f"diag_shift must be > 0 so M stays positive definite, got {diag_shift}")
        self.features, self.n, self.diag_shift = features, n, diag_shift
        n_off = n * (n - 1) // 2
        self.mlp = TangentMLP(features.n_features, n + n_off, hidden, layers, activation)
        rows, cols = torch.tril_indices(n, n, -1)
        gather = torch.full((n * n,), n + n_off, dtype=torch.long)  # default: the zero slot
        gather[torch.arange(n) * (n + 1)] = torch.arange(n)
        gather[rows * n + cols] = n + torch.arange(n_off)
        self.register_buffer("rows", rows, persistent=False)
        self.register_buffer("cols", cols, persistent=False)
        self.register_buffer("gather", gather, persistent=False)

    def _assemble(self, diag: Tensor, off: Tensor) -> Tensor:
        """(..., n), (..., n(n-1)/2) -> lower-triangular (..., n, n)."""
        flat = torch.cat([diag, off, diag.new_zeros(diag.shape[:-1] + (1,))], dim=-1)
        return flat[..., self.gather].unflatten(-1, (self.n, self.n))

    def jet(self, q: Tensor, qd: Tensor) -> CholeskyJet:
        n = self.n
        fwd = self.mlp(self.features(q), self.features.jvp(q, qd))
        raw_diag, off = fwd.out[..., :n], fwd.out[..., n:]
        slope = torch.sigmoid(raw_diag)
        L = self._assemble(F.softplus(raw_diag) + self.diag_shift, off)
        L_dot = self._assemble(slope * fwd.d_out[..., :n], fwd.d_out[..., n:])

        def pullback(cotangent: Tensor) -> Tensor:
            d_diag = torch.diagonal(cotangent, dim1=-2, dim2=-1) * slope
            d_off = cotangent[..., self.rows, self.cols]
            d_features = self.mlp.vjp(fwd, torch.cat([d_diag, d_off], dim=-1))
            return self.features.vjp(q, d_features)

        return CholeskyJet(L=L, L_dot=L_dot, pullback=pullback)


class PotentialNetwork(PotentialField):
    """V(q) from an MLP on features of q; g = dV/dq by one cotangent pass."""

    def __init__(self, features: QFeatures, hidden: int, layers: int, activation: str) -> None:
        super().__init__()
        self.features = features
        self.mlp = TangentMLP(features.n_features, 1, hidden, layers, activation)

    def jet(self, q: Tensor) -> PotentialJet:
        fwd = self.mlp(self.features(q))
        ones = torch.ones_like(fwd.out)
        gravity = self.features.vjp(q, self.mlp.vjp(fwd, ones))
        return PotentialJet(potential_energy=fwd.out.squeeze(-1), gravity=gravity)


class Dissipation(nn.Module):
    """d(q, qd) = D qd + F tanh(qd / v_c), with D = softplus(.) and F = softplus(.) per DoF."""

    def __init__(self, n: int, coulomb: bool = True, coulomb_velocity: float = 0.01) -> None:
        super().__init__()
        self.raw_viscous = nn.Parameter(torch.full((n,), -4.0))
        self.raw_coulomb = nn.Parameter(torch.full((n,), -6.0)) if coulomb else None
        self.coulomb_velocity = coulomb_velocity

    @property
    def viscous(self) -> Tensor:
        """Learned viscous damping per DoF, (n,)."""
        return F.softplus(self.raw_viscous)

    def forward(self, qd: Tensor) -> Tensor:
        force = self.viscous * qd
        if self.raw_coulomb is not None:
            force = force + F.softplus(self.raw_coulomb) * torch.tanh(qd / self.coulomb_velocity)
        return force


class LagrangianDynamics(nn.Module):
    """The DeLaN equations over any mass and potential fields."""

    def __init__(
        self, mass: CholeskyField, potential: PotentialField, dissipation: Dissipation | None,
        actuation: Tensor,
    ) -> None:
        super().__init__()
        self.mass, self.potential, self.dissipation = mass, potential, dissipation
        self.register_buffer("actuation", actuation.clone())  # B, (n, nu)

    def terms(self, q: Tensor, qd: Tensor) -> LagrangianTerms:
        """All terms at (q, qd): (..., nq), (..., n)."""
        jet = self.mass.jet(q, qd)
        L, L_dot = jet.L, jet.L_dot
        w = (L.transpose(-1, -2) @ qd.unsqueeze(-1)).squeeze(-1)  # L^T qd
        w_dot = (L_dot.transpose(-1, -2) @ qd.unsqueeze(-1)).squeeze(-1)  # Ldot^T qd
        m_dot_qd = (L_dot @ w.unsqueeze(-1) + L @ w_dot.unsqueeze(-1)).squeeze(-1)
        half_grad_kinetic = jet.pullback(qd.unsqueeze(-1) * w.unsqueeze(-2))  # 1/2 d(qd^T M qd)/dq
        pot = self.potential.jet(q)
        diss = torch.zeros_like(qd) if self.dissipation is None else self.dissipation(qd)
        return LagrangianTerms(
            mass_matrix=L @ L.transpose(-1, -2),
            cholesky=L,
            coriolis=m_dot_qd - half_grad_kinetic,
            gravity=pot.gravity,
            dissipation=diss,
            kinetic_energy=0.5 * (w * w).sum(-1),
            potential_energy=pot.potential_energy,
        )

    def inverse_dynamics(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        """Generalized force tau = M qdd + c + g + d. (..., n)"""
        t = self.terms(q, qd)
        return (t.mass_matrix @ qdd.unsqueeze(-1)).squeeze(-1) + t.bias

    def forward_dynamics(self, q: Tensor, qd: Tensor, tau: Tensor) -> Tensor:
        """qdd = M^-1 (tau - c - g - d) by two triangular solves with L. (..., n)"""
        t = self.terms(q, qd)
        rhs = (tau - t.bias).unsqueeze(-1)
        return torch.cholesky_solve(rhs, t.cholesky).squeeze(-1)

    def generalized_force(self, action: Tensor) -> Tensor:
        """tau = B a: (..., nu) -> (..., n)."""
        return action @ self.actuation.T


def _scale(x: Tensor, floor_ratio: float = 1e-2) -> Tensor:
    """Per-column std with a floor relative to the largest (unactuated DoFs have std 0)."""
    std = x.std(dim=0) if x.shape[0] > 1 else x.abs().mean(dim=0)
    return std.clamp_min(floor_ratio * float(std.max().clamp_min(1e-8)))


class DeLaN(WorldModel):
    """DeLaN world model: the Lagrangian equations over networks, stepped by an integrator.

    Losses (`loss=`): 'forward' compares the integrated next state with the data, per DoF
    normalised by the std of the one-step change; 'inverse' compares the predicted torque
    B a with DeLaN's inverse dynamics at the finite-difference acceleration (or the batch's
    `qdd` when present), normalised by the per-DoF torque std; 'both' adds them.
    """

    def __init__(
        self,
        layout: JointLayout,
        actuation: Tensor,
        control_dt: float,
        hidden: int = 64,
        layers: int = 2,
        activation: str = "softplus",
        diag_shift: float = 1e-3,
        integrator: str = "rk4",
        substeps: int = 1,
        loss: str = "forward",
        dissipation: bool = True,
        coulomb: bool = True,
    ) -> None:
        super().__init__()
        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
        if loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
        if control_dt <= 0 or substeps < 1:
            raise ValueError(f"need control_dt > 0 and substeps >= 1, got {control_dt}, {substeps}")
        n = layout.nv
        features = QFeatures(layout)
        self.layout, self.control_dt = layout, control_dt
        self.integrator, self.substeps, self.loss_kind = integrator, substeps, loss
        self.dynamics = LagrangianDynamics(
            mass=CholeskyNetwork(features, n, hidden, layers, activation, diag_shift),
            potential=PotentialNetwork(features, hidden, layers, activation),
            dissipation=Dissipation(n, coulomb=coulomb) if dissipation else None,
            actuation=actuation.to(torch.get_default_dtype()),
        )
        for name in ("q_scale", "qd_scale", "tau_scale"):
            self.register_buffer(name, torch.ones(n))

    def terms(self, q: Tensor, qd: Tensor) -> LagrangianTerms:
        return self.dynamics.terms(q, qd)

    def acceleration(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """Forward dynamics under actuator controls: (..., nq), (..., nv), (..., nu) -> (..., nv)."""
        return self.dynamics.forward_dynamics(q, qd, self.dynamics.generalized_force(action))

    def step(
        self, q: Tensor, qd: Tensor, action: Tensor, generator: torch.Generator | None = None
    ) -> State:
        tau = self.dynamics.generalized_force(action)

        def accel(q_: Tensor, qd_: Tensor) -> Tensor:
            return self.dynamics.forward_dynamics(q_, qd_, tau)

        return integrate(
            self.layout, accel, q, qd, self.control_dt, self.integrator, self.substeps
        )

    @torch.no_grad()
    def fit_normalization(self, data: TensorDictBase) -> None:
        q, qd, q_next, qd_next = (
            data[k] for k in (keys.Q, keys.QD, keys.NEXT_Q, keys.NEXT_QD)
        )
        tau = self.dynamics.generalized_force(data[keys.ACTION].to(self.q_scale.dtype))
        self.q_scale.copy_(_scale(differentiate_pos(self.layout, q, q_next, 1.0)))
        self.qd_scale.copy_(_scale(qd_next - qd))
        self.tau_scale.copy_(_scale(tau))

    def loss(self, batch: TensorDictBase) -> LossOutput:
        q, qd, action = batch[keys.Q], batch[keys.QD], batch[keys.ACTION]
        q_next, qd_next = batch[keys.NEXT_Q], batch[keys.NEXT_QD]
        metrics: dict[str, float] = {}
        total = q.new_zeros(())
        if self.loss_kind in ("forward", "both"):
            pred = self.step(q, qd, action)
            e_q = differentiate_pos(self.layout, q_next, pred.q, 1.0) / self.q_scale
            e_qd = (pred.qd - qd_next) / self.qd_scale
            forward = e_q.pow(2).mean() + e_qd.pow(2).mean()
            metrics["forward_mse"] = float(forward.detach())
            total = total + forward
        if self.loss_kind in ("inverse", "both"):
            qdd = batch.get(keys.QDD, None)
            if qdd is None:
                qdd = (qd_next - qd) / self.control_dt
            tau = self.dynamics.generalized_force(action)
            e_tau = (self.dynamics.inverse_dynamics(q, qd, qdd) - tau) / self.tau_scale
            inverse = e_tau.pow(2).mean()
            metrics["inverse_mse"] = float(inverse.detach())
            total = total + inverse
        metrics["loss"] = float(total.detach())
        return LossOutput(loss=total, metrics=metrics)
