"""Replay buffers and transition data."""

from mbrl_delan.data.buffer import (
    NonFiniteDataError,
    add_transitions,
    all_transitions,
    check_finite,
    episode_transitions,
    make_replay_buffer,
)

__all__ = [
    "NonFiniteDataError",
    "add_transitions",
    "all_transitions",
    "check_finite",
    "episode_transitions",
    "make_replay_buffer",
]
