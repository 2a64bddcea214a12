"""Rollouts of a batch in shares on worker threads, each share on one intra-op thread."""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor

import torch
from torch import Tensor


class RolloutThreads:
    """Worker threads that each roll out a share of a batch with one intra-op thread.

    On a CPU of a few cores a batch split this way runs its shares side by side, each share's
    kernels on one core with its data in that core's cache, where the whole batch on all the
    intra-op threads synchronises the cores and moves data between them at every kernel. (On
    the 2-core CI machines, the pendulum's loop at N 1024: 8.4-9.5 ms in shares, 9.0-9.7 ms as
    one batch, and 12.6-13.3 ms in the processes where the host made the cores slow to
    share data.) The compiled rollout loop and a compiled step release the GIL while they
    run (the humanoid tree's step: 60 calls of 32 states in 156 to 183 ms on two workers,
    239 to 302 ms on one; a development measurement). The caller's own intra-op threads
    should stay idle meanwhile (`ModelObjectiveFactory.planning_threads`).
    """

    def __init__(self, threads: int) -> None:
        if threads < 2:
            raise ValueError(f"RolloutThreads needs threads >= 2, got {threads}")
        self.threads = threads
        self._pool: ThreadPoolExecutor | None = None
        self._seen: set[tuple[int, ...]] = set()  # share shapes already run (compiled)

    def map(self, fn: Callable[[Tensor], Tensor], shares: Sequence[Tensor]) -> list[Tensor]:
        """[fn(share) for share in shares], the shares in the workers under the caller's grad
        and inference modes. The first share of a new shape runs alone (it compiles)."""
        pool = self._start()
        modes = (torch.is_grad_enabled(), torch.is_inference_mode_enabled())
        results: list[Future[Tensor] | Tensor] = []
        for share in shares:
            future = pool.submit(_call_in_modes, fn, share, *modes)
            shape = tuple(share.shape)
            if shape not in self._seen:
                results.append(future.result())
                self._seen.add(shape)
            else:
                results.append(future)
        return [r.result() if isinstance(r, Future) else r for r in results]

    def _start(self) -> ThreadPoolExecutor:
        """The pool, its workers started with one intra-op thread each. `torch.set_num_threads`
        in a worker also sets the default of threads started later, so the caller's is put
        back once all the workers run."""
        if self._pool is None:
            threads = torch.get_num_threads()
            pool = ThreadPoolExecutor(self.threads, "rollout", initializer=_one_intra_op_thread)
            ready = threading.Barrier(self.threads)
            for started in [pool.submit(ready.wait) for _ in range(self.threads)]:
                started.result()
            torch.set_num_threads(threads)
            self._pool = pool
        return self._pool

    def close(self) -> None:
        """Stop the workers (a later `map` starts new ones)."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None


def _one_intra_op_thread() -> None:
    """A worker's intra-op threads set to 1. torch sets a thread's count from its default at
    the thread's first parallel call, unless that has happened: read it first, so a later
    call does not raise it back to the caller's count."""
    torch.get_num_threads()
    torch.set_num_threads(1)


def _call_in_modes(
    fn: Callable[[Tensor], Tensor], x: Tensor, grad: bool, inference: bool
) -> Tensor:
    with torch.inference_mode(inference), torch.set_grad_enabled(grad):
        return fn(x)
