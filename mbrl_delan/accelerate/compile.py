"""`torch.compile` as the project uses it: the planning rollouts' static-shape graphs, the
fits' forward-and-backward graphs, and a compiled step for code that steps a model itself."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn

from mbrl_delan.models.base import LossOutput, WorldModel
from mbrl_delan.systems.system import State


def compile_dynamics(fn: Callable[..., Any]) -> Callable[..., Any]:
    """`torch.compile` for the model's hot path: static shapes (one specialised graph per
    input shape: a graph with a dynamic batch size ran up to 10x slower on CPU), a C++
    wrapper (less Python per call), and no guards on module attributes (weights updated in
    place are read at each call; inputs of another dtype or device compile another graph).
    The C++ kernels may contract a multiply and an add into one fused multiply-add (one
    rounding instead of two: the softplus polynomial and the layer products are chains of
    them).

    Each call compiles graphs of its own: Dynamo keeps its graphs on the code object it
    enters, and without module guards a graph traced for one model would run for another
    whose method shares that code (another model's structure, or its float settings such as
    `substeps` baked in). `fn` is entered through a wrapper with a code object of its own."""
    options = {
        "cpp_wrapper": True,
        "cpp.enable_floating_point_contract_flag": "fast",
        "guard_filter_fn": torch.compiler.skip_guard_on_all_nn_modules_unsafe,
    }

    def entry(*args: Any, **kwargs: Any) -> Any:
        return fn(*args, **kwargs)

    entry.__code__ = entry.__code__.replace()  # a copy: this call's own graph cache
    return torch.compile(entry, dynamic=False, options=options)


class FitGraph:
    """A training function through `torch.compile` (forward and backward graphs) for the
    first batch shape met under autograd. Other shapes (an epoch's last, partial batch) and
    calls without autograd run eagerly, so a fit compiles once."""

    def __init__(self, fn: Callable[..., Any]) -> None:
        self.fn = fn
        self.graph: Callable[..., Any] | None = None
        self.shape: torch.Size | None = None

    def __call__(self, q: Tensor, *args: Any, **kwargs: Any) -> Any:
        """`fn(q, ...)`, compiled when `q` has the batch shape of the first call under autograd."""
        if not torch.is_grad_enabled():
            return self.fn(q, *args, **kwargs)
        if self.graph is None:
            self.graph, self.shape = torch.compile(self.fn, dynamic=False), q.shape
        chosen = self.graph if q.shape == self.shape else self.fn
        return chosen(q, *args, **kwargs)


def compile_fit(model: nn.Module) -> None:
    """Route the fit of `model` through a `FitGraph`: its per-batch training function (the
    method named by its ``fit_kernel``, first argument the batch's q) is replaced on this
    instance by the compiled one. Call it where the fit is set up, after the model is on its
    device and dtype (another device or dtype compiles another graph)."""
    name = getattr(model, "fit_kernel", None)
    if name is None:
        raise ValueError(f"{type(model).__name__} has no fit_kernel to compile")
    setattr(model, name, FitGraph(getattr(model, name)))


class CompiledLoop:
    """`compile_dynamics(fn)` for a whole-horizon rollout loop, which notes when the compiler
    gave an input shape up (its recompile limit) and `fn` ran as Python (`ran_eagerly`).
    `compiler` replaces `compile_dynamics` (tests: the identity stands for a compiler that
    gave up)."""

    def __init__(
        self,
        fn: Callable[..., Tensor],
        compiler: Callable[[Callable[..., Tensor]], Callable[..., Tensor]] = compile_dynamics,
    ) -> None:
        self.ran_eagerly = False

        def traced(*args: Tensor) -> Tensor:
            if not torch.compiler.is_compiling():
                self.ran_eagerly = True
            return fn(*args)

        self._compiled = compiler(traced)

    def __call__(self, *args: Tensor) -> Tensor:
        return self._compiled(*args)


class CompiledStep(WorldModel):
    """`model` with its `step` compiled (`compile_dynamics`, one graph per input shape) for
    calls without autograd: for code that steps a world model itself, such as TorchRL's
    planners over `ModelEnv`. Build it after the model is on its device and dtype."""

    def __init__(self, model: WorldModel) -> None:
        super().__init__()
        self.model = model
        self.deterministic, self.layout = model.deterministic, model.layout
        self._compiled = compile_dynamics(lambda q, qd, a: model.step(q, qd, a))

    def step(
        self, q: Tensor, qd: Tensor, action: Tensor, generator: torch.Generator | None = None
    ) -> State:
        if torch.is_grad_enabled() or not self.model.deterministic:
            return self.model.step(q, qd, action, generator)
        return self._compiled(q, qd, action)

    def loss(self, batch: TensorDictBase) -> LossOutput:
        return self.model.loss(batch)
