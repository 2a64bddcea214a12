"""Multi-step (rollout) training: windows of consecutive transitions and DeLaN's K-step loss."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from mbrl_delan import keys
from mbrl_delan.models.delan import DeLaN
from mbrl_delan.models.delan_ensemble import DeLaNEnsemble
from mbrl_delan.models.ensemble import GaussianEnsemble
from mbrl_delan.models.structure import Structure
from mbrl_delan.systems.system import load_system
from mbrl_delan.training import FitConfig, fit_model
from mbrl_delan.training.fit import transition_windows


def chain(starts: list[float], lengths: list[int]) -> TensorDict:
    """Episodes of a 1-D counter: q runs start, start + 1, ...; next q = q + 1."""
    q = torch.cat(
        [s + torch.arange(n, dtype=torch.float32) for s, n in zip(starts, lengths, strict=True)]
    )
    q = q.unsqueeze(-1)  # (N, 1)
    n = q.shape[0]
    return TensorDict(
        {
            keys.Q: q,
            keys.QD: torch.zeros(n, 1),
            keys.ACTION: torch.zeros(n, 1),
            keys.NEXT: {keys.Q: q + 1, keys.QD: torch.zeros(n, 1)},
        },
        batch_size=[n],
    )


def test_windows_stay_inside_episodes() -> None:
    # two episodes of 4 and 3 steps: windows of 3 start at 0, 1 (first) and 4 (second)
    data = chain([0.0, 100.0], [4, 3])
    windows = transition_windows(data, 3)
    assert windows.batch_size == torch.Size([3, 3])
    assert windows[keys.Q][:, :, 0].tolist() == [[0, 1, 2], [1, 2, 3], [100, 101, 102]]
    # every window's states follow each other
    torch.testing.assert_close(windows[keys.NEXT_Q][:, :-1], windows[keys.Q][:, 1:])
    assert transition_windows(data, 1).batch_size == torch.Size([7, 1])
    assert transition_windows(data, 5).shape[0] == 0  # no episode has 5 steps


def test_windows_need_the_exact_next_state() -> None:
    data = chain([0.0], [5])
    data[keys.NEXT_QD][2] = 1e-6  # transition 2's next state is not transition 3's state
    starts = transition_windows(data, 2)[keys.Q][:, 0, 0].tolist()
    assert starts == [0, 1, 3]


def pendulum_episode(model: DeLaN, steps: int, seed: int) -> TensorDict:
    """An episode rolled out by `model` itself: its own data, so its rollout loss is 0."""
    g = torch.Generator().manual_seed(seed)
    q, qd = torch.randn(1, 1, generator=g), torch.randn(1, 1, generator=g)
    actions = torch.rand(steps, 1, 1, generator=g) * 2 - 1
    rows = []
    with torch.no_grad():
        for a in actions:
            nxt = model.step(q, qd, a)
            rows.append((q, qd, a, nxt.q, nxt.qd))
            q, qd = nxt.q, nxt.qd
    cols = [torch.cat(c) for c in zip(*rows, strict=True)]
    return TensorDict(
        {
            keys.Q: cols[0],
            keys.QD: cols[1],
            keys.ACTION: cols[2],
            keys.NEXT: {keys.Q: cols[3], keys.QD: cols[4]},
        },
        batch_size=[steps],
    )


def delan(seed: int) -> DeLaN:
    system = load_system("pendulum")
    torch.manual_seed(seed)
    return DeLaN(system.layout, system.actuation.float(), system.control_dt, Structure(hidden=16))


def test_rollout_loss_is_the_mean_of_the_compounded_errors() -> None:
    truth, model = delan(0), delan(1)
    episode = pendulum_episode(truth, 6, seed=2)
    windows = transition_windows(episode, 3)  # (4, 3)
    out = model.loss(windows)
    # by hand: step the model from each window's first state on the window's actions
    q, qd = windows[keys.Q][:, 0], windows[keys.QD][:, 0]
    per_step = []
    for k in range(3):
        pred = model.step(q, qd, windows[keys.ACTION][:, k])
        e_q = (pred.q - windows[keys.NEXT_Q][:, k]) / model.q_scale
        e_qd = (pred.qd - windows[keys.NEXT_QD][:, k]) / model.qd_scale
        per_step.append(e_q.pow(2).mean() + e_qd.pow(2).mean())
        q, qd = pred.q, pred.qd
    torch.testing.assert_close(out.loss, torch.stack(per_step).mean())
    assert out.metrics["rollout_mse"] == pytest.approx(float(out.loss.detach()))
    # the first step of the rollout is the one-step loss of the first transitions
    one_step = model.loss(windows[:, 0])
    assert out.metrics["forward_mse"] == pytest.approx(one_step.metrics["forward_mse"], rel=1e-5)
    # a model scored on its own rollouts has zero loss at every step
    assert float(truth.loss(windows).loss.detach()) < 1e-10
    # and the compounded error is larger than the one-step error for the wrong model
    assert float(per_step[-1]) > float(per_step[0])


def test_fit_with_rollout_steps_trains_on_windows() -> None:
    truth, model = delan(0), delan(1)
    data = torch.cat([pendulum_episode(truth, 20, seed=s) for s in range(4)])
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    normalized_on: list[int] = []
    fit_normalization = model.fit_normalization
    model.fit_normalization = lambda d: (normalized_on.append(d.shape[0]), fit_normalization(d))
    cfg = FitConfig(batch_size=16, max_epochs=3, patience=None, rollout_steps=4)
    report = fit_model(model, optimizer, data, cfg, torch.Generator().manual_seed(0))
    # first a one-step fit on the 80 transitions, which alone sets the normalisation
    assert report.warmup is not None
    assert report.warmup.n_train + report.warmup.n_val == 80
    assert normalized_on == [report.warmup.n_train]
    # then windows of 4, none across the 4 episodes
    assert report.n_train + report.n_val == 4 * (20 - 4 + 1)
    assert "rollout_mse" in report.metrics
    assert report.val_loss[-1] < report.val_loss[0]


def test_rollout_steps_are_checked() -> None:
    with pytest.raises(ValueError, match="rollout_steps must be >= 1"):
        FitConfig(rollout_steps=0)
    system = load_system("pendulum")
    ensemble = GaussianEnsemble(system.layout, system.nu, system.control_dt, ensemble_size=2)
    optimizer = torch.optim.Adam(ensemble.parameters())
    data = pendulum_episode(delan(0), 8, seed=0)
    cfg = FitConfig(rollout_steps=2)
    with pytest.raises(ValueError, match="GaussianEnsemble trains on single ones"):
        fit_model(ensemble, optimizer, data, cfg, torch.Generator().manual_seed(0))
    short = chain([0.0, 10.0], [2, 2])
    model = delan(0)
    with pytest.raises(ValueError, match="no run of 3 consecutive"):
        fit_model(
            model,
            torch.optim.Adam(model.parameters()),
            short,
            FitConfig(rollout_steps=3),
            torch.Generator().manual_seed(0),
        )


def test_delan_ensemble_rollout_loss_is_the_sum_of_its_members() -> None:
    system = load_system("pendulum")
    torch.manual_seed(0)
    ensemble = DeLaNEnsemble(
        system.layout,
        system.actuation.float(),
        system.control_dt,
        ensemble_size=3,
        structure=Structure(hidden=16),
    )
    assert ensemble.trains_on_windows
    windows = transition_windows(pendulum_episode(delan(0), 8, seed=1), 3)
    ensemble.eval()  # no bootstrap: every member sees every window
    total = ensemble.loss(windows).loss
    members = [ensemble.member(e).loss(windows).loss for e in range(3)]
    torch.testing.assert_close(total, torch.stack(members).sum())


def test_loss_both_on_windows_adds_the_inverse_term_of_the_first_transitions() -> None:
    truth, model = delan(0), delan(1)
    windows = transition_windows(pendulum_episode(truth, 6, seed=3), 3)
    model.loss_kind = "both"
    out = model.loss(windows)
    forward = model._rollout_mse(windows).mean()
    inverse = model.loss(windows[:, 0]).metrics["inverse_mse"]
    assert float(out.loss.detach()) == pytest.approx(float(forward.detach()) + inverse, rel=1e-5)
    model.loss_kind = "inverse"
    assert not model.trains_on_windows
    with pytest.raises(ValueError, match="need loss 'forward' or 'both'"):
        model.loss(windows)
