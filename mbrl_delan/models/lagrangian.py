"""The Lagrangian equations of motion over a mechanics field (DeLaN's maths).

    tau = M(q) qdd + c(q, qd) + g(q) + d(q, qd)

- M(q) = L L^T with L lower-triangular and a positive diagonal (softplus + shift): M is
  symmetric positive definite for every input and every weight.
- g(q) = dV/dq from a potential-energy network V(q).
- c(q, qd) = Mdot qd - 1/2 d/dq (qd^T M qd). With w = L^T qd and Ldot the derivative of L
  along qd, Mdot qd = Ldot w + L (Ldot^T qd) and 1/2 d/dq (qd^T M qd) = (dL/dq)^T [qd w^T]:
  one tangent pass and one cotangent pass through the L network, whatever the DoF count.
- d(q, qd) = D qd + F tanh(qd / v_c): viscous and Coulomb friction with D, F >= 0, so
  qd^T d >= 0 always (dissipative). With a Coulomb lead l >= 0 its argument is qd + l qdd
  (`Dissipation`); the forward solve then takes it linearly implicit.
- Forward dynamics qdd = M^-1 (B a - c - g - d) by two triangular solves with L.

L and V come from a swappable `MechanicsField`: a network with one trunk and two heads, or,
in tests, closed-form models of known systems, so the same equations serve both.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from mbrl_delan.models.features import rotation_matrix, skew, unskew_of_rt
from mbrl_delan.models.kernels import cholesky_solve, linear, matvec, matvec_t


@dataclass
class MechanicsJet:
    """L(q), V(q), the derivative of L along qd, and the pullback of cotangents to velocity space.

    `pullback(dL, dV)` returns (dL/dq)^T dL + (dV/dq)^T dV: one reverse pass for both.
    """

    L: Tensor  # (..., n, n) triangular (lower; upper if the field's `upper`), positive diagonal
    L_dot: Tensor  # (..., n, n) dL/dt = dL/dq [qd]
    potential_energy: Tensor  # (...)
    pullback: Callable[[Tensor, Tensor], Tensor]  # (..., n, n), (...) -> (..., n)
    # with a free root's frame (`LagrangianNetwork`, ``root_frame``): L = S factor, S the
    # rotation `frame` (..., 3, 3) on L's first three rows and the identity elsewhere, so
    # L is not triangular; M = L L^T is solved with the triangular `factor` (..., n, n)
    frame: Tensor | None = None
    factor: Tensor | None = None


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


class MechanicsField(nn.Module, abc.ABC):
    """Supplies L(q) and V(q) with the derivatives the Lagrangian equations need."""

    upper: bool = False  # L is upper-triangular (M = L L^T either way)

    @abc.abstractmethod
    def jet(self, q: Tensor, qd: Tensor) -> MechanicsJet: ...


def to_root_frame(R: Tensor, x: Tensor) -> Tensor:
    """A free root's world-frame linear entries x[..., :3] into its body frame (R^T x);
    the other entries as they are. (..., 3, 3), (..., n) -> (..., n)"""
    top = (R.transpose(-1, -2) @ x[..., :3].unsqueeze(-1)).squeeze(-1)
    return torch.cat([top, x[..., 3:]], dim=-1)


def from_root_frame(R: Tensor, x: Tensor) -> Tensor:
    """The inverse of `to_root_frame` (R x on the first three entries)."""
    top = (R @ x[..., :3].unsqueeze(-1)).squeeze(-1)
    return torch.cat([top, x[..., 3:]], dim=-1)


def root_frame_jet(jet: MechanicsJet, q: Tensor, qd: Tensor) -> MechanicsJet:
    """L = S L_b for a free root first (q[0:7], qd[0:6]): S = diag(R, I), R its rotation.

    MuJoCo's free joint moves with the world-frame linear velocity v and the body-frame
    angular velocity omega; in the body frame (R^T v, omega, joint rates) the kinetic
    energy of a free-floating body does not depend on where the root is or how it is
    turned, so M(q) = S M_b S^T with M_b = L_b L_b^T from features that leave the heading
    out: M (and with it c) turns with the body about the vertical. dS/dt = diag(R [omega]x, 0).
    """
    R = rotation_matrix(q[..., 3:7])  # (..., 3, 3)
    top, top_dot = jet.L[..., :3, :], jet.L_dot[..., :3, :]
    L = torch.cat([R @ top, jet.L[..., 3:, :]], dim=-2)
    R_dot = R @ skew(qd[..., 3:6])
    L_dot = torch.cat([R_dot @ top + R @ top_dot, jet.L_dot[..., 3:, :]], dim=-2)
    n = jet.L.shape[-1]

    def pullback(d_L: Tensor, d_V: Tensor) -> Tensor:
        d_top = d_L[..., :3, :]
        d_factor = torch.cat([R.transpose(-1, -2) @ d_top, d_L[..., 3:, :]], dim=-2)
        turn = unskew_of_rt(R, d_top @ top.transpose(-1, -2))  # through R: omega's cotangent
        return jet.pullback(d_factor, d_V) + F.pad(turn, (3, n - 6))

    return MechanicsJet(
        L=L,
        L_dot=L_dot,
        potential_energy=jet.potential_energy,
        pullback=pullback,
        frame=R,
        factor=jet.L,
    )


class Dissipation(nn.Module):
    """d(q, qd) = D qd + F tanh((qd + l qdd) / v_c), D = a softplus(.), F = b softplus(.) per
    DoF.

    a and b (`viscous_scale`, `coulomb_scale`, buffers, 1 by default) are positive units set
    from data (`DeLaN.fit_normalization` with `inertia_scaling`): d stays dissipative.
    `lead`: a learned Coulomb lead l = `LEAD_UNIT` softplus(.) >= 0 per DoF (else l = 0): the
    friction opposes where the velocity is going, as a soft friction constraint (MuJoCo's
    ``frictionloss`` opposes qdd + b qd, l = 1 / b) does; it starts at 0.69 `LEAD_UNIT`.
    Without qdd (energy, `LagrangianDynamics.terms`) the argument is qd.
    `learn_velocity`: the width v_c is learned per DoF, v_c = `coulomb_velocity` exp(w), w
    starting at 0: exact velocities pull it toward a sign law, noisy ones widen it to about
    their noise (the expected friction force under noise is smooth on that scale).
    """

    LEAD_UNIT = 0.01  # s

    def __init__(
        self,
        n: int,
        coulomb: bool = True,
        coulomb_velocity: float = 0.01,
        raw_init: float = -4.0,
        lead: bool = False,
        learn_velocity: bool = False,
    ) -> None:
        super().__init__()
        if lead and not coulomb:
            raise ValueError("a Coulomb lead needs Coulomb friction (coulomb=True)")
        if learn_velocity and not coulomb:
            raise ValueError("a learned Coulomb width needs Coulomb friction (coulomb=True)")
        self.raw_viscous = nn.Parameter(torch.full((n,), raw_init))
        self.raw_coulomb = nn.Parameter(torch.full((n,), raw_init - 2.0)) if coulomb else None
        self.raw_lead = nn.Parameter(torch.zeros(n)) if lead else None
        self.raw_velocity = nn.Parameter(torch.zeros(n)) if learn_velocity else None
        self.coulomb_velocity = coulomb_velocity
        self.register_buffer("viscous_scale", torch.ones(n))
        self.register_buffer("coulomb_scale", torch.ones(n))

    @property
    def viscous(self) -> Tensor:
        """Learned viscous damping per DoF, (n,)."""
        return self.viscous_scale * F.softplus(self.raw_viscous)

    @property
    def lead(self) -> Tensor | None:
        """The Coulomb lead l per DoF (n,) in s; None without."""
        return None if self.raw_lead is None else self.LEAD_UNIT * F.softplus(self.raw_lead)

    @property
    def velocity(self) -> Tensor | float:
        """The Coulomb width v_c: `coulomb_velocity`, or per DoF (n,) where learned."""
        if self.raw_velocity is None:
            return self.coulomb_velocity
        return self.coulomb_velocity * torch.exp(self.raw_velocity)

    def _coulomb(self) -> Tensor:
        return self.coulomb_scale * F.softplus(self.raw_coulomb)

    def slope(self, qd: Tensor) -> Tensor:
        """dd/dqd at qdd = 0, per DoF (..., n): D + F sech^2(qd / v_c) / v_c, >= 0."""
        slope = self.viscous.expand_as(qd)
        if self.raw_coulomb is not None:
            slope = slope + self._coulomb() * self._sech2(qd) / self.velocity
        return slope

    def lead_inertia(self, qd: Tensor) -> Tensor | None:
        """dd/dqdd at qdd = 0, per DoF (..., n): F l sech^2(qd / v_c) / v_c, >= 0 (what a
        linearly implicit solve adds to M's diagonal); None without a lead."""
        lead = self.lead
        if lead is None:
            return None
        return self._coulomb() * lead * self._sech2(qd) / self.velocity

    def _sech2(self, qd: Tensor) -> Tensor:
        return 1.0 - torch.tanh(qd / self.velocity).square()

    def forward(self, qd: Tensor, qdd: Tensor | None = None) -> Tensor:
        """d at (qd, qdd) (..., n); qdd None: at qdd = 0."""
        force = self.viscous * qd
        if self.raw_coulomb is not None:
            argument = qd if qdd is None or self.raw_lead is None else qd + self.lead * qdd
            force = force + self._coulomb() * torch.tanh(argument / self.velocity)
        return force


class LagrangianDynamics(nn.Module):
    """The DeLaN equations over any mechanics field (network or closed form)."""

    def __init__(
        self,
        field: MechanicsField,
        dissipation: Dissipation | None,
        actuation: Tensor,
        rotational_dofs: Tensor | None = None,
        armature: Tensor | None = None,
    ) -> None:
        """`rotational_dofs` (K, 3): velocity indices of the body-frame angular velocity of
        each ball or free joint (see `rotational_dofs`); they get the Euler-Poincare term.
        `armature` (n,): a known constant inertia per DoF (MuJoCo's ``dof_armature``, the
        rotor inertia of a motor), added to the field's M: M = L L^T + diag(armature)."""
        super().__init__()
        self.field, self.dissipation = field, dissipation
        self.register_buffer("actuation", actuation.clone())  # B, (n, nu)
        self.has_armature = armature is not None
        if armature is not None:  # set by the structure (config), so not in the state dict
            self.register_buffer("armature", armature.clone(), persistent=False)  # (n,)
        rot = torch.zeros(0, 3, dtype=torch.long) if rotational_dofs is None else rotational_dofs
        self.register_buffer("rotational_dofs", rot.long(), persistent=False)

    def _add_euler_poincare(self, force: Tensor, L: Tensor, w: Tensor, qd: Tensor) -> Tensor:
        """force + omega x (M qd)_omega on each ball/free joint's angular DoFs. (..., n)

        With body-frame angular velocities (quasi-velocities) the Euler-Lagrange equations
        gain this term (Euler's omega x I omega for a single body); M qd = L w.
        """
        if not self.rotational_dofs.numel():
            return force
        idx = self.rotational_dofs  # (K, 3)
        momentum = matvec(L, w)
        if self.has_armature:
            momentum = momentum + self.armature * qd
        term = torch.linalg.cross(qd[..., idx], momentum[..., idx], dim=-1)  # (..., K, 3)
        return force.index_add(-1, idx.flatten(), term.flatten(-2))

    @staticmethod
    def _velocity_products(jet: MechanicsJet, qd: Tensor) -> tuple[Tensor, Tensor]:
        """w = L^T qd and Mdot qd = Ldot w + L Ldot^T qd. (..., n) each"""
        w, w_dot = matvec_t(jet.L, qd), matvec_t(jet.L_dot, qd)
        return w, matvec(jet.L_dot, w) + matvec(jet.L, w_dot)

    def _dissipation(
        self, qd: Tensor, frame: Tensor | None = None, qdd: Tensor | None = None
    ) -> Tensor:
        """d(qd, qdd); with a root `frame` R, in the root's frame: S d(S^T qd, S^T qdd)
        (still qd^T d >= 0 at qdd = 0)."""
        if self.dissipation is None:
            return torch.zeros_like(qd)
        if frame is None:
            return self.dissipation(qd, qdd)
        qdd = None if qdd is None else to_root_frame(frame, qdd)
        return from_root_frame(frame, self.dissipation(to_root_frame(frame, qd), qdd))

    def terms(self, q: Tensor, qd: Tensor) -> LagrangianTerms:
        """All terms at (q, qd): (..., nq), (..., n). Two reverse passes (c and g apart)."""
        jet = self.field.jet(q, qd)
        w, m_dot_qd = self._velocity_products(jet, qd)
        zero_v = torch.zeros_like(jet.potential_energy)
        kinetic_cotangent = qd.unsqueeze(-1) * w.unsqueeze(-2)  # qd w^T, (..., n, n)
        half_grad_kinetic = jet.pullback(kinetic_cotangent, zero_v)  # 1/2 d(qd^T M qd)/dq
        gravity = jet.pullback(torch.zeros_like(jet.L), torch.ones_like(zero_v))
        mass_matrix, factor = jet.L @ jet.L.transpose(-1, -2), jet.L
        kinetic = 0.5 * (w * w).sum(-1)
        if self.has_armature:
            mass_matrix = mass_matrix + torch.diag_embed(self.armature.expand_as(qd))
            kinetic = kinetic + 0.5 * (self.armature * qd * qd).sum(-1)
        if self.has_armature or jet.frame is not None:  # L is not M's Cholesky factor
            factor = torch.linalg.cholesky(mass_matrix)
        return LagrangianTerms(
            mass_matrix=mass_matrix,
            cholesky=factor,
            coriolis=self._add_euler_poincare(m_dot_qd - half_grad_kinetic, jet.L, w, qd),
            gravity=gravity,
            dissipation=self._dissipation(qd, jet.frame),
            kinetic_energy=kinetic,
            potential_energy=jet.potential_energy,
        )

    def _bias_and_jet(
        self, q: Tensor, qd: Tensor, qdd: Tensor | None = None
    ) -> tuple[Tensor, MechanicsJet]:
        """c + g + d with one reverse pass (the pullback is linear), and the jet (L); d at
        (qd, qdd), qdd None: at qdd = 0."""
        jet = self.field.jet(q, qd)
        w, m_dot_qd = self._velocity_products(jet, qd)
        minus_kinetic_cotangent = (-qd).unsqueeze(-1) * w.unsqueeze(-2)  # -qd w^T
        coriolis_gravity = m_dot_qd + jet.pullback(
            minus_kinetic_cotangent, torch.ones_like(jet.potential_energy)
        )
        coriolis_gravity = self._add_euler_poincare(coriolis_gravity, jet.L, w, qd)
        return coriolis_gravity + self._dissipation(qd, jet.frame, qdd), jet

    def mass_and_bias(
        self, q: Tensor, qd: Tensor, damping_dt: float = 0.0
    ) -> tuple[Tensor, Tensor]:
        """M (..., n, n) and c + g + d (..., n) at (q, qd), for solves with M changed (an
        implicit contact step adds to it). `damping_dt` > 0: M + damping_dt dd/dqd, the
        friction taken at the end of a step of that length too (linearly implicit; not with
        a free root's frame, whose friction acts in the root's axes). A Coulomb lead adds its
        `Dissipation.lead_inertia` to M's diagonal (`forward_dynamics`)."""
        bias, jet = self._bias_and_jet(q, qd)
        mass = self.with_armature(jet.L @ jet.L.transpose(-1, -2))
        if self.dissipation is not None and jet.frame is None:
            diagonal = self.dissipation.lead_inertia(qd)
            if damping_dt > 0:
                slope = damping_dt * self.dissipation.slope(qd)
                diagonal = slope if diagonal is None else diagonal + slope
            if diagonal is not None:
                mass = mass + torch.diag_embed(diagonal)
        return mass, bias

    def with_armature(self, inner: Tensor) -> Tensor:
        """M from the field's part L L^T (..., n, n): plus diag(armature) where there is one."""
        if not self.has_armature:
            return inner
        return inner + torch.diag(self.armature.to(inner.dtype))

    def inverse_dynamics(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        """Generalized force tau = M qdd + c + g + d(qd, qdd). (..., n)"""
        bias, jet = self._bias_and_jet(q, qd, qdd)
        L = jet.L
        m_qdd = matvec(L, matvec_t(L, qdd))
        if self.has_armature:
            m_qdd = m_qdd + self.armature * qdd
        return m_qdd + bias

    def forward_dynamics(self, q: Tensor, qd: Tensor, tau: Tensor) -> Tensor:
        """qdd = M^-1 (tau - c - g - d) by two triangular solves with L. (..., n)

        With a Coulomb lead l, d is taken linearly implicit in qdd: (M + diag(F l sech^2 /
        v_c)) qdd = tau - c - g - d(qd, 0) (`Dissipation.lead_inertia`)."""
        if self.dissipation is not None and self.dissipation.lead is not None:
            mass, bias = self.mass_and_bias(q, qd)
            return cholesky_solve(torch.linalg.cholesky_ex(mass).L, tau - bias)
        bias, jet = self._bias_and_jet(q, qd)
        if self.has_armature:  # M = L L^T + diag(armature): factor it whole
            L = jet.L
            mass_matrix = L @ L.transpose(-1, -2) + torch.diag_embed(self.armature.expand_as(tau))
            factor = torch.linalg.cholesky_ex(mass_matrix).L  # PD by construction: no check
            return cholesky_solve(factor, tau - bias)
        if jet.frame is None or jet.factor is None:
            return self._solve(jet.L, tau - bias)
        # M = S M_b S^T with S orthogonal: M^-1 b = S M_b^-1 S^T b
        solved = self._solve(jet.factor, to_root_frame(jet.frame, tau - bias))
        return from_root_frame(jet.frame, solved)

    def _solve(self, L: Tensor, b: Tensor) -> Tensor:
        """x with L L^T x = b, L the field's triangular factor. (..., n, n), (..., n) -> (..., n)"""
        rhs = b.unsqueeze(-1)  # (..., n, 1)
        if self.field.upper:  # M = U U^T: U y = rhs, then U^T x = y
            y = torch.linalg.solve_triangular(L, rhs, upper=True)
            return torch.linalg.solve_triangular(L.transpose(-1, -2), y, upper=False).squeeze(-1)
        return cholesky_solve(L, b)

    def generalized_force(self, action: Tensor) -> Tensor:
        """tau = B a: (..., nu) -> (..., n). Compiled with few actuators: broadcast products
        (`linear`), which fuse into the next kernel."""
        return linear(action, self.actuation)
