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

import copy
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import EnvBase

from mbrl_delan import keys

log = logging.getLogger(__name__)

# Key that TensorDictReplayBuffer writes into stored samples; not part of a transition.
_BUFFER_INDEX_KEY = "index"
_TIME_DIM_NAME = "time"
# TensorDictReplayBuffer.state_dict(): the entry that holds the stored transitions
_STORAGE_STATE_KEY = "_storage"
_FILLED_KEY = "filled"  # `buffer_state`: the filled slots' transitions

_STATE_KEYS = (keys.Q, keys.QD, keys.ACTION, keys.NEXT_Q, keys.NEXT_QD, keys.NEXT_REWARD)


def make_replay_buffer(
    capacity: int, device: str | torch.device = "cpu", memmap_dir: str | None = None
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


def storage_device(buffer: TensorDictReplayBuffer) -> torch.device:
    """Where the buffer keeps its transitions: the host for a memmap (on disk, mapped into
    host memory), else its tensor storage's device."""
    storage = buffer.storage
    if isinstance(storage, LazyMemmapStorage):
        return torch.device("cpu")
    return torch.device(storage.device)


def transition_nbytes(env: EnvBase) -> int:
    """Bytes one of `env`'s transitions takes in a replay buffer: every key of a transition
    (from the env's own specs and dtypes) and the buffer's int64 index."""
    example = episode_transitions(env.fake_tensordict().unsqueeze(-1))  # (B,)
    index = torch.empty((), dtype=torch.int64).element_size()
    return example.bytes() // example.shape[0] + index


@dataclass(frozen=True)
class BufferPlacement:
    """Where the replay buffer keeps its data, and why."""

    device: torch.device
    reason: str


MiB = 2**20


def place_buffer(
    requested: str,
    model_device: torch.device,
    full_bytes: int,
    free_bytes: int | None,
    max_fraction: float,
) -> BufferPlacement:
    """The buffer's device: `requested`, or with "auto" the model's device when the full
    buffer (`full_bytes` at capacity) takes at most `max_fraction` of that device's
    `free_bytes` (None: unknown), else the host.

    The host always holds the env's transitions first; a buffer on the model's device saves
    the copy of all the data to the device at every refit.
    """
    if requested != "auto":
        return BufferPlacement(torch.device(requested), "as configured (buffer.device)")
    host = torch.device("cpu")
    if model_device.type == "cpu":
        return BufferPlacement(host, "the model is on the CPU")
    if free_bytes is None:
        return BufferPlacement(host, f"the free memory of {model_device} is unknown")
    need, free = full_bytes / MiB, free_bytes / MiB
    fits = full_bytes <= max_fraction * free_bytes
    verdict = "fits in" if fits else "exceeds"
    reason = f"{need:.1f} MiB at capacity {verdict} {max_fraction:g} of {free:.0f} MiB free"
    return BufferPlacement(model_device if fits else host, f"{reason} on {model_device}")


def free_device_bytes(device: torch.device) -> int | None:
    """Free memory on a CUDA device (bytes); None for other devices."""
    if device.type != "cuda":
        return None
    free, _total = torch.cuda.mem_get_info(device)
    return int(free)


def state_to_device(state: Any, device: torch.device) -> Any:
    """A buffer's `state_dict()` with every tensor on `device` (nested dicts, lists kept)."""
    if isinstance(state, torch.Tensor):
        return state.to(device)
    if isinstance(state, Mapping):
        moved = copy.copy(state)  # keeps a TensorDict state's `_metadata` (batch sizes)
        for key, value in state.items():
            moved[key] = state_to_device(value, device)
        return moved
    if isinstance(state, list | tuple):
        return type(state)(state_to_device(v, device) for v in state)
    return state


def buffer_state(buffer: TensorDictReplayBuffer) -> dict[str, Any]:
    """What a checkpoint keeps of `buffer`: its filled slots only, in slot order, on the
    host, and its writer's cursor. Its size grows with the transitions collected, not with
    the capacity (TorchRL's `state_dict()` holds every slot, filled or not, memmap included).
    Plain tensors and containers, so it loads with `torch.load(weights_only=True)`."""
    n = len(buffer)
    filled: dict[str, Any] = {}
    if n:
        slots = buffer.storage.get(torch.arange(n, device=storage_device(buffer)))
        filled = slots.exclude(_BUFFER_INDEX_KEY).to("cpu").clone().to_dict()
    return {_FILLED_KEY: filled, "size": n, "writer": buffer.writer.state_dict()}


def load_buffer_state(buffer: TensorDictReplayBuffer, state: dict[str, Any]) -> None:
    """Restore an empty `buffer` from `buffer_state` (or from TorchRL's `state_dict()`, which
    older checkpoints hold), onto the buffer's own device whichever device saved it."""
    device = storage_device(buffer)
    if _FILLED_KEY not in state:  # TorchRL's state_dict: move only the stored transitions
        stored = state_to_device(state[_STORAGE_STATE_KEY], device)
        buffer.load_state_dict({**state, _STORAGE_STATE_KEY: stored})
        return
    if len(buffer):
        raise ValueError(f"load_buffer_state needs an empty buffer, this one holds {len(buffer)}")
    size, capacity = int(state["size"]), buffer.storage.max_size
    if size > capacity:
        raise ValueError(
            f"the saved buffer holds {size} transitions, more than capacity {capacity}"
        )
    if size:
        buffer.extend(TensorDict(state[_FILLED_KEY], batch_size=[size]).to(device))
    buffer.writer.load_state_dict(state["writer"])


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
    buffer.extend(transitions.to(storage_device(buffer)))


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
    idx = torch.arange(n, device=storage_device(buffer))
    if n == storage.max_size:
        idx = (idx + cursor) % n
    data = storage.get(idx)
    if _BUFFER_INDEX_KEY in data.keys():
        data = data.exclude(_BUFFER_INDEX_KEY)
    return data.clone()
