"""Replay buffer, rollout -> transitions, finiteness checks."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from mbrl_delan import keys
from mbrl_delan.data import (
    add_transitions,
    all_transitions,
    check_finite,
    episode_transitions,
    make_replay_buffer,
)


def fake_rollout(batch: int = 2, steps: int = 5, nq: int = 2, nu: int = 1) -> TensorDict:
    """A rollout shaped like TorchRL's ``env.rollout`` output: (B, T), time last.

    Values encode (row, step) so that flattening can be checked; row 0 ends an episode at
    step 2 (auto-reset), row 1 runs one episode.
    """
    row = torch.arange(batch, dtype=torch.float32).view(batch, 1, 1)
    t = torch.arange(steps, dtype=torch.float32).view(1, steps, 1)
    code = 100 * row + t  # (B, T, 1)
    done = torch.zeros(batch, steps, 1, dtype=torch.bool)
    done[0, 2] = True
    td = TensorDict(
        {
            keys.Q: code.expand(batch, steps, nq).clone(),
            keys.QD: -code.expand(batch, steps, nq).clone(),
            keys.ACTION: 0.5 * code.expand(batch, steps, nu).clone(),
            keys.DONE: torch.zeros(batch, steps, 1, dtype=torch.bool),
            "observation_extra": torch.zeros(batch, steps, 3),
            keys.NEXT: {
                keys.Q: (code + 1).expand(batch, steps, nq).clone(),
                keys.QD: -(code + 1).expand(batch, steps, nq).clone(),
                keys.REWARD: code.clone() / 10,
                keys.DONE: done,
                keys.TERMINATED: done.clone(),
                keys.TRUNCATED: torch.zeros_like(done),
            },
        },
        batch_size=[batch, steps],
        names=[None, "time"],
    )
    return td


def test_episode_transitions_flatten_and_index():
    rollout = fake_rollout()
    tr = episode_transitions(rollout, first_episode=3)
    assert tr.batch_size == torch.Size([10])
    assert torch.equal(tr[keys.Q], rollout[keys.Q].reshape(10, 2))
    assert torch.equal(tr[keys.NEXT_QD], rollout[keys.NEXT_QD].reshape(10, 2))
    assert torch.equal(tr[keys.ACTION], rollout[keys.ACTION].reshape(10, 1))
    assert torch.equal(tr[keys.REWARD], tr[keys.NEXT_REWARD])
    assert torch.equal(tr[keys.NEXT_REWARD], rollout[keys.NEXT_REWARD].reshape(10, 1))
    assert tr[keys.EPISODE].shape == (10, 1) and tr[keys.EPISODE].dtype == torch.int64
    assert tr[keys.EPISODE].squeeze(-1).tolist() == [3, 3, 3, 4, 4, 5, 5, 5, 5, 5]
    assert tr[keys.NEXT_DONE].dtype == torch.bool
    assert tr[keys.NEXT_DONE].squeeze(-1).tolist() == [False, False, True] + [False] * 7
    assert "observation_extra" not in tr.keys()


def test_episode_transitions_unbatched_and_missing_flags():
    rollout = fake_rollout(batch=1)[0]  # (T,), like an unbatched env
    del rollout[keys.NEXT_DONE]
    del rollout[keys.NEXT_TRUNCATED]
    tr = episode_transitions(rollout)
    assert tr.batch_size == torch.Size([5])
    assert tr[keys.EPISODE].squeeze(-1).tolist() == [0, 0, 0, 1, 1]
    assert torch.equal(tr[keys.NEXT_DONE], tr[keys.NEXT_TERMINATED])
    assert not tr[keys.NEXT_TRUNCATED].any()


def test_episode_transitions_missing_key():
    rollout = fake_rollout()
    del rollout[keys.NEXT_Q]
    with pytest.raises(KeyError, match="next"):
        episode_transitions(rollout)


def test_check_finite_names_key_and_index():
    tr = episode_transitions(fake_rollout())
    check_finite(tr, "clean data")
    tr[keys.NEXT_QD][4, 1] = float("nan")
    with pytest.raises(ValueError, match=r"'next', 'qd'.*\(4, 1\).*my rollout"):
        check_finite(tr, "my rollout")
    tr = episode_transitions(fake_rollout())
    tr[keys.REWARD][7, 0] = float("inf")
    with pytest.raises(ValueError, match=r"reward.*\(7, 0\)"):
        check_finite(tr, "x")


def test_add_transitions_rejects_nan_and_keeps_buffer_clean():
    buffer = make_replay_buffer(100)
    tr = episode_transitions(fake_rollout())
    add_transitions(buffer, tr)
    bad = tr.clone()
    bad[keys.ACTION][0, 0] = float("nan")
    with pytest.raises(ValueError, match="action"):
        add_transitions(buffer, bad)
    assert len(buffer) == 10


def test_all_transitions_in_order_after_wraparound():
    buffer = make_replay_buffer(8)
    tr = episode_transitions(fake_rollout())  # 10 transitions into 8 slots
    buffer.extend(tr[:6])
    data = all_transitions(buffer)
    assert "index" not in data.keys()
    assert torch.equal(data[keys.Q], tr[keys.Q][:6])
    buffer.extend(tr[6:])
    data = all_transitions(buffer)
    assert data.batch_size == torch.Size([8])
    assert torch.equal(data[keys.Q], tr[keys.Q][2:])  # oldest first
    with pytest.raises(ValueError, match="empty"):
        all_transitions(make_replay_buffer(4))


@pytest.mark.filterwarnings("ignore:Loading the storage on an uninitialized")
@pytest.mark.parametrize("memmap", [False, True])
def test_buffer_state_round_trip(tmp_path, memmap):
    def make(sub):
        return make_replay_buffer(8, memmap_dir=str(tmp_path / sub) if memmap else None)

    buffer = make("a")
    tr = episode_transitions(fake_rollout())
    buffer.extend(tr[:7])
    buffer.extend(tr[7:])  # wraps: cursor = 2
    path = tmp_path / "buffer.pt"
    torch.save(buffer.state_dict(), path)

    restored = make("b")
    restored.load_state_dict(torch.load(path, weights_only=True))
    assert len(restored) == len(buffer) == 8
    assert restored.writer.state_dict() == buffer.writer.state_dict()
    assert (all_transitions(restored) == all_transitions(buffer)).all()
    # the write cursor carried over: the next write overwrites the same slot in both
    extra = tr[:1].clone()
    extra[keys.Q] += 1000
    buffer.extend(extra)
    restored.extend(extra)
    assert (all_transitions(restored) == all_transitions(buffer)).all()
    assert all_transitions(restored)[keys.Q][-1, 0] == 1000
