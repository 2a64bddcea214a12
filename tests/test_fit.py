"""fit_model: convergence, split, early stopping, best-weights restoring, divergence."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn

from mbrl_delan import keys
from mbrl_delan.data.buffer import add_transitions, make_replay_buffer
from mbrl_delan.models.base import LossOutput, WorldModel
from mbrl_delan.systems.system import State
from mbrl_delan.training import FitConfig, TrainingDivergedError, fit_model
from mbrl_delan.training.fit import _split
from mbrl_delan.training.loop import MBRLLoop


class LinearModel(WorldModel):
    """next_qd = qd @ A^T + action @ B^T, fitted by MSE; records what fit_model does to it."""

    def __init__(self, nv: int = 2, nu: int = 1):
        super().__init__()
        self.lin = nn.Linear(nv + nu, nv, bias=False)
        nn.init.zeros_(self.lin.weight)
        self.normalization_sizes: list[int] = []
        self.eval_weights: list[torch.Tensor] = []  # weights seen at each validation batch

    def step(self, q, qd, action, generator=None) -> State:
        return State(q, self.lin(torch.cat([qd, action], -1)))

    def fit_normalization(self, data: TensorDictBase) -> None:
        self.normalization_sizes.append(data.shape[0])

    def loss(self, batch: TensorDictBase) -> LossOutput:
        if not self.training:
            self.eval_weights.append(self.lin.weight.detach().clone())
        pred = self.step(batch[keys.Q], batch[keys.QD], batch[keys.ACTION]).qd
        err = (pred - batch[keys.NEXT_QD]) ** 2
        metrics = {"mse": float(err.detach().mean()), "max_err": float(err.detach().max())}
        return LossOutput(err.mean(), metrics)


def linear_data(n: int, true_w: torch.Tensor, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    qd = torch.randn(n, 2, generator=g)
    action = torch.randn(n, 1, generator=g)
    next_qd = torch.cat([qd, action], -1) @ true_w.T
    return TensorDict(
        {
            keys.Q: torch.zeros(n, 2),
            keys.QD: qd,
            keys.ACTION: action,
            keys.NEXT: {keys.Q: torch.zeros(n, 2), keys.QD: next_qd},
        },
        batch_size=[n],
    )


TRUE_W = torch.tensor([[0.9, 0.1, 0.5], [-0.2, 1.1, -0.3]])


def test_fit_recovers_true_weights():
    model = LinearModel()
    data = linear_data(400, TRUE_W)
    opt = torch.optim.Adam(model.parameters(), lr=0.05)
    cfg = FitConfig(batch_size=50, max_epochs=80, val_fraction=0.2, patience=20)
    report = fit_model(model, opt, data, cfg, torch.Generator().manual_seed(0))
    torch.testing.assert_close(model.lin.weight.detach(), TRUE_W, atol=1e-3, rtol=0)
    assert (report.n_train, report.n_val) == (320, 80)
    assert model.normalization_sizes == [320]
    assert not report.validated_on_train
    assert len(report.train_loss) == len(report.val_loss) == report.epochs_run
    assert report.val_loss[report.best_epoch] == report.best_val_loss == min(report.val_loss)
    assert report.best_val_loss < 1e-5
    assert set(report.metrics) == {"mse", "max_err"}
    assert math.isclose(report.metrics["mse"], report.best_val_loss, rel_tol=1e-4)
    assert model.training  # mode restored


def test_fit_is_reproducible_with_the_generator():
    weights = []
    for _ in range(2):
        torch.manual_seed(123)  # the init is zeros; the minibatch order comes from the generator
        model = LinearModel()
        opt = torch.optim.SGD(model.parameters(), lr=0.05)
        cfg = FitConfig(batch_size=16, max_epochs=3, val_fraction=0.25)
        gen = torch.Generator().manual_seed(7)
        report = fit_model(model, opt, linear_data(64, TRUE_W), cfg, gen)
        weights.append((model.lin.weight.detach().clone(), report.val_loss))
    torch.testing.assert_close(weights[0][0], weights[1][0], rtol=0, atol=0)
    assert weights[0][1] == weights[1][1]


def test_a_growing_buffer_keeps_each_transition_on_its_side_of_the_split():
    """The loop refits on a buffer that grows by appending: a transition that validated one
    fit must not train the next, and one that trained it must not validate the next (a new
    random split each refit scores the warm-started model on data it has just fitted)."""
    cfg = FitConfig(val_fraction=0.1)
    train_a, val_a, _ = _split(torch.arange(600), cfg)
    for n in (800, 2400):
        train_b, val_b, on_train = _split(torch.arange(n), cfg)
        assert not on_train
        assert set(val_a.tolist()) <= set(val_b.tolist())
        assert set(train_a.tolist()) <= set(train_b.tolist())
        assert set(train_b.tolist()).isdisjoint(val_b.tolist())
        assert sorted(train_b.tolist() + val_b.tolist()) == list(range(n))
        assert abs(len(val_b) - 0.1 * n) <= 2  # the asked share
        new_val = val_b[val_b >= 600]
        assert new_val.numel() > 0 and (new_val.diff() > 1).all()  # spread over new data too


class RecordingModel(LinearModel):
    """Records the running numbers (kept in q[:, 0]) of the samples it trains and validates on."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: dict[bool, set[int]] = {True: set(), False: set()}  # training -> ids

    def loss(self, batch: TensorDictBase) -> LossOutput:
        self.seen[self.training].update(batch[keys.Q][:, 0].long().tolist())
        return super().loss(batch)


def numbered_data(first: int, n: int) -> TensorDict:
    data = linear_data(n, TRUE_W)
    data[keys.Q][:, 0] = torch.arange(first, first + n, dtype=torch.float32)
    return data


def test_a_full_buffer_keeps_each_transition_on_its_side_of_the_split():
    """Once the buffer is full its oldest transitions drop out and every position shifts;
    the split follows each transition's running number (`first_index`), not its position:
    of the transitions two fits share, the same ones validate both."""
    cfg = FitConfig(batch_size=32, max_epochs=1, val_fraction=0.2)
    before, after = RecordingModel(), RecordingModel()
    for model, first in ((before, 0), (after, 200)):  # after: the oldest 200 have left
        opt = torch.optim.SGD(model.parameters(), lr=0.01)
        fit_model(
            model, opt, numbered_data(first, 600), cfg, torch.Generator().manual_seed(0), first
        )
    shared = set(range(200, 600))
    assert before.seen[False] & shared == after.seen[False] & shared
    assert before.seen[True] & shared == after.seen[True] & shared
    assert after.seen[False].isdisjoint(after.seen[True])
    assert after.seen[False] | after.seen[True] == set(range(200, 800))
    assert len(after.seen[False] & shared) == pytest.approx(0.2 * 400, abs=3)
    # by position instead, 0.2 of the shared transitions would change sides
    _, by_position, _ = _split(torch.arange(600), cfg)
    moved = {200 + int(i) for i in by_position} ^ (after.seen[False])
    assert len(moved & shared) > 50


def test_the_loop_numbers_its_transitions_past_a_full_buffer():
    """`MBRLLoop.fit` gives `fit_model` the running number of the buffer's oldest
    transition: the count that has left the full buffer."""
    buffer = make_replay_buffer(50)
    model = RecordingModel()
    system = SimpleNamespace(ctrl_low=torch.tensor([-1.0]), ctrl_high=torch.tensor([1.0]))
    loop = MBRLLoop(
        None, None, system, 20, model, torch.optim.SGD(model.parameters(), lr=0.01), None,
        buffer, FitConfig(batch_size=8, max_epochs=1, val_fraction=0.2), seed=0, error_horizon=1,
    )  # fmt: skip
    for first in (0, 20, 40):  # episodes of 20 transitions; the third wraps the buffer
        add_transitions(buffer, numbered_data(first, 20))
        loop.counters.env_steps += 20
    loop.fit()
    seen = model.seen[False] | model.seen[True]
    assert seen == set(range(10, 60))  # the 50 the buffer keeps
    _, held_out, _ = _split(torch.arange(10, 60), loop.fit_config)
    assert model.seen[False] == {10 + int(i) for i in held_out}


def test_first_index_must_not_be_negative():
    model = LinearModel()
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    with pytest.raises(ValueError, match="first_index"):
        fit_model(model, opt, linear_data(20, TRUE_W), FitConfig(), torch.Generator(), -1)


def test_too_few_samples_validates_on_train():
    model = LinearModel()
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    cfg = FitConfig(batch_size=4, max_epochs=2, val_fraction=0.1, min_val_size=2)
    report = fit_model(model, opt, linear_data(5, TRUE_W), cfg, torch.Generator().manual_seed(0))
    assert report.validated_on_train
    assert report.n_train == report.n_val == 5
    assert model.normalization_sizes == [5]


class ScalarModel(WorldModel):
    """One weight w. Training pulls w to 1; validation prefers w = 0.5.

    Starting at w = 0 with small SGD steps, the validation loss improves until w passes 0.5 and
    then gets worse, so early stopping must trigger and w ~ 0.5 must be restored.
    A NaN loss can be injected after ``nan_after`` training calls.
    """

    def __init__(self, nan_after: int | None = None, grad_inf_after: int | None = None):
        super().__init__()
        self.w = nn.Parameter(torch.zeros(()))
        self.nan_after = nan_after
        self.grad_inf_after = grad_inf_after
        self.train_calls = 0
        self.val_weights: list[float] = []

    def step(self, q, qd, action, generator=None) -> State:
        return State(q, qd * self.w)

    def loss(self, batch: TensorDictBase) -> LossOutput:
        ones = torch.ones(batch.shape[0])
        if not self.training:
            self.val_weights.append(float(self.w.detach()))
            loss = ((self.w * ones - 0.5) ** 2).mean()
            return LossOutput(loss, {"w": float(self.w.detach())})
        self.train_calls += 1
        loss = ((self.w * ones - 1.0) ** 2).mean()
        if self.nan_after is not None and self.train_calls > self.nan_after:
            loss = loss * float("nan")
        if self.grad_inf_after is not None and self.train_calls > self.grad_inf_after:
            loss = loss + torch.sqrt((self.w - self.w.detach()).abs())  # value +0, grad inf
        return LossOutput(loss, {"w": float(self.w.detach())})


def scalar_data(n: int = 40) -> TensorDict:
    return TensorDict({keys.Q: torch.zeros(n, 1)}, batch_size=[n])


def test_early_stopping_restores_best_weights():
    model = ScalarModel()
    opt = torch.optim.SGD(model.parameters(), lr=0.01)
    cfg = FitConfig(
        batch_size=10, max_epochs=200, val_fraction=0.25, patience=3, max_grad_norm=None
    )
    report = fit_model(model, opt, scalar_data(), cfg, torch.Generator().manual_seed(0))
    assert report.stopped_early
    assert report.epochs_run == report.best_epoch + 1 + 3
    assert report.epochs_run < 200
    assert min(report.val_loss) == report.best_val_loss
    assert report.val_loss[-1] > report.best_val_loss
    assert abs(float(model.w.detach()) - 0.5) < 0.03
    assert float(model.w.detach()) == report.metrics["w"]  # weights of the best epoch are back


def test_min_delta_and_no_patience():
    model = ScalarModel()
    opt = torch.optim.SGD(model.parameters(), lr=0.01)
    cfg = FitConfig(batch_size=10, max_epochs=5, val_fraction=0.25, patience=None)
    report = fit_model(model, opt, scalar_data(), cfg, torch.Generator().manual_seed(0))
    assert report.epochs_run == 5 and not report.stopped_early
    model = ScalarModel()
    opt = torch.optim.SGD(model.parameters(), lr=0.01)
    cfg = FitConfig(batch_size=10, max_epochs=50, val_fraction=0.25, patience=2, min_delta=10.0)
    report = fit_model(model, opt, scalar_data(), cfg, torch.Generator().manual_seed(0))
    assert report.best_epoch == 0 and report.epochs_run == 3 and report.stopped_early


def test_gradient_clipping_bounds_the_step():
    model = ScalarModel()
    opt = torch.optim.SGD(model.parameters(), lr=1.0)
    cfg = FitConfig(batch_size=40, max_epochs=1, val_fraction=0.0, max_grad_norm=0.1)
    fit_model(model, opt, scalar_data(), cfg, torch.Generator().manual_seed(0))
    assert abs(float(model.w.detach()) - 0.1) < 1e-6  # gradient -2 clipped to norm 0.1


def test_nan_loss_raises_and_restores_last_good_weights():
    model = ScalarModel(nan_after=10)  # 3 batches per epoch: NaN in epoch 3
    opt = torch.optim.Adam(model.parameters(), lr=0.01)
    cfg = FitConfig(batch_size=10, max_epochs=50, val_fraction=0.25, patience=5)
    with pytest.raises(TrainingDivergedError, match=r"epoch 3.*train_loss = nan") as info:
        fit_model(model, opt, scalar_data(), cfg, torch.Generator().manual_seed(0))
    err = info.value
    assert (err.epoch, err.metric) == (3, "train_loss")
    assert math.isnan(err.value)
    assert err.report.epochs_run == 3 and err.report.best_epoch == 2
    assert math.isfinite(float(model.w.detach()))
    assert float(model.w.detach()) == model.val_weights[-1]  # weights validated after epoch 2
    assert all(
        math.isfinite(float(v))
        for s in opt.state.values()
        for v in s.values()
        if torch.is_tensor(v)
    )


def test_nan_in_first_epoch_restores_initial_weights():
    model = ScalarModel(nan_after=1)
    opt = torch.optim.SGD(model.parameters(), lr=0.01)
    cfg = FitConfig(batch_size=10, max_epochs=5, val_fraction=0.25)
    with pytest.raises(TrainingDivergedError) as info:
        fit_model(model, opt, scalar_data(), cfg, torch.Generator().manual_seed(0))
    assert info.value.epoch == 0 and info.value.report.best_epoch == -1
    assert float(model.w.detach()) == 0.0


def test_infinite_gradient_raises_before_the_step():
    model = ScalarModel(grad_inf_after=4)
    opt = torch.optim.SGD(model.parameters(), lr=0.01)
    cfg = FitConfig(batch_size=10, max_epochs=5, val_fraction=0.25)
    with pytest.raises(TrainingDivergedError, match="grad_norm") as info:
        fit_model(model, opt, scalar_data(), cfg, torch.Generator().manual_seed(0))
    assert info.value.epoch == 1
    assert float(model.w.detach()) == model.val_weights[-1]


def test_empty_data_is_an_error():
    model = LinearModel()
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    with pytest.raises(ValueError, match="non-empty"):
        fit_model(model, opt, linear_data(0, TRUE_W), FitConfig(), torch.Generator())
