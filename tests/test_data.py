"""Replay buffer, rollout -> transitions, finiteness checks."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from mbrl_delan import keys
from mbrl_delan.data import (
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
from mbrl_delan.data.buffer import state_to_device
from mbrl_delan.envs.real import make_real_env

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


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
    torch.save(buffer_state(buffer), path)

    restored = make("b")
    load_buffer_state(restored, torch.load(path, weights_only=True))
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


@pytest.mark.parametrize("env_name", ["pendulum", "humanoid_stand"])
def test_transition_nbytes_is_what_a_full_buffer_stores(env_name: str) -> None:
    env = make_real_env(env_name, seed=0)
    rollout = env.rollout(6, break_when_any_done=False)
    transitions = episode_transitions(rollout)
    buffer = make_replay_buffer(capacity=6)
    add_transitions(buffer, transitions)
    stored = buffer.storage.get(torch.arange(6))  # every slot, with the buffer's index key
    assert transition_nbytes(env) * 6 == stored.bytes()


def test_place_buffer_auto_fits_on_the_model_device_or_falls_back_to_the_host() -> None:
    cuda, cpu, mib = torch.device("cuda"), torch.device("cpu"), 2**20
    fits = place_buffer("auto", cuda, 40 * mib, free_bytes=100 * mib, max_fraction=0.5)
    assert fits.device == cuda and "fits in 0.5 of 100 MiB" in fits.reason
    too_big = place_buffer("auto", cuda, 60 * mib, free_bytes=100 * mib, max_fraction=0.5)
    assert too_big.device == cpu and "60.0 MiB at capacity exceeds" in too_big.reason
    assert place_buffer("auto", cuda, 1, None, 0.5).device == cpu  # free memory unknown
    assert place_buffer("auto", cpu, 1, 10**12, 0.5).device == cpu
    forced = place_buffer("cuda:1", cpu, 10**12, None, 0.5)
    assert forced.device == torch.device("cuda:1") and "as configured" in forced.reason


def test_state_to_device_moves_every_tensor_and_keeps_the_rest() -> None:
    state = {"_storage": {"q": torch.ones(2), "inner": [torch.zeros(1), 3]}, "_len": 2}
    moved = state_to_device(state, torch.device("meta"))
    assert moved["_storage"]["q"].is_meta and moved["_storage"]["inner"][0].is_meta
    assert moved["_storage"]["inner"][1] == 3 and moved["_len"] == 2
    assert not state["_storage"]["q"].is_meta  # the input is not changed


def test_torchrl_state_dict_of_older_checkpoints_still_loads() -> None:
    buffer = make_replay_buffer(8)
    add_transitions(buffer, episode_transitions(fake_rollout()))
    restored = make_replay_buffer(8)  # a TensorDict's state keeps its batch sizes as metadata
    load_buffer_state(restored, state_to_device(buffer.state_dict(), torch.device("cpu")))
    assert (all_transitions(restored) == all_transitions(buffer)).all()
    assert restored.writer.state_dict() == buffer.writer.state_dict()


@pytest.mark.parametrize("memmap", [False, True])
def test_buffer_state_grows_with_the_data_not_the_capacity(tmp_path, memmap) -> None:
    def saved_bytes(buffer) -> int:
        path = tmp_path / "state.pt"
        torch.save(buffer_state(buffer), path)
        return path.stat().st_size

    memmap_dir = str(tmp_path / "mm") if memmap else None
    small = make_replay_buffer(10, memmap_dir=memmap_dir)
    large = make_replay_buffer(100_000, memmap_dir=str(tmp_path / "mm2") if memmap else None)
    tr = episode_transitions(fake_rollout())  # 10 transitions, about 100 bytes each
    for buffer in (small, large):
        add_transitions(buffer, tr)
    assert saved_bytes(large) == pytest.approx(saved_bytes(small), abs=64)
    assert saved_bytes(large) < 20_000  # all 10^5 slots would take over 10 MB


def test_load_buffer_state_refuses_a_full_buffer_or_too_small_capacity() -> None:
    buffer = make_replay_buffer(20)
    add_transitions(buffer, episode_transitions(fake_rollout()))
    state = buffer_state(buffer)
    with pytest.raises(ValueError, match="needs an empty buffer, this one holds 10"):
        load_buffer_state(buffer, state)
    with pytest.raises(ValueError, match="holds 10 transitions, more than capacity 4"):
        load_buffer_state(make_replay_buffer(4), state)


@needs_cuda
def test_buffer_on_cuda_takes_host_transitions_and_round_trips_across_devices(tmp_path) -> None:
    tr = episode_transitions(fake_rollout())  # (10,) on the host
    on_gpu = make_replay_buffer(8, device="cuda")
    add_transitions(on_gpu, tr)  # wraps: cursor 2
    data = all_transitions(on_gpu)
    assert storage_device(on_gpu).type == "cuda" and data[keys.Q].is_cuda
    assert torch.equal(data[keys.Q].cpu(), tr[keys.Q][2:])
    for name, state in (("ours", buffer_state(on_gpu)), ("torchrl", on_gpu.state_dict())):
        path = tmp_path / f"{name}.pt"
        torch.save(state, path)
        for device in ("cpu", "cuda"):  # a checkpoint loads on the host (map_location="cpu")
            restored = make_replay_buffer(8, device=device)
            load_buffer_state(restored, torch.load(path, map_location="cpu", weights_only=True))
            again = all_transitions(restored)
            assert again[keys.Q].device.type == device
            assert torch.equal(again[keys.Q].cpu(), tr[keys.Q][2:])
            add_transitions(restored, tr[:1])  # the cursor carried over; the next write lands
            assert torch.equal(all_transitions(restored)[keys.Q][-1].cpu(), tr[keys.Q][0])
