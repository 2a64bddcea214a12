"""Replay buffers and transition data."""

from mbrl_delan.data.buffer import (
    BufferPlacement,
    NonFiniteDataError,
    add_transitions,
    all_transitions,
    buffer_state,
    check_finite,
    episode_transitions,
    load_buffer_state,
    make_replay_buffer,
    place_buffer,
    storage_device,
    transition_nbytes,
)

__all__ = [
    "BufferPlacement",
    "NonFiniteDataError",
    "add_transitions",
    "all_transitions",
    "buffer_state",
    "check_finite",
    "episode_transitions",
    "load_buffer_state",
    "make_replay_buffer",
    "place_buffer",
    "storage_device",
    "transition_nbytes",
]
