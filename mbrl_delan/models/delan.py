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

L and V come from a swappable `MechanicsField`: a network with one trunk and two heads, or,
in tests, closed-form models of known systems, so the same equations serve both.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn
from torch.nn import functional as F

from mbrl_delan import keys
from mbrl_delan.accelerate.compile import FitGraph
from mbrl_delan.models.base import LossOutput, WorldModel
from mbrl_delan.models.features import QFeatures, rotation_matrix, skew, unskew_of_rt
from mbrl_delan.models.integrators import INTEGRATORS, integrate
from mbrl_delan.models.kernels import cholesky_solve, linear
from mbrl_delan.models.tangent_mlp import TangentMLP
from mbrl_delan.systems.posarith import differentiate_pos
from mbrl_delan.systems.system import BALL, FREE, JointLayout, State

LOSSES = ("forward", "inverse", "both")
# the batch entries a per-transition loss reads (`DeLaN._transition_losses`; absent: None)
LOSS_INPUTS = {
    "q": keys.Q,
    "qd": keys.QD,
    "action": keys.ACTION,
    "qdd": keys.QDD,
    "next_q": keys.NEXT_Q,
    "next_qd": keys.NEXT_QD,
}


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


class LagrangianNetwork(MechanicsField):
    """One MLP trunk on features of q with two linear heads.

    The L head gives n diagonal entries (softplus + shift, so diag(L) > 0) and n(n-1)/2
    entries below the diagonal; the V head gives the potential energy.

    `heights`: (q index, v index) of coordinates that enter V only through a learned linear
    term, V = V_net(phi(q)) + sum_k w_k q_k: the height of a free root, whose features then
    leave it out (uniform gravity on the whole body's mass is m g z, and nothing else in M or
    V depends on where the body is). Its v index must be the world-frame z velocity.

    `still_potential` (with features built with ``freeze_still``): coordinates held still in
    the data (their features frozen: M and V_net do not depend on them) enter V to first
    order about their held value, V += sum_p (q_p - q_p0) s_p G_p(phi(q)), G a third head
    and s_p a force unit (``still_scale``). The generalized force on such a coordinate is
    then s_p G_p: what holding it against gravity takes, as a function of the moving ones;
    no kinetic term depends on it (its Coriolis force is not identifiable from data in which
    it never moves, and a free network makes up large ones on new motions).

    `dof_parents`: each DoF's parent DoF in the kinematic tree (-1 at the root; MuJoCo's
    ``dof_parentid``, parents before children). L is then upper-triangular with entries
    only at (i, j) where DoF i is an ancestor of j: the factor of a tree's mass matrix
    without fill-in (M = U U^T with U = L^T D^1/2 of MuJoCo's M = L^T D L), so M_ij = 0
    exactly between DoFs on different branches (a hand and a foot), as in the true M.
    """

    def __init__(
        self,
        features: QFeatures,
        n: int,
        hidden: int,
        layers: int,
        activation: str,
        diag_shift: float,
        heights: Sequence[tuple[int, int]] = (),
        still_potential: bool = False,
        dof_parents: Sequence[int] | None = None,
        root_frame: bool = False,
    ) -> None:
        super().__init__()
        self.root_frame = root_frame
        if diag_shift <= 0:
            raise ValueError(
                f"diag_shift must be > 0 so M stays positive definite, got {diag_shift}"
            )
        if still_potential and not features.freeze_still:
            raise ValueError("still_potential needs features built with freeze_still=True")
        self.features, self.n, self.diag_shift = features, n, diag_shift
        self.upper = dof_parents is not None
        if dof_parents is None:
            rows, cols = torch.tril_indices(n, n, -1)
        else:
            rows, cols = tree_entries(dof_parents)
        n_off = int(rows.numel())
        self.still_potential = still_potential
        n_still = features.n_plain if still_potential else 0
        self.v_row = n + n_off  # head rows: [diag L (n); lower L (n_off); V (1); G (n_still)]
        self.trunk = TangentMLP(
            features.n_features, n + n_off + 1 + n_still, hidden, layers, activation
        )
        if still_potential:
            self.register_buffer("still_scale", torch.ones(n_still))
        # row of [diag head rows; off-diagonal head rows; a zero row] for each entry of L
        layout = torch.full((n * n,), n + n_off, dtype=torch.long)
        layout[torch.arange(n) * (n + 1)] = torch.arange(n)
        layout[rows * n + cols] = n + torch.arange(n_off)
        self.register_buffer("layout", layout, persistent=False)
        self.register_buffer("rows", rows, persistent=False)
        self.register_buffer("cols", cols, persistent=False)
        # per-row scale of L (M = D L~ L~^T D, D = diag(row_scale)) and scale of V: constant
        # changes of units, set from data (`DeLaN.fit_normalization`), 1 by default
        self.register_buffer("row_scale", torch.ones(n))
        self.register_buffer("energy_scale", torch.ones(()))
        row_of_entry = torch.arange(n).repeat_interleave(n)
        row_of_entry[torch.arange(n) * (n + 1)] = n  # diagonal entries: unscaled (slot n)
        self.register_buffer("row_of_entry", row_of_entry, persistent=False)
        height_q, height_v = [h[0] for h in heights], [h[1] for h in heights]
        self.register_buffer("height_q", torch.tensor(height_q, dtype=torch.long), persistent=False)
        self.register_buffer("height_v", torch.tensor(height_v, dtype=torch.long), persistent=False)
        self.height_weight: nn.Parameter | None = None
        if heights:  # w_k in units of energy_scale per metre (m g for a free root's height)
            self.height_weight = nn.Parameter(torch.zeros(len(heights)))
            self.register_buffer("height_started", torch.zeros((), dtype=torch.bool))

    @torch.no_grad()
    def start_height_weight(self, force: Tensor) -> None:
        """Start w at the mean generalized force (N, n) along each height: the body's weight
        m g when the data's mean vertical acceleration is zero. Once: later calls (refits on
        more data) keep the learned w."""
        if self.height_weight is not None and not bool(self.height_started):
            mean = force.index_select(-1, self.height_v).mean(dim=0)
            self.height_weight.copy_(mean.to(self.height_weight) / self.energy_scale)
            self.height_started.fill_(True)

    def _still_terms(self, q: Tensor, hidden: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """For the plain coordinates: the force s G (0 where not held still) (..., m), the
        offset q_p - q_p0 (..., m) and the G head's weight in force units (m, hidden)."""
        features, head = self.features, self.trunk.head
        rows = slice(self.v_row + 1, None)
        unit = (self.still_scale * features.plain_still).unsqueeze(-1)  # (m, 1)
        weight, bias = head.weight[rows] * unit, head.bias[rows] * unit.squeeze(-1)
        offset = q.index_select(-1, features.plain_q) - features.plain_mean
        return linear(hidden, weight, bias), offset, weight

    def _height_potential(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """sum_k w_k q_k (...) and w in SI units (K,)."""
        assert self.height_weight is not None
        weight = self.height_weight * self.energy_scale
        return q.index_select(-1, self.height_q) @ weight, weight

    @torch.no_grad()
    def start_diagonal(self) -> None:
        """Zero the heads of L's off-diagonal entries and of V: M starts diagonal, g at 0."""
        head = self.trunk.head
        head.weight[self.n :].zero_()
        head.bias[self.n :].zero_()

    def _matrix_head(self) -> tuple[Tensor, Tensor]:
        """The L head laid out as the matrix L, row-major: weight (n*n, hidden), bias (n*n,).

        Entries above the diagonal get zero rows, so `linear(h, W, b)` gives the raw L
        directly (no per-sample gather), and a cotangent on all of L maps back with one
        matmul (the entries above the diagonal meet zero rows). Costs one gather of the
        weights per call, independent of the batch.
        """
        head, rows = self.trunk.head, self.v_row
        weight = torch.cat([head.weight[:rows], head.weight.new_zeros(1, head.in_features)])
        bias = torch.cat([head.bias[:rows], head.bias.new_zeros(1)])
        scale = torch.cat([self.row_scale, self.row_scale.new_ones(1)])[self.row_of_entry]
        weight = weight.index_select(0, self.layout) * scale.unsqueeze(-1)
        return weight, bias.index_select(0, self.layout) * scale

    def jet(self, q: Tensor, qd: Tensor) -> MechanicsJet:
        """L, V and their derivatives; with ``root_frame``, L = S L_b (`root_frame_jet`)."""
        jet = self._network_jet(q, qd)
        return root_frame_jet(jet, q, qd) if self.root_frame else jet

    def _network_jet(self, q: Tensor, qd: Tensor) -> MechanicsJet:
        """The jet through the trunk: a tangent along qd forward, one reverse pass back."""
        if self.n == 1 and not self.still_potential and not self.height_q.numel():
            return self._scalar_jet(q, qd)
        n, head = self.n, self.trunk.head
        body = self.trunk.body(self.features(q), self.features.jvp(q, qd))
        weight, bias = self._matrix_head()
        raw = linear(body.out, weight, bias).unflatten(-1, (n, n))  # (..., n, n), 0 above
        d_raw = linear(body.d_out, weight).unflatten(-1, (n, n))
        raw_diag = torch.diagonal(raw, dim1=-2, dim2=-1).clone()  # (..., n), unscaled
        diag_slope = self.row_scale * torch.sigmoid(raw_diag)  # d L_ii / d raw_ii
        L = raw  # fresh output of `linear`: its diagonal is replaced in place
        diag = self.row_scale * (F.softplus(raw_diag) + self.diag_shift)
        torch.diagonal(L, dim1=-2, dim2=-1).copy_(diag)
        L_dot = d_raw
        torch.diagonal(L_dot, dim1=-2, dim2=-1).mul_(diag_slope)
        v_weight, v_bias = self._potential_head()
        potential = linear(body.out, v_weight.unsqueeze(0), v_bias).squeeze(-1)
        if self.height_q.numel():
            height_potential, height_weight = self._height_potential(q)
            potential = potential + height_potential
        if self.still_potential:
            still_force, still_offset, still_weight = self._still_terms(q, body.out)
            potential = potential + (still_offset * still_force).sum(-1)

        def pullback(d_L: Tensor, d_V: Tensor) -> Tensor:
            d_diag = torch.diagonal(d_L, dim1=-2, dim2=-1)  # (..., n)
            d_hidden = (
                linear(d_L.flatten(-2), weight.T)  # every entry as if raw; diagonal fixed below
                + linear((diag_slope - 1.0) * d_diag, head.weight[:n].T)
                + d_V.unsqueeze(-1) * v_weight
            )
            if self.still_potential:
                d_hidden = d_hidden + linear(d_V.unsqueeze(-1) * still_offset, still_weight.T)
            grad = self.features.vjp(q, self.trunk.body_vjp(body, d_hidden))
            if self.still_potential:
                still_grad = d_V.unsqueeze(-1) * still_force
                grad = grad.index_add(-1, self.features.plain_v, still_grad)
            if self.height_q.numel():
                grad = grad.index_add(-1, self.height_v, d_V.unsqueeze(-1) * height_weight)
            return grad

        return MechanicsJet(L=L, L_dot=L_dot, potential_energy=potential, pullback=pullback)

    def _potential_head(self) -> tuple[Tensor, Tensor]:
        """The V head in energy units: weight (hidden,), bias (1,)."""
        head, v = self.trunk.head, self.v_row
        return head.weight[v] * self.energy_scale, head.bias[v : v + 1] * self.energy_scale

    def _scalar_jet(self, q: Tensor, qd: Tensor) -> MechanicsJet:
        """One DoF: the tangent along a unit velocity is the trunk's whole Jacobian J = dh/dq
        (..., hidden). The two heads (raw L, V) map h and J once each, (..., hidden) x
        (hidden, 2); L_dot and the pullback are then products of (...)-sized values (no
        reverse pass through the trunk, no reduction over the hidden units per cotangent)."""
        body = self.trunk.body(self.features(q), self.features.jvp(q, torch.ones_like(qd)))
        weight, bias = self._matrix_head()  # (1, hidden), (1,)
        v_weight, v_bias = self._potential_head()
        heads = torch.cat([weight, v_weight.unsqueeze(0)])  # (2, hidden)
        values = linear(body.out, heads, torch.cat([bias, v_bias]))  # raw L, V (..., 2)
        slopes = linear(body.d_out, heads)  # d raw/dq, dV/dq (..., 2)
        raw, potential = values[..., :1], values[..., 1]  # (..., 1), (...)
        raw_q, potential_q = slopes[..., :1], slopes[..., 1:]  # (..., 1) each
        L_q = self.row_scale * torch.sigmoid(raw) * raw_q  # dL/dq (..., 1)
        L = (self.row_scale * (F.softplus(raw) + self.diag_shift)).unsqueeze(-1)  # (..., 1, 1)

        def pullback(d_L: Tensor, d_V: Tensor) -> Tensor:
            return d_L.flatten(-2) * L_q + d_V.unsqueeze(-1) * potential_q  # (..., 1)

        return MechanicsJet(
            L=L, L_dot=(L_q * qd).unsqueeze(-1), potential_energy=potential, pullback=pullback
        )


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
    """d(q, qd) = D qd + F tanh(qd / v_c), D = a softplus(.), F = b softplus(.) per DoF.

    a and b (`viscous_scale`, `coulomb_scale`, buffers, 1 by default) are positive units set
    from data (`DeLaN.fit_normalization` with `inertia_scaling`): d stays dissipative.
    """

    def __init__(
        self, n: int, coulomb: bool = True, coulomb_velocity: float = 0.01, raw_init: float = -4.0
    ) -> None:
        super().__init__()
        self.raw_viscous = nn.Parameter(torch.full((n,), raw_init))
        self.raw_coulomb = nn.Parameter(torch.full((n,), raw_init - 2.0)) if coulomb else None
        self.coulomb_velocity = coulomb_velocity
        self.register_buffer("viscous_scale", torch.ones(n))
        self.register_buffer("coulomb_scale", torch.ones(n))

    @property
    def viscous(self) -> Tensor:
        """Learned viscous damping per DoF, (n,)."""
        return self.viscous_scale * F.softplus(self.raw_viscous)

    def forward(self, qd: Tensor) -> Tensor:
        force = self.viscous * qd
        if self.raw_coulomb is not None:
            coulomb = self.coulomb_scale * F.softplus(self.raw_coulomb)
            force = force + coulomb * torch.tanh(qd / self.coulomb_velocity)
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
        momentum = (L @ w.unsqueeze(-1)).squeeze(-1)
        if self.has_armature:
            momentum = momentum + self.armature * qd
        term = torch.linalg.cross(qd[..., idx], momentum[..., idx], dim=-1)  # (..., K, 3)
        return force.index_add(-1, idx.flatten(), term.flatten(-2))

    @staticmethod
    def _velocity_products(jet: MechanicsJet, qd: Tensor) -> tuple[Tensor, Tensor]:
        """w = L^T qd and Mdot qd = Ldot w + L Ldot^T qd. (..., n) each"""
        w = (jet.L.transpose(-1, -2) @ qd.unsqueeze(-1)).squeeze(-1)
        w_dot = (jet.L_dot.transpose(-1, -2) @ qd.unsqueeze(-1)).squeeze(-1)
        m_dot_qd = (jet.L_dot @ w.unsqueeze(-1) + jet.L @ w_dot.unsqueeze(-1)).squeeze(-1)
        return w, m_dot_qd

    def _dissipation(self, qd: Tensor, frame: Tensor | None = None) -> Tensor:
        """d(qd); with a root `frame` R, in the root's frame: S d(S^T qd) (still qd^T d >= 0)."""
        if self.dissipation is None:
            return torch.zeros_like(qd)
        if frame is None:
            return self.dissipation(qd)
        return from_root_frame(frame, self.dissipation(to_root_frame(frame, qd)))

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

    def _bias_and_jet(self, q: Tensor, qd: Tensor) -> tuple[Tensor, MechanicsJet]:
        """c + g + d with one reverse pass (the pullback is linear), and the jet (L)."""
        jet = self.field.jet(q, qd)
        w, m_dot_qd = self._velocity_products(jet, qd)
        minus_kinetic_cotangent = (-qd).unsqueeze(-1) * w.unsqueeze(-2)  # -qd w^T
        coriolis_gravity = m_dot_qd + jet.pullback(
            minus_kinetic_cotangent, torch.ones_like(jet.potential_energy)
        )
        coriolis_gravity = self._add_euler_poincare(coriolis_gravity, jet.L, w, qd)
        return coriolis_gravity + self._dissipation(qd, jet.frame), jet

    def inverse_dynamics(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        """Generalized force tau = M qdd + c + g + d. (..., n)"""
        bias, jet = self._bias_and_jet(q, qd)
        L = jet.L
        m_qdd = (L @ (L.transpose(-1, -2) @ qdd.unsqueeze(-1))).squeeze(-1)
        if self.has_armature:
            m_qdd = m_qdd + self.armature * qdd
        return m_qdd + bias

    def forward_dynamics(self, q: Tensor, qd: Tensor, tau: Tensor) -> Tensor:
        """qdd = M^-1 (tau - c - g - d) by two triangular solves with L. (..., n)"""
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


class ResidualForce(nn.Module):
    """r(q, qd, a): a generalized force the Lagrangian terms leave out (contacts, joint limits).

    A plain MLP (SiLU) on [phi(q), qd / qd_unit, a] whose output is in units of `tau_unit`;
    its last layer starts at zero, so a fresh model is the Lagrangian one. It adds to B a in
    the forward and inverse dynamics and has no structure: what it learns is not energy
    conserving, which is why it is kept apart from M, c, g and d.
    """

    def __init__(self, features: QFeatures, n: int, nu: int, hidden: int, layers: int) -> None:
        super().__init__()
        sizes = [features.n_features + n + nu] + [hidden] * layers
        blocks: list[nn.Module] = []
        for a, b in zip(sizes[:-1], sizes[1:], strict=True):
            blocks += [nn.Linear(a, b), nn.SiLU()]
        out = nn.Linear(hidden, n)
        nn.init.zeros_(out.weight)
        nn.init.zeros_(out.bias)
        self.features = features
        self.net = nn.Sequential(*blocks, out)

    def forward(self, q: Tensor, qd: Tensor, action: Tensor, qd_unit: Tensor) -> Tensor:
        """(..., nq), (..., nv), (..., nu), (nv,) -> (..., nv), unitless."""
        return self.net(torch.cat([self.features(q), qd / qd_unit, action], dim=-1))


def tree_entries(dof_parents: Sequence[int]) -> tuple[Tensor, Tensor]:
    """(rows, cols) of the entries (i, j), i < j, where DoF i is an ancestor of DoF j."""
    rows: list[int] = []
    cols: list[int] = []
    for j, parent in enumerate(dof_parents):
        ancestors = []
        while parent >= 0:
            if parent >= j:
                raise ValueError(f"dof_parents must list parents first: DoF {j} has {parent}")
            ancestors.append(parent)
            parent = dof_parents[parent]
        rows += sorted(ancestors)
        cols += [j] * len(ancestors)
    return torch.tensor(rows, dtype=torch.long), torch.tensor(cols, dtype=torch.long)


def free_root_heights(layout: JointLayout) -> list[tuple[int, int]]:
    """(q index, v index) of each free joint's height z (its world-frame z velocity)."""
    return [
        (qa + 2, va + 2)
        for jtype, qa, va in zip(layout.types, layout.qpos_adr, layout.dof_adr, strict=True)
        if jtype == FREE
    ]


def rotational_dofs(layout: JointLayout) -> Tensor:
    """(K, 3) velocity indices of the angular velocity of each ball and free joint."""
    rows = [
        [adr + (3 if jtype == FREE else 0) + k for k in range(3)]
        for jtype, adr in zip(layout.types, layout.dof_adr, strict=True)
        if jtype in (BALL, FREE)
    ]
    return torch.tensor(rows, dtype=torch.long) if rows else torch.zeros(0, 3, dtype=torch.long)


CONSTANT_RATIO = 1e-6  # a per-DoF spread below this fraction of the largest: not varying


def _armature(armature: Sequence[float] | Tensor | None, n: int) -> Tensor | None:
    """A known inertia per DoF as a tensor (n,), >= 0; None stays None."""
    if armature is None:
        return None
    value = torch.as_tensor(armature, dtype=torch.get_default_dtype()).reshape(-1)
    if value.shape != (n,) or not bool(torch.isfinite(value).all()) or bool((value < 0).any()):
        raise ValueError(f"armature must be {n} finite values >= 0, got {armature!r}")
    return value


def _is_mechanics(key: str) -> bool:
    """A state-dict entry of the Lagrangian part (M, V, friction), not the actuation B."""
    return key.startswith("dynamics.") and key != "dynamics.actuation"


def _varies(spread: Tensor) -> Tensor:
    """(n,) bool: spread_i >= CONSTANT_RATIO * max(spread) and > 0."""
    return (spread > 0) & (spread >= CONSTANT_RATIO * spread.max())


def _fill_geometric(units: Tensor, known: Tensor) -> Tensor:
    """units where known, the geometric mean of the known ones elsewhere. (n,)"""
    fill = units[known].log().mean().exp()
    return torch.where(known, units, fill)


def _scale(x: Tensor, floor_ratio: float = 1e-2) -> Tensor:
    """Per-column std with a floor relative to the largest (unactuated DoFs have std 0)."""
    std = x.std(dim=0) if x.shape[0] > 1 else x.abs().mean(dim=0)
    return std.clamp_min(floor_ratio * float(std.max().clamp_min(1e-8)))


def _needed(value: Tensor | None, key: str | tuple[str, ...]) -> Tensor:
    """A loss input the batch must hold."""
    if value is None:
        raise KeyError(f"the loss needs {key!r} in the batch")
    return value


class DeLaN(WorldModel):
    """DeLaN world model: the Lagrangian equations over networks, stepped by an integrator.

    Losses (`loss=`): 'forward' compares the integrated next state with the data, per DoF
    normalised by the std of the one-step change; 'inverse' compares the predicted torque
    B a with DeLaN's inverse dynamics at the finite-difference acceleration (or the batch's
    `qdd` when present), normalised by the per-DoF torque std; 'both' adds them.

    A DoF without actuator has tau = 0 in every sample; its torque error is normalised by
    `unactuated_torque_scale` times the largest actuated std (a std floor would give it 10^4
    times the weight and pull M towards 0, see docs/benchmarks.md, suite identify).

    Safety at extreme inputs: `fit_normalization` also standardises the plain position
    features (bounded at +-5 std, see `QFeatures`) and sets `velocity_limit` to
    `velocity_margin` times the largest |qd| in the data per DoF; `step` evaluates the
    dynamics at velocities clamped to it and clamps the velocity it returns, so any finite
    state and action give a finite next state.

    `inertia_scaling`: `fit_normalization` also sets units for M, V and the friction from
    the data (see `_fit_inertia_scale`); for systems whose inertias span decades
    (humanoids). `diagonal_init`: L's off-diagonal and V heads start at zero (M diagonal,
    g = 0) and the viscous friction at softplus(0) = 0.69 of its unit, not near 0.

    `residual`: add a learned generalized force r(q, qd, a) (`ResidualForce`, in units of
    `tau_scale`, zero at initialisation) to B a, for what the Lagrangian terms cannot hold:
    contacts and joint limits.

    `translation_invariant`: M and the network part of V do not see a free root's height
    (its x/y never enter), and V gains an exact gravity term w z in that height, w learned
    and started at the data's mean vertical force (`LagrangianNetwork`, ``heights``). For a
    free-floating body under uniform gravity this is the whole dependence of M and V on the
    root's position. The residual force still sees the height (contacts depend on it).

    `yaw_invariant` (a free root first): nothing depends on the root's heading or
    horizontal position. The networks see its tilt (e_z^T R), height and the joints, and
    M = S M_b S^T turns the world-frame linear velocity into the root's frame
    (`root_frame_jet`); the residual force sees body-frame velocities and acts in that frame.
    Turning a state about the vertical turns the predicted accelerations with it, exactly.

    `still_first_order`: coordinates that do not move in the data given to
    `fit_normalization` (motion capture's uncaptured fingers and fixed clavicles) are taken to
    first order about their held value: M does not depend on them and V is linear in them
    (`LagrangianNetwork`, ``still_potential``), with force units from the data's torques.

    `dof_parents` (MuJoCo's ``dof_parentid``): M's factor gets the kinematic tree's
    sparsity (`LagrangianNetwork`), so M couples only DoFs on one branch.

    `armature` (n,), in SI units: a known constant inertia per DoF, MuJoCo's
    ``dof_armature`` (the motors' rotor inertia), added to the learned part:
    M = L L^T + diag(armature). It bounds M's eigenvalues from below where the data do not
    (joints motion capture holds still); forward dynamics then factors M whole.

    `compile_fit`: training losses and their backward pass run through `torch.compile`
    (`_losses_for`). Planning compiles at the call site (`mbrl_delan.accelerate`): `step` is
    the plain maths.
    """

    deterministic = True

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
        unactuated_torque_scale: float = 1.0,
        velocity_margin: float = 3.0,
        max_velocity: float = 100.0,
        compile_fit: bool = False,
        inertia_scaling: bool = False,
        diagonal_init: bool = False,
        residual: bool = False,
        translation_invariant: bool = False,
        still_first_order: bool = False,
        dof_parents: Sequence[int] | None = None,
        armature: Sequence[float] | Tensor | None = None,
        yaw_invariant: bool = False,
    ) -> None:
        super().__init__()
        if yaw_invariant and not (layout.types and layout.types[0] == FREE):
            raise ValueError("yaw_invariant needs a model whose first joint is a free root")
        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
        if loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
        if control_dt <= 0 or substeps < 1:
            raise ValueError(f"need control_dt > 0 and substeps >= 1, got {control_dt}, {substeps}")
        if min(unactuated_torque_scale, velocity_margin, max_velocity) <= 0:
            raise ValueError(
                "need unactuated_torque_scale, velocity_margin, max_velocity > 0, got "
                f"{unactuated_torque_scale}, {velocity_margin}, {max_velocity}"
            )
        self.unactuated_torque_scale = unactuated_torque_scale
        self.velocity_margin = velocity_margin
        self.inertia_scaling = inertia_scaling
        self.compile_fit = compile_fit
        self._fit_graph = FitGraph()  # `_losses_for`
        n = layout.nv
        self.yaw_invariant = yaw_invariant
        features = QFeatures(layout, yaw_invariant=yaw_invariant)
        self.layout, self.control_dt = layout, control_dt
        self.integrator, self.substeps, self.loss_kind = integrator, substeps, loss
        heights = free_root_heights(layout) if translation_invariant else []
        own_features = bool(heights) or still_first_order
        network = LagrangianNetwork(
            QFeatures(
                layout,
                root_height=not heights,
                freeze_still=still_first_order,
                yaw_invariant=yaw_invariant,
            )
            if own_features
            else features,
            n,
            hidden,
            layers,
            activation,
            diag_shift,
            heights=heights,
            still_potential=still_first_order,
            dof_parents=dof_parents,
            root_frame=yaw_invariant,
        )
        raw_init = 0.0 if diagonal_init else -4.0
        self.dynamics = LagrangianDynamics(
            field=network,
            dissipation=Dissipation(n, coulomb=coulomb, raw_init=raw_init) if dissipation else None,
            actuation=actuation.to(torch.get_default_dtype()),
            rotational_dofs=rotational_dofs(layout),
            armature=_armature(armature, n),
        )
        if diagonal_init:
            network.start_diagonal()
        nu = actuation.shape[-1]
        self.residual = ResidualForce(features, n, nu, hidden, layers) if residual else None
        for name in ("q_scale", "qd_scale", "tau_scale"):
            self.register_buffer(name, torch.ones(n))
        self.register_buffer("velocity_limit", torch.full((n,), float(max_velocity)))
        # true once `load_mechanics` gave M, V and the friction (with their units and feature
        # statistics): `fit_normalization` then leaves them as they are
        self.register_buffer("mechanics_loaded", torch.zeros((), dtype=torch.bool))

    def _apply(self, fn: Callable[..., Any], recurse: bool = True) -> DeLaN:
        self._fit_graph.reset()  # a compiled loss is specific to a device and dtype
        return super()._apply(fn, recurse)

    def terms(self, q: Tensor, qd: Tensor) -> LagrangianTerms:
        return self.dynamics.terms(q, qd)

    def acceleration(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """Forward dynamics under controls: (..., nq), (..., nv), (..., nu) -> (..., nv)."""
        return self.dynamics.forward_dynamics(q, qd, self.applied_force(q, qd, action))

    def applied_force(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """B a, plus the residual force when the model has one. (..., nv)"""
        return self._with_residual(self.dynamics.generalized_force(action), q, qd, action)

    def _with_residual(self, tau: Tensor, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """tau + r(q, qd, a) in torque units; tau itself without a residual. (..., nv)"""
        if self.residual is None:
            return tau
        qd_unit = self.velocity_limit / self.velocity_margin  # the largest |qd| in the data
        if not self.yaw_invariant:
            return tau + self.tau_scale * self.residual(q, qd, action, qd_unit)
        R = rotation_matrix(q[..., 3:7])  # in the root's frame, turned back to the world's
        force = self.tau_scale * self.residual(q, to_root_frame(R, qd), action, qd_unit)
        return tau + from_root_frame(R, force)

    def step(
        self, q: Tensor, qd: Tensor, action: Tensor, generator: torch.Generator | None = None
    ) -> State:
        """One control step: (..., nq), (..., nv), (..., nu) -> State((..., nq), (..., nv))."""
        tau = self.dynamics.generalized_force(action)  # B a: once per step, not per stage

        def accel(q_: Tensor, qd_: Tensor) -> Tensor:
            qd_ = self._clamp_velocity(q_, qd_)
            force = self._with_residual(tau, q_, qd_, action)
            return self.dynamics.forward_dynamics(q_, qd_, force)

        nxt = integrate(self.layout, accel, q, qd, self.control_dt, self.integrator, self.substeps)
        return State(q=nxt.q, qd=self._clamp_velocity(nxt.q, nxt.qd))

    def _clamp_velocity(self, q: Tensor, qd: Tensor) -> Tensor:
        """qd within +-`velocity_limit` per DoF; with `yaw_invariant` the root's linear
        velocity is clamped in its own frame, so the clamp turns with the body too."""
        limit = self.velocity_limit
        if not self.yaw_invariant:
            return torch.clamp(qd, -limit, limit)
        R = rotation_matrix(q[..., 3:7])
        return from_root_frame(R, torch.clamp(to_root_frame(R, qd), -limit, limit))

    @torch.no_grad()
    def fit_normalization(self, data: TensorDictBase) -> None:
        """Loss scales, feature statistics and the velocity limit from training data.

        Inverse-dynamics data without ("next", ...) states set everything but the
        next-state scales (used by the forward loss only)."""
        q, qd = data[keys.Q], data[keys.QD]
        tau = self.dynamics.generalized_force(data[keys.ACTION].to(self.q_scale.dtype))
        self.tau_scale.copy_(self._torque_scale(tau))
        if keys.NEXT_Q in data.keys(include_nested=True):
            q_next, qd_next = data[keys.NEXT_Q], data[keys.NEXT_QD]
            self.q_scale.copy_(_scale(differentiate_pos(self.layout, q, q_next, 1.0)))
            self.qd_scale.copy_(_scale(qd_next - qd))
            q, qd = torch.cat([q, q_next]), torch.cat([qd, qd_next])
        if not bool(self.mechanics_loaded):
            self._fit_mechanics_units(data, q, tau)
        if self.residual is not None:
            self.residual.features.standardize(q)
        speed = qd.abs().amax(dim=0).clamp_min(1e-3)
        self.velocity_limit.copy_(self.velocity_margin * speed)

    def _fit_mechanics_units(self, data: TensorDictBase, q: Tensor, tau: Tensor) -> None:
        """The Lagrangian part's units and feature statistics from the data (q: every state)."""
        if self.inertia_scaling:
            self._fit_inertia_scale(data, tau)
        field = self.dynamics.field
        field.features.standardize(q)
        if isinstance(field, LagrangianNetwork):
            field.start_height_weight(tau)

    @torch.no_grad()
    def load_mechanics(self, state: Mapping[str, Tensor]) -> None:
        """Take M, V and the friction from another DeLaN of the same structure and system.

        `state`: that DeLaN's `state_dict()` (for example the mechanics of an inverse-dynamics
        fit on motion capture, `models.inverse.DeLaNInverse.delan`). Its ``dynamics.*``
        entries are copied: the networks of M and V, their units and feature statistics, the
        friction. The actuation B stays this model's (the other may map a different action,
        such as every generalized force); the residual force and the loss scales stay too.
        Afterwards `fit_normalization` keeps the mechanics' units and statistics, so
        refitting starts from the loaded M(q), V(q). A missing entry or one of another shape
        (another width, depth, system or structure option) raises ValueError naming it.
        """
        own = {k: v for k, v in self.state_dict().items() if _is_mechanics(k)}
        missing = sorted(k for k in own if k not in state)
        wrong = sorted(
            f"{k} {tuple(state[k].shape)} (this model: {tuple(own[k].shape)})"
            for k in own
            if k in state and state[k].shape != own[k].shape
        )
        extra = sorted(k for k in state if _is_mechanics(k) and k not in own)
        if missing or wrong or extra:
            raise ValueError(
                "the given mechanics do not fit this DeLaN: "
                + "; ".join(
                    f"{label}: {', '.join(keys_)}"
                    for label, keys_ in (
                        ("missing", missing),
                        ("other shape", wrong),
                        ("not in this model", extra),
                    )
                    if keys_
                )
            )
        for k, v in own.items():
            v.copy_(state[k].to(v))
        self.mechanics_loaded.fill_(True)

    def _fit_inertia_scale(self, data: TensorDictBase, tau: Tensor) -> None:
        """Units from the data, all positive constants (the structure is kept):

        - M = D L~ L~^T D with D_i^2 = std(tau_i) / std(qdd_i), an inertia per DoF (qdd from
          the data's `qdd`, else finite differences);
        - V in units of the largest torque std;
        - viscous friction in std(tau_i) / rms(qd_i), Coulomb friction in std(tau_i).

        A DoF whose qdd or qd does not vary (spread below `CONSTANT_RATIO` of the largest)
        but whose torque does is held still against gravity and its neighbours' motion (the
        mocap's clavicles, fingers, thumbs): its inertia unit is std(tau_i) over the moving
        DoFs' geometric-mean qdd std (the fingers: ~0.003, not the body's ~0.6). A DoF whose
        torque does not vary either (unactuated) gets the geometric mean of the others' units,
        as do its friction units. Starts M near the data's inertia scale, which matters when
        it spans decades (a humanoid: 40 kg root, 0.02 kg m^2 wrists).
        """
        qdd = data.get(keys.QDD, None)
        if qdd is None:
            qdd = (data[keys.NEXT_QD] - data[keys.QD]) / self.control_dt
        qd = data[keys.QD].to(tau.dtype)
        tau_std, qdd_std = tau.std(dim=0), qdd.to(tau.dtype).std(dim=0)
        qd_rms = qd.pow(2).mean(dim=0).sqrt()
        known = _varies(tau_std) & _varies(qdd_std) & _varies(qd.std(dim=0))
        if not known.any():
            return
        field = self.dynamics.field
        inertia = _fill_geometric(tau_std / qdd_std, known)
        held = _varies(tau_std) & ~known  # torque without motion
        typical_qdd = qdd_std[known].log().mean().exp()
        inertia = torch.where(held, tau_std / typical_qdd, inertia)
        field.row_scale.copy_(inertia.sqrt())
        field.energy_scale.fill_(float(tau_std.max()))
        if isinstance(field, LagrangianNetwork) and field.still_potential:
            still_tau = tau_std.index_select(0, field.features.plain_v)
            field.still_scale.copy_(still_tau.clamp_min(CONSTANT_RATIO * float(tau_std.max())))
        dissipation = self.dynamics.dissipation
        if dissipation is not None:
            dissipation.viscous_scale.copy_(_fill_geometric(tau_std / qd_rms, known))
            dissipation.coulomb_scale.copy_(_fill_geometric(tau_std, _varies(tau_std)))

    def _torque_scale(self, tau: Tensor) -> Tensor:
        """Per-DoF torque std; unactuated DoFs get `unactuated_torque_scale` x the largest."""
        scale = _scale(tau)
        unactuated = self.dynamics.actuation.abs().sum(dim=-1) == 0
        if unactuated.any() and not unactuated.all():
            scale[unactuated] = self.unactuated_torque_scale * scale[~unactuated].max()
        return scale

    @property
    def trains_on_windows(self) -> bool:  # type: ignore[override]
        return self.loss_kind != "inverse"

    def loss(self, batch: TensorDictBase) -> LossOutput:
        """Per-transition loss on (B,); on windows (B, K), the forward term is the mean over
        a K-step rollout from each window's first state (`rollout_mse`) and the inverse term
        (loss 'both') is taken on each window's first transition."""
        windows = batch.batch_dims == 2
        terms: dict[str, Tensor] = {}
        if windows:
            if not self.trains_on_windows:
                raise ValueError("windows of transitions need loss 'forward' or 'both'")
            rollout = self._rollout_mse(batch)  # (K,)
            terms = {"rollout_mse": rollout.mean(), "forward_mse": rollout[0]}
            batch = batch[:, 0]  # the inverse term below: first transitions only
        inputs = {name: batch.get(key, None) for name, key in LOSS_INPUTS.items()}
        terms |= self._losses_for(batch[keys.Q].shape)(**inputs, forward=not windows)
        forward_term = "rollout_mse" if windows else "forward_mse"
        total = sum(terms[k] for k in (forward_term, "inverse_mse") if k in terms)
        metrics = {name: float(value.detach()) for name, value in terms.items()}
        metrics["loss"] = float(total.detach())
        return LossOutput(loss=total, metrics=metrics)

    def _transition_losses(
        self,
        q: Tensor,
        qd: Tensor,
        action: Tensor,
        qdd: Tensor | None,
        next_q: Tensor | None,
        next_qd: Tensor | None,
        forward: bool = True,
    ) -> dict[str, Tensor]:
        """The loss terms of transitions (B,) as scalars: `forward_mse` (when `forward` and
        the loss has it) and `inverse_mse`, at `qdd` or else the finite difference."""
        terms = {}
        if forward and self.loss_kind in ("forward", "both"):
            next_q, next_qd = _needed(next_q, keys.NEXT_Q), _needed(next_qd, keys.NEXT_QD)
            terms["forward_mse"] = self._state_mse(self.step(q, qd, action), next_q, next_qd)
        if self.loss_kind in ("inverse", "both"):
            if qdd is None:
                qdd = (_needed(next_qd, keys.NEXT_QD) - qd) / self.control_dt
            tau = self.applied_force(q, qd, action)
            e_tau = (self.dynamics.inverse_dynamics(q, qd, qdd) - tau) / self.tau_scale
            terms["inverse_mse"] = e_tau.pow(2).mean()
        return terms

    def _losses_for(self, shape: torch.Size) -> Callable[..., dict[str, Tensor]]:
        """`_transition_losses`, compiled for the fit's batch shape with `compile_fit`
        (`FitGraph`)."""
        return self._fit_graph.choose(self._transition_losses, shape, self.compile_fit)

    def _state_mse(self, pred: State, q_next: Tensor, qd_next: Tensor) -> Tensor:
        """Per-DoF normalised squared error of a predicted next state (scalar)."""
        e_q = differentiate_pos(self.layout, q_next, pred.q, 1.0) / self.q_scale
        e_qd = (pred.qd - qd_next) / self.qd_scale
        return e_q.pow(2).mean() + e_qd.pow(2).mean()

    def _rollout_mse(self, windows: TensorDictBase) -> Tensor:
        """`_state_mse` at each step of the model's rollout through windows (B, K). (K,)"""
        state = State(q=windows[keys.Q][:, 0], qd=windows[keys.QD][:, 0])
        errors = []
        for k in range(windows.shape[1]):
            state = self.step(state.q, state.qd, windows[keys.ACTION][:, k])
            errors.append(
                self._state_mse(state, windows[keys.NEXT_Q][:, k], windows[keys.NEXT_QD][:, k])
            )
        return torch.stack(errors)
