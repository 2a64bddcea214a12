"""Replay buffer factory and the conversion of TorchRL rollouts into transitions.

A transition is one control step, laid out flat (batch shape ``[N]``) with the keys

- ``q`` (N, nq), ``qd`` (N, nv), ``action`` (N, nu)
- ``reward`` (N, 1): the reward received for this transition (a copy of ``("next", "reward")``)
- ``("next", "q")``, ``("next", "qd")``, ``("next", "reward")``
- ``("next", "done")``, ``("next", "terminated")``, ``("next", "truncated")`` (N, 1) bool
- ``episode`` (N, 1) int64: index of the episode the transition belongs to.

Every transition has the same key set, so a buffer can be extended with transitions from any
number of rollouts.
"""

from __future__ import annotations

import logging

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer

from mbrl_delan import keys

log = logging.getLogger(__name__)

# Key that TensorDictReplayBuffer writes into stored samples; not part of a transition.
_BUFFER_INDEX_KEY = "index"
_TIME_DIM_NAME = "time"

_STATE_KEYS = (keys.Q, keys.QD, keys.ACTION, keys.NEXT_Q, keys.NEXT_QD, keys.NEXT_REWARD)


def make_replay_buffer(
    capacity: int, device: str = "cpu", memmap_dir: str | None = None
) -> TensorDictReplayBuffer:
    """A FIFO replay buffer of transitions.

    Args:
        capacity: number of transitions kept; the oldest are overwritten when full.
        device: device the stored (in-memory) data, or sampled (memmap) data, live on.
        memmap_dir: when given, the storage is a ``LazyMemmapStorage`` in that folder
            (data on disk, for buffers larger than memory); otherwise a ``LazyTensorStorage``.
    """
    if capacity <= 0:
        raise ValueError(f"replay buffer capacity must be positive, got {capacity}")
    if memmap_dir is None:
        storage = LazyTensorStorage(capacity, device=device)
    else:
        storage = LazyMemmapStorage(capacity, scratch_dir=memmap_dir, device=device)
    return TensorDictReplayBuffer(storage=storage)


def _time_dim(rollout_td: TensorDictBase) -> int:
    """Index of the time dim: TorchRL names it "time" and puts it last."""
    if rollout_td.batch_dims == 0:
        raise ValueError("a rollout needs at least a time dim, got batch_size []")
    names = rollout_td.names
    last = rollout_td.batch_dims - 1
    if _TIME_DIM_NAME in names and names.index(_TIME_DIM_NAME) != last:
        raise ValueError(
            f"the time dim must be the last batch dim (TorchRL's layout), got names {names}"
        )
    return last


def _next_flag(rollout_td: TensorDictBase, key: tuple[str, str]) -> torch.Tensor | None:
    flag = rollout_td.get(key, None)
    return None if flag is None else flag.to(torch.bool)


def _done_flags(rollout_td: TensorDictBase) -> dict[tuple[str, str], torch.Tensor]:
    """("next", done/terminated/truncated), (*B, T, 1) bool; missing flags are derived."""
    shape = (*rollout_td.batch_size, 1)
    false = torch.zeros(shape, dtype=torch.bool, device=rollout_td.get(keys.Q).device)
    terminated = _next_flag(rollout_td, keys.NEXT_TERMINATED)
    truncated = _next_flag(rollout_td, keys.NEXT_TRUNCATED)
    done = _next_flag(rollout_td, keys.NEXT_DONE)
    terminated = false if terminated is None else terminated.reshape(shape)
    truncated = false if truncated is None else truncated.reshape(shape)
    done = (terminated | truncated) if done is None else done.reshape(shape)
    return {keys.NEXT_DONE: done, keys.NEXT_TERMINATED: terminated, keys.NEXT_TRUNCATED: truncated}


def _episode_index(done: torch.Tensor, first_episode: int) -> torch.Tensor:
    """Episode number per step from done flags.

    ``done`` is (*B, T, 1) bool; each batch row is its own trajectory and a new episode starts
    after every done step (auto-reset). Rows are numbered one after another in row-major order.
    Returns (*B, T, 1) int64.
    """
    d = done.squeeze(-1).to(torch.int64)
    rows = d.reshape(-1, d.shape[-1])  # (R, T)
    local = torch.cumsum(rows, dim=-1) - rows  # episodes finished before step t
    per_row = local[:, -1] + 1  # episodes touched by each row
    offsets = torch.cumsum(per_row, dim=0) - per_row
    episode = local + offsets.unsqueeze(-1) + first_episode
    return episode.reshape(done.shape)


def episode_transitions(rollout_td: TensorDictBase, first_episode: int = 0) -> TensorDict:
    """Flatten a TorchRL ``env.rollout`` output into episode-indexed transitions.

    Args:
        rollout_td: batch shape (*B, T) with time last (TorchRL's layout), holding at least
            q, qd, action and ("next", q/qd/reward); done flags are optional (derived when
            missing). Several episodes may share a row (auto-reset after a done step).
        first_episode: number given to the first episode, so that a caller can keep a running
            episode count across rollouts (``int(out["episode"].max()) + 1`` is the next one).

    Returns:
        TensorDict of batch shape (N,) with N = prod(B) * T and the keys listed in the module
        docstring; transitions of one episode are contiguous and in time order.
    """
    _time_dim(rollout_td)
    missing = [k for k in _STATE_KEYS if rollout_td.get(k, None) is None]
    if missing:
        raise KeyError(f"rollout is missing keys {missing}; it has {list(rollout_td.keys(True))}")
    flags = _done_flags(rollout_td)
    out = TensorDict(
        {k: rollout_td.get(k) for k in _STATE_KEYS},
        batch_size=rollout_td.batch_size,
        device=rollout_td.device,
    )
    out.set(keys.REWARD, rollout_td.get(keys.NEXT_REWARD).clone())
    for k, v in flags.items():
        out.set(k, v)
    out.set(keys.EPISODE, _episode_index(flags[keys.NEXT_DONE], first_episode))
    return out.reshape(-1).clone()


class NonFiniteDataError(ValueError):
    """Data holds NaN or inf; the message names the key, the first bad index and the source."""


def check_finite(td: TensorDictBase, where: str) -> None:
    """Raise ``NonFiniteDataError`` naming the key and first bad index on any NaN/inf entry.

    Args:
        td: any TensorDict; non-floating entries are ignored.
        where: what the data are (e.g. "rollout of iteration 3"), quoted in the message.
    """
    for key in td.keys(include_nested=True, leaves_only=True):
        value = td.get(key)
        if not (torch.is_floating_point(value) or torch.is_complex(value)):
            continue
        bad = ~torch.isfinite(value)
        if not bool(bad.any()):
            continue
        first = tuple(int(i) for i in torch.nonzero(bad)[0])
        raise NonFiniteDataError(
            f"non-finite value {value[first].item()} in key {key!r} at index {first} "
            f"({int(bad.sum())} of {value.numel()} entries bad) in {where}"
        )


def add_transitions(buffer: TensorDictReplayBuffer, transitions: TensorDictBase) -> None:
    """Check ``transitions`` (N,) for NaN/inf, then append them to ``buffer``."""
    check_finite(transitions, "transitions added to the replay buffer")
    buffer.extend(transitions)


def all_transitions(buffer: TensorDictReplayBuffer) -> TensorDict:
    """The filled part of the buffer's storage, oldest first, as an in-memory copy.

    Returns a TensorDict of batch shape (len(buffer),) without the buffer's bookkeeping
    ``index`` key. Raises ``ValueError`` when the buffer is empty.
    """
    n = len(buffer)
    if n == 0:
        raise ValueError("the replay buffer is empty: collect data before fitting")
    storage = buffer.storage
    cursor = int(buffer.writer.state_dict().get("_cursor", 0)) % n
    idx = (torch.arange(n) + cursor) % n if n == storage.max_size else torch.arange(n)
    data = storage.get(idx)
    if _BUFFER_INDEX_KEY in data.keys():
        data = data.exclude(_BUFFER_INDEX_KEY)
    return data.clone()
