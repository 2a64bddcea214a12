"""An ensemble of Deep Lagrangian Networks, vectorised over stacked member parameters.

E `DeLaN` members with independent initialisations keep their parameters and floating-point
buffers stacked along a leading member dim (E, ...) in `self.members`, a module tree shaped
like one `DeLaN` (so `state_dict` keys read `members.dynamics.field.trunk.head.weight`, of
shape (E, ...)). A DeLaN "skeleton" on the meta device, kept out of the module's
registration, supplies the code: `torch.func.functional_call` runs it on one member's
tensors and `torch.vmap` maps that over the member dim. Whatever parameters and buffers
`DeLaN` has are carried along; integer buffers (index tables of the joint layout) are the
same for every member and are shared, not stacked.

Propagation of a flat batch of particles through `step` (as `GaussianEnsemble`):
- ``"tsinf"``: element b always uses member b % E,
- ``"ts1"``: every element draws a fresh member on every call (from `generator`),
- ``"mean"``: every member steps every element; q is averaged in velocity space around the
  input q (`differentiate_pos` / `integrate_pos`, so quaternions stay unit), qd plainly.

Training (`loss`): member e's own `DeLaN.loss` on its own bootstrap resample of the batch
(in training mode, with `bootstrap=True`), summed over members, so each member's gradient
is the one it would get alone. The members run one after the other there: `DeLaN.loss`
reports float metrics, which `vmap` cannot carry.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any

import torch
from omegaconf import MISSING, DictConfig
from tensordict import TensorDictBase
from torch import Tensor, nn
from torch.func import functional_call, stack_module_state

from mbrl_delan import keys
from mbrl_delan.models.base import LossOutput, WorldModel
from mbrl_delan.models.delan import DeLaN, LagrangianTerms
from mbrl_delan.models.delan_config import delan_arguments
from mbrl_delan.models.structure import LagrangianConfig
from mbrl_delan.registry import register_model
from mbrl_delan.rules import rule
from mbrl_delan.systems.posarith import differentiate_pos, integrate_pos
from mbrl_delan.systems.system import JointLayout, State, System

log = logging.getLogger(__name__)

PROPAGATIONS = ("ts1", "tsinf", "mean")

MemberFn = Callable[..., Any]  # (member DeLaN, *tensors) -> tensor or tuple of tensors


class _Call(nn.Module):
    """Runs `fn(model, *args)`, so `functional_call` can run any method of `model`."""

    def __init__(self, model: DeLaN) -> None:
        super().__init__()
        self.model = model

    def forward(self, fn: MemberFn, *args: Any) -> Any:
        return fn(self.model, *args)


def _register(root: nn.Module, name: str, tensor: Tensor, persistent: bool) -> None:
    """Register a parameter or buffer under a dotted `name`, creating plain submodules."""
    *path, leaf = name.split(".")
    owner = root
    for part in path:
        if not hasattr(owner, part):
            owner.add_module(part, nn.Module())
        owner = getattr(owner, part)
    if isinstance(tensor, nn.Parameter):
        owner.register_parameter(leaf, tensor)
    else:
        owner.register_buffer(leaf, tensor, persistent=persistent)


def _replace(root: nn.Module, name: str, tensor: Tensor) -> None:
    """Put `tensor` in place of the parameter or buffer called `name` (persistence kept)."""
    *path, leaf = name.split(".")
    owner = root.get_submodule(".".join(path))
    setattr(owner, leaf, tensor)


def _flatten_terms(terms: LagrangianTerms) -> tuple[Tensor, ...]:
    return tuple(getattr(terms, f.name) for f in fields(terms))


def _tsinf_groups(batch: int, ensemble_size: int, device: torch.device) -> tuple[Tensor, ...]:
    """Element b -> member b % E, slot b // E.

    Returns idx (E, W) flat indices of the elements each member steps (padding slots point
    at element 0, a valid state), and member, slot (B,) to read the results back.
    """
    e = ensemble_size
    width = max(-(-batch // e), 1)  # ceil(B / E)
    idx = torch.arange(width, device=device) * e + torch.arange(e, device=device).unsqueeze(1)
    idx = torch.where(idx < batch, idx, torch.zeros_like(idx))  # (E, W)
    flat = torch.arange(batch, device=device)
    return idx, flat % e, flat // e


def _member_groups(member: Tensor, ensemble_size: int) -> tuple[Tensor, ...]:
    """Group elements by their member: member (B,) long in [0, E).

    Returns idx (E, W) (padding slots point at element 0), member (B,), slot (B,).
    """
    n, device = member.shape[0], member.device
    order = torch.argsort(member, stable=True)  # (B,)
    counts = torch.bincount(member, minlength=ensemble_size)  # (E,)
    starts = torch.cumsum(counts, 0) - counts
    slot = torch.empty_like(member)
    slot[order] = torch.arange(n, device=device) - starts[member[order]]
    width = max(int(counts.max()), 1) if n else 1
    idx = torch.zeros(ensemble_size, width, dtype=torch.long, device=device)
    idx[member, slot] = torch.arange(n, device=device)
    return idx, member, slot


class DeLaNEnsemble(WorldModel):
    """E DeLaN members evaluated together by `vmap` over their stacked parameters."""

    def __init__(
        self,
        layout: JointLayout,
        actuation: Tensor,
        control_dt: float,
        ensemble_size: int = 5,
        propagation: str = "tsinf",
        bootstrap: bool = True,
        seed: int | None = None,
        **delan_options: Any,
    ) -> None:
        """Build E independently initialised members (torch's default RNG).

        Args:
            layout: joint layout, as `DeLaN`'s.
            actuation: B (nv, nu), as `DeLaN`'s.
            control_dt: control period (s), as `DeLaN`'s.
            ensemble_size: number of members E (>= 1).
            propagation: "tsinf", "ts1" or "mean" (how `step` uses the members).
            bootstrap: in training mode each member trains on its own resample (with
                replacement) of every batch; in eval mode (validation) on the whole batch.
            seed: seeds `self.generator` (bootstrap draws); None uses torch's default RNG.
            delan_options: any other keyword argument of `DeLaN` (``structure``,
                ``stepping``, ...), the same for every member.
        """
        super().__init__()
        if ensemble_size < 1:
            raise ValueError(f"ensemble_size must be >= 1, got {ensemble_size}")
        self.layout, self.control_dt = layout, float(control_dt)
        self.ensemble_size = ensemble_size
        self.propagation = propagation  # validated by the setter
        self.bootstrap = bootstrap
        self.generator: torch.Generator | None = (
            None if seed is None else torch.Generator().manual_seed(seed)
        )
        members = [
            DeLaN(layout, actuation, control_dt, **delan_options) for _ in range(ensemble_size)
        ]
        self.members = self._stacked_store(members)
        # code only: its tensors are never used (every call passes the members' tensors)
        self._call = (_Call(copy.deepcopy(members[0]).to("meta")),)

    # ------------------------------------------------------------------ set-up

    @staticmethod
    def _stacked_store(members: Sequence[DeLaN]) -> nn.Module:
        """A module tree shaped like a DeLaN holding every member's tensors stacked (E, ...).

        Parameters and floating buffers are stacked; other buffers (integer index tables)
        are shared, taken from member 0. Buffer persistence follows the DeLaN's.
        """
        params, buffers = stack_module_state(list(members))
        persistent = set(members[0].state_dict().keys())
        store = nn.Module()
        for name, value in params.items():
            _register(store, name, nn.Parameter(value.detach()), persistent=True)
        for name, value in buffers.items():
            shared = value if value.is_floating_point() else value[0]
            _register(store, name, shared.clone(), persistent=name in persistent)
        return store

    @property
    def propagation(self) -> str:
        return self._propagation

    @propagation.setter
    def propagation(self, value: str) -> None:
        if value not in PROPAGATIONS:
            raise ValueError(f"unknown propagation {value!r}; known: {PROPAGATIONS}")
        self._propagation = value

    def _tensors(self) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """(stacked, shared): every tensor of `self.members` by the skeleton's key."""
        stacked: dict[str, Tensor] = {}
        shared: dict[str, Tensor] = {}
        for name, t in self.members.named_parameters():
            stacked["model." + name] = t
        for name, t in self.members.named_buffers():
            (stacked if t.is_floating_point() else shared)["model." + name] = t
        return stacked, shared

    @torch.no_grad()
    def load_members(self, members: Sequence[DeLaN]) -> None:
        """Copy the parameters and buffers of E DeLaN modules (same architecture) in."""
        if len(members) != self.ensemble_size:
            raise ValueError(f"need {self.ensemble_size} members, got {len(members)}")
        own = dict(self.members.named_parameters()) | dict(self.members.named_buffers())
        for e, member in enumerate(members):
            theirs = dict(member.named_parameters()) | dict(member.named_buffers())
            if set(theirs) != set(own):
                raise ValueError(f"member {e} does not have this ensemble's tensors")
            for name, t in own.items():
                if t.is_floating_point():
                    t[e].copy_(theirs[name])
                elif e == 0:
                    t.copy_(theirs[name])

    def member(self, index: int) -> DeLaN:
        """A standalone DeLaN holding copies of member `index`'s parameters and buffers."""
        template = self._call[0].model
        for name, t in self.members.named_buffers():
            # a vmapped call can leave its batched value in a buffer that two paths of the
            # module tree share (the features): put a meta tensor back before copying
            if t.is_floating_point():
                _replace(template, name, torch.empty_like(t[index], device="meta"))
        module = copy.deepcopy(template)
        for name, t in self.members.named_parameters():
            value = nn.Parameter(t[index].detach().clone(), requires_grad=t.requires_grad)
            _replace(module, name, value)
        for name, t in self.members.named_buffers():
            _replace(module, name, (t[index] if t.is_floating_point() else t).clone())
        return module

    # ------------------------------------------------------------- evaluation

    def _vmap(self, fn: MemberFn, *args: Tensor) -> Any:
        """Member e runs fn(member e, *(a[e] for a in args)); args are (E, ...)."""
        stacked, shared = self._tensors()
        caller = self._call[0]

        def one(tensors: dict[str, Tensor], *inputs: Tensor) -> Any:
            return functional_call(caller, {**tensors, **shared}, (fn, *inputs))

        return torch.vmap(one)(stacked, *args)

    def _run_member(self, index: int, fn: MemberFn, *args: Any) -> Any:
        """fn(member `index`, *args) on that member's slice of the stacked tensors."""
        stacked, shared = self._tensors()
        tensors = {name: t[index] for name, t in stacked.items()}
        return functional_call(self._call[0], {**tensors, **shared}, (fn, *args))

    def _every_member(self, *inputs: Tensor) -> tuple[Tensor, ...]:
        """Broadcast inputs (..., k) to one lead shape and give each member a view (E, ..., k)."""
        lead = torch.broadcast_shapes(*(x.shape[:-1] for x in inputs))
        e = self.ensemble_size
        return tuple(x.expand(*lead, x.shape[-1]).expand(e, *lead, x.shape[-1]) for x in inputs)

    def terms(self, q: Tensor, qd: Tensor) -> LagrangianTerms:
        """Every member's terms at (q, qd): (..., nq), (..., nv) -> fields with a leading E.

        E.g. `mass_matrix` (E, ..., n, n), `gravity` (E, ..., n), `kinetic_energy` (E, ...).
        """
        out = self._vmap(
            lambda m, q_, qd_: _flatten_terms(m.terms(q_, qd_)), *self._every_member(q, qd)
        )
        return LagrangianTerms(*out)

    def mass_matrix(self, q: Tensor) -> Tensor:
        """Every member's M(q): (..., nq) -> (E, ..., nv, nv), symmetric positive definite."""
        qd = q.new_zeros(q.shape[:-1] + (self.layout.nv,))
        return self.terms(q, qd).mass_matrix

    def acceleration(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """Every member's forward dynamics: (..., nq), (..., nv), (..., nu) -> (E, ..., nv)."""
        return self._vmap(lambda m, *x: m.acceleration(*x), *self._every_member(q, qd, action))

    def step_members(self, q: Tensor, qd: Tensor, action: Tensor) -> State:
        """Every member steps every element: (..., ·) -> State((E, ..., nq), (E, ..., nv))."""
        q_e, qd_e = self._vmap(_step_tuple, *self._every_member(q, qd, action))
        return State(q=q_e, qd=qd_e)

    def _step_routed(self, q: Tensor, qd: Tensor, action: Tensor, groups: tuple) -> State:
        """Element b through its member only. q, qd, action: (B, ·); groups as `_tsinf_groups`."""
        idx, member, slot = groups  # (E, W), (B,), (B,)
        q_e, qd_e = self._vmap(_step_tuple, q[idx], qd[idx], action[idx])  # (E, W, ·)
        return State(q=q_e[member, slot], qd=qd_e[member, slot])

    def _mean_step(self, q: Tensor, qd: Tensor, action: Tensor) -> State:
        """Average of the members' next states; q averaged in velocity space around q."""
        nxt = self.step_members(q, qd, action)  # (E, B, nq), (E, B, nv)
        base = q.expand_as(nxt.q[0])
        v = differentiate_pos(self.layout, base.expand_as(nxt.q), nxt.q, 1.0)  # (E, B, nv)
        return State(q=integrate_pos(self.layout, base, v.mean(dim=0), 1.0), qd=nxt.qd.mean(dim=0))

    def _draw_members(
        self, n: int, device: torch.device, generator: torch.Generator | None
    ) -> Tensor:
        """(n,) member indices uniform in [0, E) from `generator` (default RNG if None)."""
        gen_device = generator.device if generator is not None else device
        draw = torch.randint(self.ensemble_size, (n,), generator=generator, device=gen_device)
        return draw.to(device)

    def step(
        self, q: Tensor, qd: Tensor, action: Tensor, generator: torch.Generator | None = None
    ) -> State:
        """Next state one control step ahead. (..., nq), (..., nv), (..., nu) -> State.

        The flattened batch goes through the members as set by `self.propagation` (module
        docstring); under "tsinf" element b uses member b % E for any batch size (with B a
        multiple of E every member steps equally many elements). `generator` drives the ts1
        draws.
        """
        lead = torch.broadcast_shapes(q.shape[:-1], qd.shape[:-1], action.shape[:-1])
        q_f, qd_f, a_f = (
            x.expand(*lead, x.shape[-1]).reshape(-1, x.shape[-1]) for x in (q, qd, action)
        )  # (B, ·)
        if self.propagation == "mean":
            nxt = self._mean_step(q_f, qd_f, a_f)
        elif self.propagation == "tsinf":
            groups = _tsinf_groups(q_f.shape[0], self.ensemble_size, q_f.device)
            nxt = self._step_routed(q_f, qd_f, a_f, groups)
        else:
            member = self._draw_members(q_f.shape[0], q_f.device, generator)
            nxt = self._step_routed(q_f, qd_f, a_f, _member_groups(member, self.ensemble_size))
        return State(q=nxt.q.reshape(*lead, -1), qd=nxt.qd.reshape(*lead, -1))

    # ----------------------------------------------------------------- training

    def _bootstrap_indices(self, n: int, device: torch.device) -> Tensor | None:
        """(E, n) rows per member (with replacement), or None for the whole batch."""
        if not (self.bootstrap and self.training):
            return None
        gen = self.generator
        gen_device = gen.device if gen is not None else torch.device("cpu")
        idx = torch.randint(n, (self.ensemble_size, n), generator=gen, device=gen_device)
        return idx.to(device)

    @property
    def trains_on_windows(self) -> bool:  # type: ignore[override]
        return self._call[0].model.trains_on_windows

    def loss(self, batch: TensorDictBase) -> LossOutput:
        """Sum over members of member e's `DeLaN.loss` on its bootstrap resample of the
        transitions (B,), or of the windows (B, K) of consecutive transitions.

        Metrics: every metric of the members averaged over members, with "member_loss" the
        mean member loss and "loss" the summed total (the value optimised).
        """
        flat = batch if batch.batch_dims == 2 else batch.reshape(-1)
        idx = self._bootstrap_indices(flat.shape[0], flat.get(keys.Q).device)
        outputs = [
            self._run_member(e, lambda m, b: m.loss(b), flat if idx is None else flat[idx[e]])
            for e in range(self.ensemble_size)
        ]
        total = torch.stack([out.loss for out in outputs]).sum()
        names = {name for out in outputs for name in out.metrics}
        metrics = {
            name: sum(out.metrics.get(name, 0.0) for out in outputs) / len(outputs)
            for name in sorted(names)
        }
        metrics["member_loss"] = metrics.pop("loss", float(total.detach()) / len(outputs))
        metrics["loss"] = float(total.detach())
        return LossOutput(loss=total, metrics=metrics)

    @torch.no_grad()
    def fit_normalization(self, data: TensorDictBase) -> None:
        """Member 0's `DeLaN.fit_normalization` on `data`, its buffers copied to every member.

        The statistics depend on the data only, so every member gets the same ones.
        """
        reference = self.member(0)
        reference.fit_normalization(data)
        fitted = dict(reference.named_buffers())
        for name, buf in self.members.named_buffers():
            buf.copy_(fitted[name].to(buf.dtype).expand_as(buf))
        log.debug("DeLaN ensemble normalisation fitted on %d transitions", data.numel())


def _step_tuple(model: DeLaN, q: Tensor, qd: Tensor, action: Tensor) -> tuple[Tensor, Tensor]:
    """One member's step as a tuple (vmap returns tensors and tuples, not `State`)."""
    nxt = model.step(q, qd, action)
    return nxt.q, nxt.qd


@dataclass
class DeLaNEnsembleConfig(LagrangianConfig):
    """``model=delan_ensemble``: the members' DeLaN settings and the ensemble's."""

    ensemble_size: int = rule(low=1)
    propagation: str = rule(choices=PROPAGATIONS)
    bootstrap: bool = MISSING


@register_model("delan_ensemble", schema=DeLaNEnsembleConfig)
def build_delan_ensemble(cfg: DictConfig, system: System) -> DeLaNEnsemble:
    return DeLaNEnsemble(
        **delan_arguments(cfg, system),
        ensemble_size=cfg.ensemble_size,
        propagation=cfg.propagation,
        bootstrap=cfg.bootstrap,
    )
