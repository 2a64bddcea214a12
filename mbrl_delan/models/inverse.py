"""Inverse-dynamics models: generalized forces tau from (q, qd, qdd), for fitting mocap data.

One interface (`InverseDynamicsModel`: `predict_torque`, `loss`, `fit_normalization`) and
three models:

- `DeLaNInverse`: ``tau = M(q) qdd + c(q, qd) + g(q) + d(qd)`` by a `DeLaN` of
  `mbrl_delan.models.delan` (free root and Euler-Poincare term included) with actuation
  B = I, in per-DoF units set from the data (below);
- `MLPInverse`: the paper's feed-forward baseline, three linear layers
  ``[phi(q), qd, qdd] -> tau``;
- `MLPEnsembleInverse`: E such MLPs with batched weight tensors ``(E, in, out)`` (one
  ``torch.baddbmm`` per layer for all members); the prediction is the members' mean.

What tau is: all nv generalized forces (62 on humanoid_CMU), i.e. the dataset's ``tau``: the
6 root-residual components (world-frame force, then body-frame torque) and the 56 hinge
torques. The root rows are the same equations of motion (M's root rows carry the body's mass
and momentum); the 56 joint torques alone are the columns 6: of the prediction.

Same information for every model: phi(q) (`QFeatures`: the root height and rotation matrix,
hinge angles; not the x/y position), qd and qdd. The MLPs get them concatenated and
standardised with the training mean and std (constant columns, e.g. the uncaptured fingers,
are only centred); DeLaN's networks see phi(q) (its plain entries, the hinge angles and root
height, standardised and softly bounded by `QFeatures.standardize`; the rotation-matrix entries
as they are), while qd and qdd enter through the equations.

Loss (the same for every model): the per-DoF normalised torque MSE

    loss = mean over samples and DoFs of ((tau_hat - tau) / sigma)^2,

sigma (``tau_scale``) being the training std of each DoF's torque, floored at
``std_floor`` times the largest DoF's std (so DoFs with almost no torque, the fingers, do not
dominate). `loss` also reports ``mse_si``, the plain MSE in SI units (N m^2 for torques, N^2
for the root force). An ensemble's loss averages its members' losses (each member is
trained); its metrics are those of the mean prediction.

DeLaN's units. Torques span 0.02 (fingers) to 500 (root vertical force), accelerations 0 to
50 and inertias 0.01 to 52; the networks' outputs are O(1). `DeLaNInverse` builds its `DeLaN`
with ``inertia_scaling=True`` and ``diagonal_init=True``: `fit_normalization` gives M, V and
the friction fixed positive per-DoF units from the training data (the structure, and M's
positive definiteness, are kept), and training starts from a diagonal M, g = 0 and viscous
friction of 0.69 units. The definitions are in `DeLaN`'s docstring (`mbrl_delan.models.delan`).
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable
from dataclasses import replace

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor, nn
from torch.nn import functional as F

from mbrl_delan import keys
from mbrl_delan.models.base import LossOutput
from mbrl_delan.models.delan import DeLaN, Stepping, TreePrior
from mbrl_delan.models.features import QFeatures
from mbrl_delan.models.field import LagrangianNetwork
from mbrl_delan.models.lagrangian import LagrangianDynamics
from mbrl_delan.models.structure import Structure
from mbrl_delan.models.tree import RigidBodyTree, TreeDynamics
from mbrl_delan.systems.system import JointLayout

MODEL_NAMES = ("delan", "mlp", "ensemble")
MLP_ACTIVATIONS: dict[str, Callable[[Tensor], Tensor]] = {
    "silu": F.silu,
    "tanh": torch.tanh,
    "relu": F.relu,
    "softplus": F.softplus,
    "elu": F.elu,
    "gelu": F.gelu,
}
CONSTANT_STD = 1e-6  # an input column with a smaller std is constant: centred, not scaled


def torque_scale(tau: Tensor, std_floor: float) -> Tensor:
    """Per-DoF std of tau (N, n) floored at std_floor times the largest one. -> (n,)."""
    std = tau.std(dim=0) if tau.shape[0] > 1 else tau.abs().mean(dim=0)
    return std.clamp_min(std_floor * float(std.max().clamp_min(1e-12)))


def _input_std(x: Tensor) -> Tensor:
    """Per-column std (N, k) -> (k,), 1 for constant columns."""
    std = x.std(dim=0) if x.shape[0] > 1 else torch.ones_like(x[0])
    return torch.where(std > CONSTANT_STD, std, torch.ones_like(std))


class InverseDynamicsModel(nn.Module, abc.ABC):
    """tau = f(q, qd, qdd), trained by the per-DoF normalised torque MSE.

    Args:
        nv: number of generalized velocities (and forces).
        std_floor: floor of the per-DoF torque std, relative to the largest, in (0, 1).
    """

    fit_kernel = "member_predictions"  # what `mbrl_delan.accelerate.compile_fit` compiles

    def __init__(self, nv: int, std_floor: float) -> None:
        super().__init__()
        if not 0.0 < std_floor < 1.0:
            raise ValueError(f"std_floor must be in (0, 1), got {std_floor}")
        self.nv, self.std_floor = nv, std_floor
        self.register_buffer("tau_scale", torch.ones(nv))

    @abc.abstractmethod
    def predict_torque(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        """(..., nq), (..., nv), (..., nv) -> tau (..., nv)."""

    def member_predictions(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        """Predictions of every member, (M, ..., nv); one member unless an ensemble."""
        return self.predict_torque(q, qd, qdd).unsqueeze(0)

    @torch.no_grad()
    def fit_normalization(self, data: TensorDictBase) -> None:
        """Set the loss's per-DoF torque scale (and model units) from the training data."""
        tau = data[keys.TAU].to(self.tau_scale)  # (N, nv)
        self.tau_scale.copy_(torque_scale(tau, self.std_floor))

    def loss(self, batch: TensorDictBase) -> LossOutput:
        """Normalised torque MSE on a batch with keys q, qd, qdd, tau."""
        tau = batch[keys.TAU]  # (B, nv)
        q, qd, qdd = batch[keys.Q], batch[keys.QD], batch[keys.QDD]
        members = self.member_predictions(q, qd, qdd)  # (M, B, nv)
        loss = ((members - tau) / self.tau_scale).pow(2).mean()
        with torch.no_grad():
            error = members.mean(0) - tau  # (B, nv)
            metrics = {
                "loss": float(loss),
                "mse": float((error / self.tau_scale).pow(2).mean()),
                "mse_si": float(error.pow(2).mean()),
            }
        return LossOutput(loss=loss, metrics=metrics)


# ---------------------------------------------------------------- feed-forward baselines


class _FeedForwardInverse(InverseDynamicsModel):
    """Standardised inputs [phi(q), qd, qdd] and outputs tau = net * tau_scale + tau_mean."""

    def __init__(
        self, layout: JointLayout, activation: str, std_floor: float, root_height: bool
    ) -> None:
        super().__init__(layout.nv, std_floor)
        if activation not in MLP_ACTIVATIONS:
            raise ValueError(
                f"activation must be one of {tuple(MLP_ACTIVATIONS)}, got {activation!r}"
            )
        self.activation = activation
        self.act = MLP_ACTIVATIONS[activation]
        self.features = QFeatures(layout, root_height=root_height)
        self.n_in = self.features.n_features + 2 * layout.nv
        self.register_buffer("in_mean", torch.zeros(self.n_in))
        self.register_buffer("in_std", torch.ones(self.n_in))
        self.register_buffer("tau_mean", torch.zeros(layout.nv))

    def inputs(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        """Raw network inputs [phi(q), qd, qdd]: (..., n_in)."""
        return torch.cat([self.features(q), qd, qdd], dim=-1)

    def standardised_inputs(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        return (self.inputs(q, qd, qdd) - self.in_mean) / self.in_std  # (..., n_in)

    @torch.no_grad()
    def fit_normalization(self, data: TensorDictBase) -> None:
        super().fit_normalization(data)
        dtype = self.in_mean.dtype
        x = self.inputs(*(data[k].to(dtype) for k in (keys.Q, keys.QD, keys.QDD)))
        self.in_mean.copy_(x.mean(dim=0))
        self.in_std.copy_(_input_std(x))
        self.tau_mean.copy_(data[keys.TAU].to(dtype).mean(dim=0))


class MLPInverse(_FeedForwardInverse):
    """The feed-forward baseline: Linear -> act -> Linear -> act -> Linear (three layers)."""

    def __init__(
        self,
        layout: JointLayout,
        hidden: int = 256,
        activation: str = "silu",
        std_floor: float = 1e-3,
        root_height: bool = True,
    ) -> None:
        super().__init__(layout, activation, std_floor, root_height)
        if hidden < 1:
            raise ValueError(f"hidden must be >= 1, got {hidden}")
        self.layers = nn.ModuleList(
            [nn.Linear(self.n_in, hidden), nn.Linear(hidden, hidden), nn.Linear(hidden, self.nv)]
        )

    def predict_torque(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        x = self.standardised_inputs(q, qd, qdd)
        for layer in self.layers[:-1]:
            x = self.act(layer(x))
        return self.layers[-1](x) * self.tau_scale + self.tau_mean  # (..., nv)


class BatchedLinear(nn.Module):
    """E independent linear maps: (E, B, n_in) -> (E, B, n_out), one baddbmm."""

    def __init__(self, members: int, n_in: int, n_out: int) -> None:
        super().__init__()
        bound = 1.0 / math.sqrt(n_in)  # nn.Linear's default initialisation, per member
        self.weight = nn.Parameter(torch.empty(members, n_in, n_out).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(members, 1, n_out).uniform_(-bound, bound))

    def forward(self, x: Tensor) -> Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


class MLPEnsembleInverse(_FeedForwardInverse):
    """E three-layer MLPs (as `MLPInverse`) in batched weights; predicts the members' mean."""

    def __init__(
        self,
        layout: JointLayout,
        ensemble_size: int = 5,
        hidden: int = 256,
        activation: str = "silu",
        std_floor: float = 1e-3,
        root_height: bool = True,
    ) -> None:
        super().__init__(layout, activation, std_floor, root_height)
        if ensemble_size < 1 or hidden < 1:
            raise ValueError(f"need ensemble_size >= 1 and hidden >= 1: {ensemble_size}, {hidden}")
        self.ensemble_size = ensemble_size
        sizes = (self.n_in, hidden, hidden, self.nv)
        self.layers = nn.ModuleList(
            BatchedLinear(ensemble_size, a, b) for a, b in zip(sizes[:-1], sizes[1:], strict=True)
        )

    def member_predictions(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        x = self.standardised_inputs(q, qd, qdd)  # (..., n_in)
        lead = x.shape[:-1]
        x = x.reshape(1, -1, self.n_in).expand(self.ensemble_size, -1, -1)  # (E, B, n_in)
        for layer in self.layers[:-1]:
            x = self.act(layer(x))
        out = self.layers[-1](x) * self.tau_scale + self.tau_mean  # (E, B, nv)
        return out.reshape(self.ensemble_size, *lead, self.nv)  # (E, ..., nv)

    def predict_torque(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        return self.member_predictions(q, qd, qdd).mean(0)  # (..., nv)


# ---------------------------------------------------------------- DeLaN


# the inverse fit's defaults: a wider network, no Coulomb friction
INVERSE_STRUCTURE = Structure(hidden=128, coulomb=False)


class DeLaNInverse(InverseDynamicsModel):
    """DeLaN's inverse dynamics tau = M qdd + c + g + d, in data units (module docstring).

    The mechanics is a `DeLaN` with actuation B = I (its action is tau), ``loss="inverse"``,
    and its `structure` with ``inertia_scaling`` and ``diagonal_init`` on; the loss is
    `InverseDynamicsModel`'s. With a `tree` (the robot's known kinematic tree with learned
    inertias, `RigidBodyTree`), DeLaN's networks are a residual Lagrangian beside the tree's
    rigid body (`TreeDynamics`: M = M_tree + M_res, c, g and the friction the tree's plus the
    residual's).

    Args:
        layout: joint layout (a free root gets the Euler-Poincare term).
        structure: what the mechanics are made of (`Structure`); `INVERSE_STRUCTURE` when None.
        std_floor: see `InverseDynamicsModel`.
        control_dt: DeLaN's step (s); only used for finite-difference accelerations when the
            data lack ``qdd`` (humanoid_CMU's timestep by default).
        tree: the known tree under DeLaN (None: DeLaN alone).
    """

    def __init__(
        self,
        layout: JointLayout,
        structure: Structure | None = None,
        std_floor: float = 1e-3,
        control_dt: float = 0.002,
        tree: RigidBodyTree | None = None,
    ) -> None:
        super().__init__(layout.nv, std_floor)
        structure = replace(
            structure or INVERSE_STRUCTURE, inertia_scaling=True, diagonal_init=True
        )
        self.delan = DeLaN(
            layout, torch.eye(layout.nv), control_dt=control_dt, structure=structure,
            stepping=Stepping(loss="inverse"),
            tree=None if tree is None else TreePrior(tree, residual=True),
        )  # fmt: skip

    @property
    def dynamics(self) -> LagrangianDynamics | TreeDynamics:
        return self.delan.dynamics

    @property
    def mechanics(self) -> LagrangianNetwork:
        """The scaled `LagrangianNetwork` (``row_scale``, ``energy_scale``, ``features``)."""
        return self.delan.dynamics.field  # type: ignore[return-value]

    def predict_torque(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        return self.dynamics.inverse_dynamics(q, qd, qdd)  # (..., nv)

    def mass_matrix_cholesky(self, q: Tensor) -> Tensor:
        """The factor L of the learned M at q (..., nq): DeLaN's own (M = L L^T [+ armature],
        units included; triangular), or on a tree the Cholesky factor of the whole M.
        (..., nv, nv)"""
        if isinstance(self.dynamics, TreeDynamics):
            return torch.linalg.cholesky(self.mass_matrix(q))
        qd = q.new_zeros(q.shape[:-1] + (self.nv,))
        return self.mechanics.jet(q, qd).L

    def mass_matrix(self, q: Tensor) -> Tensor:
        """The learned M(q) (DeLaN's L L^T with the known armature, or the tree's M plus the
        residual's): (..., nv, nv)."""
        if isinstance(self.dynamics, TreeDynamics):
            return self.dynamics.mass_and_bias(q, q.new_zeros(q.shape[:-1] + (self.nv,)))[0]
        L = self.mass_matrix_cholesky(q)
        return self.dynamics.with_armature(L @ L.transpose(-1, -2))

    def friction_torque(self, qd: Tensor) -> Tensor:
        """The learned joint friction at qd of a fixed-base robot: the tree's damping and
        DeLaN's dissipation, viscous and Coulomb (its lead left out). (..., nv)"""
        dynamics = self.dynamics
        force = torch.zeros_like(qd)
        if isinstance(dynamics, TreeDynamics):
            force = force + dynamics.tree.damping.to(qd) * qd
        if dynamics.dissipation is not None:
            force = force + dynamics.dissipation(qd)
        return force

    def mass_matrix_float64(self, q: Tensor) -> Tensor:
        """M(q) formed in float64 (DeLaN's from its factor L, so float32 round-off does not
        limit checks of ill-conditioned matrices). (..., nv, nv)"""
        if isinstance(self.dynamics, TreeDynamics):
            return self.mass_matrix(q).to(torch.float64)
        L = self.mass_matrix_cholesky(q).to(torch.float64)
        return self.dynamics.with_armature(L @ L.transpose(-1, -2))

    @torch.no_grad()
    def fit_normalization(self, data: TensorDictBase) -> None:
        """The loss's torque scale, and DeLaN's units and feature statistics (with tau as
        the action: B = I)."""
        super().fit_normalization(data)
        dtype = self.tau_scale.dtype
        inputs = TensorDict(
            {k: data[k].to(dtype) for k in (keys.Q, keys.QD, keys.QDD)},
            batch_size=data.batch_size,
        )
        inputs[keys.ACTION] = data[keys.TAU].to(dtype)  # (N, nv)
        self.delan.fit_normalization(inputs)
