"""PETS-style probabilistic ensemble: the black-box baseline world model.

E MLP members share one set of batched weight tensors `(E, in, out)`, so a forward pass is
one `torch.baddbmm` per layer for all members together. Each member outputs a diagonal
Gaussian over the normalised one-step targets

    y = [differentiate_pos(layout, q, q_next, control_dt), qd_next - qd]   # (..., 2 * nv)

i.e. the average velocity over the control step (position change in velocity space divided
by `control_dt`) and the change of velocity. `step` inverts the first half exactly with
`integrate_pos(layout, q, v_avg, control_dt)`, so targets and predictions use one
convention for every joint type.

Propagation of a batch of particles through `step` (Chua et al., 2018):
- ``"tsinf"``: element b of the flattened batch always uses member b % E,
- ``"ts1"``: every element draws a fresh member on every call,
- ``"mean"``: the average of all members' means.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from omegaconf import MISSING, DictConfig
from tensordict import TensorDictBase
from torch import Tensor, nn

from mbrl_delan import keys
from mbrl_delan.models.base import LossOutput, ModelConfig, WorldModel
from mbrl_delan.models.features import QFeatures
from mbrl_delan.registry import register_model
from mbrl_delan.rules import rule
from mbrl_delan.systems.posarith import differentiate_pos, integrate_pos
from mbrl_delan.systems.system import JointLayout, State, System

log = logging.getLogger(__name__)

PROPAGATIONS = ("ts1", "tsinf", "mean")
ACTIVATIONS: dict[str, Callable[[Tensor], Tensor]] = {
    "silu": F.silu,
    "swish": F.silu,
    "relu": F.relu,
    "elu": F.elu,
    "tanh": torch.tanh,
    "gelu": F.gelu,
}
STD_FLOOR = 1e-8  # a feature whose std is below this is left unscaled (std := 1)
LOGVAR_BOUND_WEIGHT = 0.01  # PETS' weight on (max_logvar - min_logvar) in the loss


@dataclass
class EnsemblePrediction:
    """Per-member Gaussians over the normalised targets."""

    mean: Tensor  # (E, ..., 2 * nv)
    logvar: Tensor  # (E, ..., 2 * nv), within [min_logvar, max_logvar] (softly)


def bound_logvar(raw: Tensor, min_logvar: Tensor, max_logvar: Tensor) -> Tensor:
    """Soft-clip a raw log-variance into [min_logvar, max_logvar] with softplus.

    s = min + softplus(raw - min) - softplus(raw - max): smooth, increasing, about `raw`
    between the bounds and strictly inside them (PETS' nested form
    `min + softplus(max - softplus(max - raw) - min)` overshoots max by
    log(1 + exp(min - max))). Evaluated in the equivalent form
    `max - softplus(max - raw) + softplus(min - raw)` above the midpoint, so neither
    branch subtracts two large numbers.
    """
    low_side = min_logvar + (F.softplus(raw - min_logvar) - F.softplus(raw - max_logvar))
    high_side = max_logvar - (F.softplus(max_logvar - raw) - F.softplus(min_logvar - raw))
    return torch.where(raw > 0.5 * (min_logvar + max_logvar), high_side, low_side)


def _flat_rows(tensor: Tensor, device: torch.device) -> Tensor:
    """(..., k) -> (N, k) on `device`."""
    return tensor.to(device).reshape(-1, tensor.shape[-1])


class GaussianEnsemble(WorldModel):
    """E probabilistic MLPs predicting velocity-space state deltas (PETS baseline).

    Inputs `[QFeatures(q), qd, action]` and targets are standardised with the buffers set by
    `fit_normalization`; the networks work entirely in normalised units.
    """

    def __init__(
        self,
        layout: JointLayout,
        nu: int,
        control_dt: float,
        ensemble_size: int = 5,
        hidden: int = 200,
        layers: int = 3,
        activation: str = "silu",
        propagation: str = "tsinf",
        min_logvar_init: float = -10.0,
        max_logvar_init: float = 0.5,
        weight_decay: float | Sequence[float] = 0.0,
        bootstrap: bool = True,
        seed: int | None = None,
    ) -> None:
        """Build the members.

        Args:
            layout: joint layout of the system (hinge and slide joints for `QFeatures`).
            nu: action size.
            control_dt: duration of one `step` (s); scales the position targets.
            ensemble_size: number of members E.
            hidden: width of each hidden layer.
            layers: number of hidden layers.
            activation: one of `ACTIVATIONS`.
            propagation: "tsinf", "ts1" or "mean" (how `step` uses the members).
            min_logvar_init: initial value of the learned lower log-variance bound (per
                output dimension, normalised units).
            max_logvar_init: initial value of the learned upper log-variance bound.
            weight_decay: L2 coefficient(s) in the loss, one per linear layer (hidden layers
                then the output layer) or one for all; the term is sum_l c_l/2 * ||W_l||^2.
            bootstrap: if True each member trains on its own resample of every batch.
            seed: seeds `self.generator` (bootstrap draws); None uses torch's default RNG.
        """
        super().__init__()
        if ensemble_size < 1 or hidden < 1 or layers < 0:
            raise ValueError("ensemble_size and hidden must be >= 1, layers >= 0")
        if activation not in ACTIVATIONS:
            raise ValueError(f"unknown activation '{activation}'; known: {sorted(ACTIVATIONS)}")
        if control_dt <= 0:
            raise ValueError(f"control_dt must be > 0, got {control_dt}")
        self.layout = layout
        self.nu = nu
        self.control_dt = float(control_dt)
        self.ensemble_size = ensemble_size
        self.activation = activation
        self._act = ACTIVATIONS[activation]
        self.propagation = propagation  # validated by the setter below
        self.bootstrap = bootstrap
        self.generator: torch.Generator | None = (
            None if seed is None else torch.Generator().manual_seed(seed)
        )
        self.features = QFeatures(layout, bound_plain=False)
        self.nv = layout.nv
        self.in_dim = self.features.n_features + self.nv + nu
        self.out_dim = 2 * self.nv
        widths = [self.in_dim] + [hidden] * layers + [2 * self.out_dim]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(widths[:-1], widths[1:], strict=True):
            self.weights.append(nn.Parameter(torch.empty(ensemble_size, fan_in, fan_out)))
            self.biases.append(nn.Parameter(torch.empty(ensemble_size, 1, fan_out)))
        self.weight_decay = self._per_layer(weight_decay, len(self.weights))
        self.min_logvar = nn.Parameter(torch.full((self.out_dim,), float(min_logvar_init)))
        self.max_logvar = nn.Parameter(torch.full((self.out_dim,), float(max_logvar_init)))
        self.register_buffer("in_mean", torch.zeros(self.in_dim))
        self.register_buffer("in_std", torch.ones(self.in_dim))
        self.register_buffer("out_mean", torch.zeros(self.out_dim))
        self.register_buffer("out_std", torch.ones(self.out_dim))
        self.reset_parameters()

    # ------------------------------------------------------------------ set-up

    @staticmethod
    def _per_layer(value: float | Sequence[float], n_layers: int) -> tuple[float, ...]:
        if isinstance(value, int | float):
            return (float(value),) * n_layers
        coeffs = tuple(float(v) for v in value)
        if len(coeffs) != n_layers:
            raise ValueError(f"weight_decay needs {n_layers} coefficients, got {len(coeffs)}")
        return coeffs

    @property
    def propagation(self) -> str:
        return self._propagation

    @propagation.setter
    def propagation(self, value: str) -> None:
        if value not in PROPAGATIONS:
            raise ValueError(f"unknown propagation '{value}'; known: {PROPAGATIONS}")
        self._propagation = value

    @torch.no_grad()
    def reset_parameters(self) -> None:
        """nn.Linear's default initialisation, drawn independently for every member.

        Weights and biases ~ U(-1/sqrt(fan_in), 1/sqrt(fan_in)) (what nn.Linear's
        kaiming_uniform(a=sqrt(5)) amounts to), from torch's default RNG.
        """
        for weight, bias in zip(self.weights, self.biases, strict=True):
            bound = 1.0 / math.sqrt(weight.shape[1])
            weight.uniform_(-bound, bound)
            bias.uniform_(-bound, bound)

    # ------------------------------------------------------------ normalisation

    def _inputs(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """Unnormalised network inputs: (..., nq), (..., nv), (..., nu) -> (..., in_dim)."""
        lead = torch.broadcast_shapes(q.shape[:-1], qd.shape[:-1], action.shape[:-1])
        return torch.cat(
            [
                self.features(q).expand(*lead, -1),
                qd.expand(*lead, -1),
                action.expand(*lead, -1),
            ],
            dim=-1,
        )

    def targets(self, q: Tensor, qd: Tensor, q_next: Tensor, qd_next: Tensor) -> Tensor:
        """Unnormalised targets [average velocity over the step, velocity change]. (..., 2nv)."""
        v_avg = differentiate_pos(self.layout, q, q_next, self.control_dt)
        return torch.cat([v_avg, qd_next - qd], dim=-1)

    def _batch_tensors(self, data: TensorDictBase) -> tuple[Tensor, Tensor]:
        """Flattened (inputs (N, in_dim), targets (N, 2nv)) of a transition TensorDict."""
        device = self.max_logvar.device
        q, qd, action, q_next, qd_next = (
            _flat_rows(data.get(key), device)
            for key in (keys.Q, keys.QD, keys.ACTION, keys.NEXT_Q, keys.NEXT_QD)
        )
        return self._inputs(q, qd, action), self.targets(q, qd, q_next, qd_next)

    @torch.no_grad()
    def fit_normalization(self, data: TensorDictBase) -> None:
        """Set input/target mean and std (population std, over all transitions in `data`).

        Dimensions with std < STD_FLOOR (e.g. a constant feature) keep std = 1.
        """
        x, y = self._batch_tensors(data)
        for tensor, mean_buf, std_buf in (
            (x, self.in_mean, self.in_std),
            (y, self.out_mean, self.out_std),
        ):
            t64 = tensor.to(torch.float64)
            std = t64.std(dim=0, unbiased=False)
            std = torch.where(std < STD_FLOOR, torch.ones_like(std), std)
            mean_buf.copy_(t64.mean(dim=0))
            std_buf.copy_(std)
        log.debug("ensemble normalisation fitted on %d transitions", x.shape[0])

    def _normalize_inputs(self, x: Tensor) -> Tensor:
        return (x.to(self.in_mean.dtype) - self.in_mean) / self.in_std

    # ------------------------------------------------------------------ network

    def forward_members(self, x: Tensor) -> EnsemblePrediction:
        """Run member e on x[e]. x: (E, N, in_dim) normalised -> mean, logvar (E, N, 2nv)."""
        h = x
        last = len(self.weights) - 1
        for i, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            h = torch.baddbmm(bias, h, weight)  # (E, N, out_i)
            if i < last:
                h = self._act(h)
        mean, raw_logvar = h.split(self.out_dim, dim=-1)
        return EnsemblePrediction(mean, bound_logvar(raw_logvar, self.min_logvar, self.max_logvar))

    def predict(self, q: Tensor, qd: Tensor, action: Tensor) -> EnsemblePrediction:
        """Every member on every element, normalised units. (..., ·) -> (E, ..., 2nv)."""
        x = self._normalize_inputs(self._inputs(q, qd, action))
        lead = x.shape[:-1]
        flat = x.reshape(1, -1, self.in_dim).expand(self.ensemble_size, -1, -1)
        pred = self.forward_members(flat)
        shape = (self.ensemble_size, *lead, self.out_dim)
        return EnsemblePrediction(pred.mean.reshape(shape), pred.logvar.reshape(shape))

    # -------------------------------------------------------------------- loss

    def _bootstrap_indices(self, n: int, device: torch.device) -> Tensor:
        """(E, n) row indices: a resample with replacement per member (identity if off)."""
        if not self.bootstrap:
            return torch.arange(n, device=device).expand(self.ensemble_size, n)
        gen = self.generator
        idx = torch.randint(
            n,
            (self.ensemble_size, n),
            generator=gen,
            device=gen.device if gen is not None else torch.device("cpu"),
        )
        return idx.to(device)

    def _weight_decay_term(self) -> Tensor:
        """sum_l c_l / 2 * ||W_l||^2 over all members; () tensor."""
        l2 = self.max_logvar.new_zeros(())
        for coeff, weight in zip(self.weight_decay, self.weights, strict=True):
            if coeff > 0:
                l2 = l2 + 0.5 * coeff * weight.square().sum()
        return l2

    def loss(self, batch: TensorDictBase) -> LossOutput:
        """Gaussian NLL summed over members, plus the log-variance bound and L2 terms.

        With y the normalised targets, (mu_e, s_e) member e's mean and log-variance on its
        bootstrap rows n and output dims d (D = 2nv):
            nll_e   = mean_{n,d} 0.5 * ((mu_e - y)^2 * exp(-s_e) + s_e + log(2 pi))
            mse_e   = mean_{n,d} (mu_e - y)^2
            bound   = 0.01 * (sum(max_logvar) - sum(min_logvar))
            l2      = sum_l c_l / 2 * ||W_l||^2   (all members)
            loss    = sum_e nll_e + bound + l2
        Metrics (floats): "nll" = mean_e nll_e, "mse" = mean_e mse_e (normalised units),
        "logvar_bound" = bound, "weight_decay" = l2, "logvar_mean" = mean_{e,n,d} s_e,
        "loss" = loss.
        """
        x, y = self._batch_tensors(batch)
        x = self._normalize_inputs(x)  # (N, in_dim)
        y = (y.to(self.out_mean.dtype) - self.out_mean) / self.out_std  # (N, D)
        idx = self._bootstrap_indices(x.shape[0], x.device)  # (E, N)
        pred = self.forward_members(x[idx])  # (E, N, D)
        y_e = y[idx]  # (E, N, D)
        sq_err = (pred.mean - y_e).square()
        nll_e = 0.5 * (sq_err * torch.exp(-pred.logvar) + pred.logvar + math.log(2 * math.pi))
        nll_e = nll_e.mean(dim=(1, 2))  # (E,)
        bound = LOGVAR_BOUND_WEIGHT * (self.max_logvar.sum() - self.min_logvar.sum())
        l2 = self._weight_decay_term()
        total = nll_e.sum() + bound + l2
        metrics = {
            "loss": total.item(),
            "nll": nll_e.mean().item(),
            "mse": sq_err.mean().item(),
            "logvar_bound": bound.item(),
            "weight_decay": l2.item(),
            "logvar_mean": pred.logvar.mean().item(),
        }
        return LossOutput(loss=total, metrics=metrics)

    # -------------------------------------------------------------------- step

    def _route_tsinf(self, x: Tensor) -> EnsemblePrediction:
        """Element b through member b % E. x: (B, in) -> mean, logvar (B, D)."""
        n, e = x.shape[0], self.ensemble_size
        rows = -(-n // e)  # ceil(n / e)
        pad = rows * e - n
        if pad:
            x = torch.cat([x, x.new_zeros(pad, x.shape[-1])], dim=0)
        grouped = x.reshape(rows, e, -1).transpose(0, 1)  # (E, rows, in): [e, r] = x[r*E + e]
        pred = self.forward_members(grouped)  # (E, rows, D)
        mean, logvar = (
            t.transpose(0, 1).reshape(rows * e, -1)[:n] for t in (pred.mean, pred.logvar)
        )
        return EnsemblePrediction(mean, logvar)

    def _route_by_member(self, x: Tensor, member: Tensor) -> EnsemblePrediction:
        """Element b through member[b]; each member sees only its own elements.

        x: (B, in), member: (B,) long in [0, E) -> mean, logvar (B, D).
        """
        n = x.shape[0]
        order = torch.argsort(member, stable=True)  # (B,)
        sorted_member = member[order]
        counts = torch.bincount(member, minlength=self.ensemble_size)  # (E,)
        starts = torch.cumsum(counts, 0) - counts
        slot = torch.arange(n, device=x.device) - starts[sorted_member]  # rank within group
        width = max(int(counts.max()), 1)
        grouped = x.new_zeros(self.ensemble_size, width, x.shape[-1])
        grouped[sorted_member, slot] = x[order]
        pred = self.forward_members(grouped)  # (E, width, D)
        mean = pred.mean.new_empty(n, self.out_dim)
        logvar = pred.logvar.new_empty(n, self.out_dim)
        mean[order] = pred.mean[sorted_member, slot]
        logvar[order] = pred.logvar[sorted_member, slot]
        return EnsemblePrediction(mean, logvar)

    def _route_mean(self, x: Tensor) -> EnsemblePrediction:
        """Moment-matched mixture of all members: mean of means; variance = mean of
        variances + variance of means. x: (B, in) -> mean, logvar (B, D)."""
        pred = self.forward_members(x.unsqueeze(0).expand(self.ensemble_size, -1, -1))
        mean = pred.mean.mean(dim=0)
        var = pred.logvar.exp().mean(dim=0) + pred.mean.var(dim=0, unbiased=False)
        return EnsemblePrediction(mean, var.log())

    def _draw_members(
        self, n: int, device: torch.device, generator: torch.Generator | None
    ) -> Tensor:
        """(n,) member indices drawn uniformly from `generator` (default RNG if None)."""
        gen_device = generator.device if generator is not None else device
        member = torch.randint(self.ensemble_size, (n,), generator=generator, device=gen_device)
        return member.to(device)

    def step(
        self,
        q: Tensor,
        qd: Tensor,
        action: Tensor,
        generator: torch.Generator | None = None,
        sample: bool = False,
    ) -> State:
        """Next state one control step ahead. (..., nq), (..., nv), (..., nu) -> State.

        Uses the members as set by `self.propagation` (see module docstring) on the
        flattened batch. With `sample=True` Gaussian noise with the predicted variance is
        added to the (normalised) delta (under "mean": the moment-matched variance of the
        mixture); `generator` drives the ts1 draws and that noise.
        """
        x = self._normalize_inputs(self._inputs(q, qd, action))
        lead = x.shape[:-1]
        flat = x.reshape(-1, self.in_dim)  # (B, in)
        if self.propagation == "tsinf":
            pred = self._route_tsinf(flat)
        elif self.propagation == "ts1":
            member = self._draw_members(flat.shape[0], flat.device, generator)
            pred = self._route_by_member(flat, member)
        else:
            pred = self._route_mean(flat)
        delta = pred.mean  # (B, D) normalised
        if sample:
            gen_device = generator.device if generator is not None else delta.device
            noise = torch.randn(
                delta.shape, generator=generator, device=gen_device, dtype=delta.dtype
            ).to(delta.device)
            delta = delta + noise * torch.exp(0.5 * pred.logvar)
        delta = (delta * self.out_std + self.out_mean).reshape(*lead, self.out_dim)
        v_avg, d_qd = delta.to(q.dtype).split(self.nv, dim=-1)
        q_b = q.expand(*lead, -1)
        q_next = integrate_pos(self.layout, q_b, v_avg, self.control_dt)
        return State(q=q_next, qd=qd.expand(*lead, -1) + d_qd.to(qd.dtype))


@dataclass
class EnsembleConfig(ModelConfig):
    """``model=ensemble``: the PETS-style ensemble of MLPs."""

    ensemble_size: int = rule(low=1)
    hidden: int = rule(low=1)
    layers: int = rule(low=1)
    activation: str = MISSING
    propagation: str = rule(choices=PROPAGATIONS)


@register_model("ensemble", schema=EnsembleConfig)
def build_ensemble(cfg: DictConfig, system: System) -> GaussianEnsemble:
    return GaussianEnsemble(
        layout=system.layout,
        nu=system.nu,
        control_dt=system.control_dt,
        ensemble_size=cfg.ensemble_size,
        hidden=cfg.hidden,
        layers=cfg.layers,
        activation=cfg.activation,
        propagation=cfg.propagation,
    )
