"""The world-model contract shared by DeLaN and the ensemble."""

from __future__ import annotations

import abc
import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import torch
from omegaconf import MISSING
from tensordict import TensorDictBase
from torch import Tensor, nn

from mbrl_delan.rules import rule
from mbrl_delan.systems.system import JointLayout, State


@dataclass
class ModelConfig:
    """What every world model's config group has (the optimiser and the planning objective
    read it); each model's schema extends it, a user's too. particles: rollouts per action
    sequence (a deterministic model: 1)."""

    name: str = MISSING
    lr: float = rule(low=0, above=True)
    weight_decay: float = rule(0.0, low=0)
    particles: int = rule(1, low=1)


@dataclass
class LossOutput:
    """A training loss and the scalar metrics that explain it."""

    loss: Tensor  # () differentiable
    metrics: dict[str, float] = field(default_factory=dict)


class WorldModel(nn.Module, abc.ABC):
    """Predicts the state one control step ahead.

    `step` is batched over any leading dims. For ensembles, particle b of a flat batch is
    propagated by member b % E under TSinf; callers lay particles out so that works.

    `trains_on_windows`: `loss` also takes windows (B, K) of K consecutive transitions and
    scores a K-step rollout from each window's first state (`FitConfig.rollout_steps`).

    `identifies`: the model fits itself from data (`identify`: a white-box model's system
    identification) instead of by gradient steps on `loss`. `objective_factory`: a model
    with a planning objective of its own (MuJoCo rollouts) returns it; the default None has
    the planner roll out `step` in torch (`objectives.model.model_objective_factory`).
    """

    trains_on_windows: bool = False
    deterministic: bool = False  # `step` draws no random numbers (ignores its generator)
    identifies: bool = False  # fitted by `identify`, not by `loss`
    layout: JointLayout | None = None  # the system's joints; models of a MuJoCo system set it

    @property
    def loops_compile(self) -> bool:
        """Whether a compiled `torch.while_loop` over its steps is tried: not with free or ball
        joints. Their loop compiles, but on `humanoid_stand`'s tree it planned at 66 ms per
        control step against 68 ms with one compiled call per step (one thread, one other job
        on the 2-core host), and its first compile took about 30 minutes on the loaded host:
        a humanoid's time is in its step, not between steps."""
        return self.layout is None or self.layout.only_scalar_joints

    @abc.abstractmethod
    def step(
        self, q: Tensor, qd: Tensor, action: Tensor, generator: torch.Generator | None = None
    ) -> State:
        """(..., nq), (..., nv), (..., nu) -> State((..., nq), (..., nv))."""

    @abc.abstractmethod
    def loss(self, batch: TensorDictBase) -> LossOutput:
        """Training loss on a batch (B,) with keys q, qd, action, ("next", "q"),
        ("next", "qd"); windows (B, K) where `trains_on_windows`."""

    def fit_normalization(self, data: TensorDictBase) -> None:  # noqa: B027
        """Set input/output statistics from the training data (before each refit)."""

    def identify(self, data: TensorDictBase, generator: torch.Generator) -> Any:
        """Fit the model to transitions (N,) itself (models with `identifies`); returns a
        `training.fit.FitReport`."""
        raise NotImplementedError(f"{type(self).__name__} is fitted by its loss, not identified")

    def rigid_body(self, q: Tensor) -> RigidBody | None:
        """Its mass matrix, potential force and actuation at configurations q (..., nq), for
        the rigid-body truth figures (`training.fidelity.rigid_body_metrics`); None: a model
        without them (a black box)."""
        return None

    def joint_stiffness(self, q: Tensor) -> Tensor | None:
        """Each DoF's spring stiffness (nv,), the median over configurations q (..., nq) of
        the potential force's slope along the DoF less gravity's, where the model can tell its
        springs from gravity; None where it cannot (a DeLaN's V holds both)."""
        return None

    def objective_factory(self, task: Any, discount: float = 1.0) -> Any | None:
        """Its own planning objective factory ((q0, qd0) -> objective over (N, H, nu)
        actions), or None: the planner rolls out `step` (`model_objective_factory`)."""
        return None


@dataclass(frozen=True)
class RigidBody:
    """A model's rigid body at configurations (...): M (..., nv, nv), the generalized force
    that holds the body still against gravity and the joints' springs (..., nv), and the
    actuation B (nv, nu)."""

    mass_matrix: Tensor
    potential_force: Tensor
    actuation: Tensor


@dataclass(frozen=True)
class Placement:
    """Device and dtype a world model computes in."""

    device: torch.device
    dtype: torch.dtype


def model_placement(
    model: nn.Module,
    fallback_device: torch.device | str = "cpu",
    fallback_dtype: torch.dtype = torch.float64,
) -> Placement:
    """Device and dtype of the model's first floating parameter or buffer, else the fallback."""
    tensors = [*model.parameters(), *model.buffers()]
    first = next((t for t in tensors if t.is_floating_point()), None)
    if first is None:
        return Placement(torch.device(fallback_device), fallback_dtype)
    return Placement(first.device, first.dtype)


@contextlib.contextmanager
def eval_mode(model: nn.Module) -> Iterator[None]:
    """Run the model in eval mode and restore its previous mode afterwards."""
    was_training = model.training
    model.eval()
    try:
        yield
    finally:
        model.train(was_training)
