"""Whole rollouts replayed from CUDA graphs (`accel.cuda_graph=true`).

On a GPU, one planning call of a small world model is thousands of short kernels: at batch
1024 each runs for a few microseconds, so launching them from Python (eager) or from a
compiled graph's wrapper costs more than the arithmetic. A CUDA graph records the launches of
one call once and replays them as one, so a call costs its kernels alone.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import torch
from torch import Tensor

WARMUP_CALLS = 2  # eager (or compiling) calls on a side stream before a capture
Signature = tuple[tuple[torch.Size, torch.dtype, torch.device], ...]  # per input


@dataclass
class _Captured:
    graph: torch.cuda.CUDAGraph
    inputs: tuple[Tensor, ...]  # the static tensors the graph reads
    output: Tensor  # the static tensor it writes


class GraphedCalls:
    """`fn(*inputs) -> Tensor` replayed from a CUDA graph, one graph per input signature
    (shapes, dtypes, device).

    `fn` must be a function of its tensor inputs and of state updated in place, such as a
    module's parameters and buffers (optimiser steps and `load_state_dict` copy into them): a
    graph reads the memory it was captured with. `watched()` yields the tensors `fn` reads
    besides its inputs; when any of their addresses changes (a module moved with `.to()`),
    every graph is dropped and captured again. `generators` are CUDA generators `fn` draws
    from: each replay advances them, so replays draw fresh numbers as eager calls do.

    A signature's first call runs `fn` `WARMUP_CALLS` times on a side stream (a compiled `fn`
    compiles there), then captures it; later calls copy their inputs into the static ones,
    replay, and return a copy of the output.
    """

    def __init__(
        self,
        fn: Callable[..., Tensor],
        watched: Callable[[], Iterable[Tensor]],
        generators: Iterable[torch.Generator] = (),
    ) -> None:
        self.fn = fn
        self.watched = watched
        self.generators = tuple(g for g in generators if g.device.type == "cuda")
        self._graphs: dict[Signature, _Captured] = {}
        self._addresses: tuple[int, ...] = ()

    def __call__(self, *inputs: Tensor) -> Tensor:
        if not all(t.is_cuda for t in inputs):
            raise ValueError("CUDA graphs need every input on a CUDA device")
        addresses = tuple(t.data_ptr() for t in self.watched())
        if addresses != self._addresses:
            self._graphs.clear()  # their memory was freed or moved
            self._addresses = addresses
        key: Signature = tuple((t.shape, t.dtype, t.device) for t in inputs)
        captured = self._graphs.get(key)
        if captured is None:
            captured = self._graphs[key] = self._capture(inputs)
        for static, value in zip(captured.inputs, inputs, strict=True):
            static.copy_(value)
        captured.graph.replay()
        return captured.output.clone()

    @property
    def captured(self) -> int:
        """How many graphs are held (one per input signature met since the last drop)."""
        return len(self._graphs)

    def _capture(self, inputs: tuple[Tensor, ...]) -> _Captured:
        static = tuple(t.clone() for t in inputs)
        device = static[0].device
        side = torch.cuda.Stream(device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            for _ in range(WARMUP_CALLS):
                self.fn(*static)
        torch.cuda.current_stream(device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        for generator in self.generators:
            graph.register_generator_state(generator)
        with torch.cuda.graph(graph):
            output = self.fn(*static)
        return _Captured(graph, static, output)
