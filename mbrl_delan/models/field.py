"""The learned fields of a DeLaN: L(q) and V(q) from one network (`LagrangianNetwork`),
and the unstructured residual force (`ResidualForce`)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from mbrl_delan.models.features import QFeatures
from mbrl_delan.models.kernels import linear, linear_t
from mbrl_delan.models.lagrangian import MechanicsField, MechanicsJet, root_frame_jet
from mbrl_delan.models.tangent_mlp import MLPPass, TangentMLP

SPRING_UNITS = {"spring_scale": 1.0, "spring_force_scale": 1.0, "spring_centre": 0.0}

# up to this many DoFs, L's head is laid out as the matrix (`LagrangianNetwork._matrix_head`):
# no per-sample scatter in the small systems' compiled planners; above, over L's entries only
MATRIX_HEAD_MAX_N = 6


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

    `springs`: (q index, v index) of hinge and slide coordinates x that V also holds a
    learned quadratic of, V += 1/2 (x - c)^T K (x - c) + b^T (x - c) with K symmetric (both start
    at 0): linear springs, each joint's and those that couple joints (a tendon over two
    joints), exactly and wherever the data did not reach, which an MLP on (sin q, cos q)
    extrapolates only as far as the data went. Units (`set_spring_units`, from the data): c
    the coordinates' mean, K_ij = W_ij sqrt(f_i f_j / (d_i d_j)) and b_i = f_i beta_i for
    the learned W (symmetrised) and beta, f_i the joint's torque std and d_i its coordinate's:
    a unit of W_ii is a spring that pushes one torque std at one std from the mean, so every
    entry learns at the rate of the joint's own torques.

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
        springs: Sequence[tuple[int, int]] = (),
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
        entry_index = torch.cat([torch.arange(n) * (n + 1), rows * n + cols])  # [diag; others]
        self.register_buffer("entry_index", entry_index, persistent=False)
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
        self._index_pairs("spring", springs)
        self.spring_stiffness: nn.Parameter | None = None
        if springs:  # W (K = E S (W + W^T) / 2 S) and beta (b = E g beta)
            self.spring_stiffness = nn.Parameter(torch.zeros(len(springs), len(springs)))
            self.spring_offset = nn.Parameter(torch.zeros(len(springs)))
            for name, fill in SPRING_UNITS.items():  # S, g, c; ones and zeros: E on raw x
                self.register_buffer(name, torch.full((len(springs),), fill))
        self.height_weight: nn.Parameter | None = None
        if heights:  # w_k in units of energy_scale per metre (m g for a free root's height)
            self.height_weight = nn.Parameter(torch.zeros(len(heights)))
            self.register_buffer("height_started", torch.zeros((), dtype=torch.bool))

    @torch.no_grad()
    def start_height_weight(self, force: Tensor, weight: float | None = None) -> None:
        """Start w at the mean generalized force (N, n) along each height: the body's weight
        m g when the data's mean vertical acceleration is zero; or at a known `weight` (N).
        Once: later calls (refits on more data) keep the learned w."""
        if self.height_weight is not None and not bool(self.height_started):
            mean = force.index_select(-1, self.height_v).mean(dim=0)
            if weight is not None:
                mean = torch.full_like(mean, weight)
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

    def _index_pairs(self, name: str, pairs: Sequence[tuple[int, int]]) -> None:
        """Buffers ``<name>_q`` and ``<name>_v`` of (q index, v index) pairs."""
        for k, suffix in enumerate(("q", "v")):
            index = torch.tensor([p[k] for p in pairs], dtype=torch.long)
            self.register_buffer(f"{name}_{suffix}", index, persistent=False)

    @torch.no_grad()
    def set_spring_units(self, q: Tensor, torque_std: Tensor) -> None:
        """The quadratic potential's units from the data: positions q (N, nq) and every
        DoF's torque std (nv,) (see the class). A coordinate that does not move gets a spread
        of 1e-3, a torque below 1e-6 of the largest that floor."""
        if self.spring_stiffness is None:
            return
        x = q.index_select(-1, self.spring_q).to(self.spring_scale)
        force = torque_std.index_select(0, self.spring_v).to(x)
        force = force.clamp_min(1e-6 * float(torque_std.max()))
        energy = self.energy_scale.to(x)
        self.spring_scale.copy_((force / (energy * x.std(dim=0).clamp_min(1e-3))).sqrt())
        self.spring_force_scale.copy_(force / energy)
        self.spring_centre.copy_(x.mean(dim=0))

    def _spring_terms(self) -> tuple[Tensor, Tensor]:
        """K (m, m) and b (m,) of the quadratic potential, in SI."""
        assert self.spring_stiffness is not None
        weight, scale = self.spring_stiffness, self.spring_scale
        stiffness = 0.5 * (weight + weight.T) * (scale.unsqueeze(-1) * scale) * self.energy_scale
        return stiffness, self.spring_offset * self.spring_force_scale * self.energy_scale

    def _spring_potential(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """1/2 (x - c)^T K (x - c) + b^T (x - c) (...) and its force K (x - c) + b
        (..., m) on the spring coordinates x (`springs`)."""
        stiffness, offset = self._spring_terms()
        x = q.index_select(-1, self.spring_q).to(stiffness.dtype) - self.spring_centre
        force = x @ stiffness + offset
        return ((0.5 * x @ stiffness + offset) * x).sum(-1), force

    def _load_from_state_dict(self, state_dict: dict[str, Tensor], prefix: str,
                              *args: object, **kwargs: object) -> None:  # fmt: skip
        """Weights saved before the springs had units load with the old ones (E on raw x)."""
        if self.spring_stiffness is not None:
            for name, fill in SPRING_UNITS.items():
                state_dict.setdefault(prefix + name, torch.full_like(getattr(self, name), fill))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def spring_force(self, q: Tensor) -> Tensor:
        """The quadratic potential's generalized force dV_spring/dq (..., nv), zero off the
        spring coordinates and without a quadratic potential."""
        force = torch.zeros(*q.shape[:-1], self.n, dtype=q.dtype, device=q.device)
        if self.spring_stiffness is None:
            return force
        return force.index_add(-1, self.spring_v, self._spring_potential(q)[1].to(q.dtype))

    def joint_springs(self) -> Tensor | None:
        """K of the learned quadratic potential (m, m) over `springs`, in SI (None without)."""
        if self.spring_stiffness is None:
            return None
        return self._spring_terms()[0].detach()

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

    @torch.no_grad()
    def start_small(self, level: float) -> None:
        """`start_diagonal`, and L's diagonal at `level` of its units everywhere (its head's
        weights zero): M starts at about level^2 of its units, V at 0 (a residual Lagrangian
        beside a known rigid body, `models.tree.TreeDynamics`). A factor L L^T cannot start
        at exactly zero: its gradient vanishes there."""
        if level <= self.diag_shift:
            raise ValueError(f"level must be > diag_shift ({self.diag_shift}), got {level}")
        self.start_diagonal()
        head = self.trunk.head
        head.weight[: self.n].zero_()
        head.bias[: self.n].fill_(math.log(math.expm1(level - self.diag_shift)))

    def _matrix_head(self) -> tuple[Tensor, Tensor]:
        """The L head laid out as the matrix L, row-major: weight (n*n, hidden), bias (n*n,).

        Entries above the diagonal get zero rows, so `linear(h, W, b)` gives the raw L
        directly (no per-sample scatter), and a cotangent on all of L maps back with one
        matmul (the entries above the diagonal meet zero rows). Costs one gather of the
        weights per call, independent of the batch.
        """
        head, rows = self.trunk.head, self.v_row
        weight = torch.cat([head.weight[:rows], head.weight.new_zeros(1, head.in_features)])
        bias = torch.cat([head.bias[:rows], head.bias.new_zeros(1)])
        scale = torch.cat([self.row_scale, self.row_scale.new_ones(1)])[self.row_of_entry]
        weight = weight.index_select(0, self.layout) * scale.unsqueeze(-1)
        return weight, bias.index_select(0, self.layout) * scale

    def _entry_head(self) -> tuple[Tensor, Tensor]:
        """The L head over L's entries only, [diagonal (n); the others (n_off)], in units:
        weight (n + n_off, hidden), bias (n + n_off,). The diagonal rows are unscaled."""
        head, rows = self.trunk.head, self.v_row
        scale = torch.cat([self.row_scale.new_ones(self.n), self.row_scale[self.rows]])
        return head.weight[:rows] * scale.unsqueeze(-1), head.bias[:rows] * scale

    def _factor(self, body: MLPPass) -> tuple[Tensor, Tensor, Callable[[Tensor], Tensor]]:
        """L and L_dot (..., n, n) from the trunk's output and tangent, and the map of a
        cotangent on L (..., n, n) to one on the trunk's output (..., hidden).

        Up to `MATRIX_HEAD_MAX_N` DoFs the head is laid out as the matrix (`_matrix_head`);
        above, it computes only L's entries and scatters them into the matrix
        (`_entry_head`): on humanoid_CMU's tree 952 of 3,844 entries, a quarter of the
        head's products.
        """
        if self.n <= MATRIX_HEAD_MAX_N:
            return self._matrix_factor(body)
        n = self.n
        weight, bias = self._entry_head()
        raw, d_raw = linear(body.out, weight, bias), linear(body.d_out, weight)  # (..., E)
        raw_diag = raw[..., :n]
        diag_slope = self.row_scale * torch.sigmoid(raw_diag)  # d L_ii / d raw_ii
        diag = self.row_scale * (F.softplus(raw_diag) + self.diag_shift)
        L = self._scatter(torch.cat([diag, raw[..., n:]], dim=-1))
        L_dot = self._scatter(torch.cat([diag_slope * d_raw[..., :n], d_raw[..., n:]], dim=-1))

        def to_hidden(d_L: Tensor) -> Tensor:
            d_entries = d_L.flatten(-2).index_select(-1, self.entry_index)  # (..., E)
            d_raw = torch.cat([diag_slope * d_entries[..., :n], d_entries[..., n:]], dim=-1)
            return linear_t(d_raw, weight)

        return L, L_dot, to_hidden

    def _scatter(self, entries: Tensor) -> Tensor:
        """L's entries (..., n + n_off) into the matrix (..., n, n), zeros elsewhere."""
        flat = entries.new_zeros(*entries.shape[:-1], self.n * self.n)
        return flat.index_copy(-1, self.entry_index, entries).unflatten(-1, (self.n, self.n))

    def _matrix_factor(self, body: MLPPass) -> tuple[Tensor, Tensor, Callable[[Tensor], Tensor]]:
        """`_factor` through the matrix-layout head."""
        n, head = self.n, self.trunk.head
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

        def to_hidden(d_L: Tensor) -> Tensor:
            d_diag = torch.diagonal(d_L, dim1=-2, dim2=-1)  # (..., n)
            return (
                linear(d_L.flatten(-2), weight.T)  # every entry as if raw; diagonal fixed here
                + linear((diag_slope - 1.0) * d_diag, head.weight[:n].T)
            )

        return L, L_dot, to_hidden

    def jet(self, q: Tensor, qd: Tensor) -> MechanicsJet:
        """L, V and their derivatives; with ``root_frame``, L = S L_b (`root_frame_jet`)."""
        jet = self._network_jet(q, qd)
        return root_frame_jet(jet, q, qd) if self.root_frame else jet

    def _network_jet(self, q: Tensor, qd: Tensor) -> MechanicsJet:
        """The jet through the trunk: a tangent along qd forward, one reverse pass back."""
        plain_scalar = not (self.still_potential or self.height_q.numel() or self.spring_q.numel())
        if self.n == 1 and plain_scalar:
            return self._scalar_jet(q, qd)
        body = self.trunk.body(self.features(q), self.features.jvp(q, qd))
        L, L_dot, factor_to_hidden = self._factor(body)
        v_weight, v_bias = self._potential_head()
        potential = linear(body.out, v_weight.unsqueeze(0), v_bias).squeeze(-1)
        if self.height_q.numel():
            height_potential, height_weight = self._height_potential(q)
            potential = potential + height_potential
        if self.still_potential:
            still_force, still_offset, still_weight = self._still_terms(q, body.out)
            potential = potential + (still_offset * still_force).sum(-1)
        if self.spring_q.numel():
            spring_potential, spring_force = self._spring_potential(q)
            potential = potential + spring_potential

        def pullback(d_L: Tensor, d_V: Tensor) -> Tensor:
            d_hidden = factor_to_hidden(d_L) + d_V.unsqueeze(-1) * v_weight
            if self.still_potential:
                d_hidden = d_hidden + linear(d_V.unsqueeze(-1) * still_offset, still_weight.T)
            grad = self.features.vjp(q, self.trunk.body_vjp(body, d_hidden))
            if self.still_potential:
                still_grad = d_V.unsqueeze(-1) * still_force
                grad = grad.index_add(-1, self.features.plain_v, still_grad)
            if self.height_q.numel():
                grad = grad.index_add(-1, self.height_v, d_V.unsqueeze(-1) * height_weight)
            if self.spring_q.numel():
                grad = grad.index_add(-1, self.spring_v, d_V.unsqueeze(-1) * spring_force)
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
