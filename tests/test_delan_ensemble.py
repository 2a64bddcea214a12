"""The DeLaN ensemble: the vectorised members are exactly E independent DeLaN modules.

Reference results come from a plain Python loop over standalone `DeLaN` modules loaded with
the same weights; the ensemble must reproduce them (float64, 1e-10) under every propagation,
in its loss and in its gradients.
"""

from __future__ import annotations

import io

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.conf.builders import build_model
from mbrl_delan.conf.checks import CONFIG_DIR, ConfigError, validate_train_config
from mbrl_delan.data.synthetic import dynamics_dataset
from mbrl_delan.envs import make_env_parts
from mbrl_delan.models.delan import DeLaN, Stepping
from mbrl_delan.models.delan_ensemble import DeLaNEnsemble
from mbrl_delan.models.structure import Structure
from mbrl_delan.objectives.model import model_objective_factory
from mbrl_delan.systems.posarith import differentiate_pos, integrate_pos
from mbrl_delan.systems.system import FREE, HINGE, SLIDE, JointLayout
from mbrl_delan.training.fit import FitConfig, fit_model

CONFIGS = CONFIG_DIR
# a slide, an unlimited hinge and a floating body: every feature kind and a quaternion
MIXED = JointLayout(
    types=(SLIDE, HINGE, FREE), qpos_adr=(0, 1, 2), dof_adr=(0, 1, 2), limited=(False, False, False)
)
NQ, NV, NU = MIXED.nq, MIXED.nv, 2
E = 3
ARCH = dict(structure=Structure(hidden=16, layers=2))  # small: fast


def arch(**options: bool) -> dict:
    """`ARCH` with more structure options."""
    return ARCH | {"structure": Structure(hidden=16, layers=2, **options)}


TOL = dict(atol=1e-10, rtol=1e-10)


@pytest.fixture(autouse=True)
def float64():
    """Exact comparisons: float64 by default for the test, then restored."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


def actuation() -> Tensor:
    B = torch.zeros(NV, NU)
    B[0, 0] = B[1, 1] = 1.0
    return B


def states(batch: int, seed: int = 1) -> tuple[Tensor, Tensor, Tensor]:
    """Random q (unit root quaternion), qd, action: (batch, NQ), (batch, NV), (batch, NU)."""
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(batch, NQ, generator=g)
    q[:, 5:9] = q[:, 5:9] / q[:, 5:9].norm(dim=-1, keepdim=True)
    return q, 2.0 * torch.randn(batch, NV, generator=g), torch.randn(batch, NU, generator=g)


def transitions(n: int = 48, seed: int = 2) -> TensorDict:
    """Made-up transitions (q, qd, action) -> (q', qd') with the root's quaternion unit."""
    q, qd, action = states(n, seed)
    q_next = integrate_pos(MIXED, q, qd, 0.02)
    qd_next = qd + 0.02 * torch.randn(n, NV, generator=torch.Generator().manual_seed(seed + 1))
    return TensorDict(
        {keys.Q: q, keys.QD: qd, keys.ACTION: action, keys.NEXT_Q: q_next, keys.NEXT_QD: qd_next},
        batch_size=[n],
    )


def reference_members(loss: str = "both", **options) -> list[DeLaN]:
    """E standalone DeLaN modules with independent random weights and fitted statistics."""
    data = transitions()
    members = []
    for seed in range(E):
        torch.manual_seed(100 + seed)
        m = DeLaN(MIXED, actuation(), 0.02, stepping=Stepping(loss=loss), **arch(**options))
        with torch.no_grad():  # biases and friction off their defaults too (|qdd| < 1e3)
            for p in m.parameters():
                p.add_(0.1 * torch.randn_like(p))
        m.fit_normalization(data)
        members.append(m)
    return members


def ensemble(members: list[DeLaN] | None = None, **kw) -> DeLaNEnsemble:
    kw = {"ensemble_size": E, "stepping": Stepping(loss="both"), **kw}
    ens = DeLaNEnsemble(MIXED, actuation(), control_dt=0.02, **(ARCH | kw))
    ens.load_members(reference_members(kw["stepping"].loss) if members is None else members)
    return ens


# -------------------------------------------------------------- equals a loop of DeLaN


@pytest.mark.parametrize("batch", [2 * E, 2 * E + 1])
def test_tsinf_equals_a_loop_over_members(batch: int) -> None:
    """Element b is stepped by member b % E alone, also when E does not divide B."""
    members = reference_members()
    ens = ensemble(members)
    q, qd, action = states(batch)
    with torch.inference_mode():
        out = ens.step(q, qd, action)
        for b in range(batch):
            ref = members[b % E].step(q[b], qd[b], action[b])
            torch.testing.assert_close(out.q[b], ref.q, **TOL)
            torch.testing.assert_close(out.qd[b], ref.qd, **TOL)


def test_member_after_a_vectorised_step_is_that_member() -> None:
    """`member` copies a template that the vmapped calls run through; a call must not leave
    anything in it that breaks the copy (the features' buffers, shared by three paths with
    the residual force, once did)."""
    members = reference_members(residual=True)
    ens = ensemble(members, **arch(residual=True))
    q, qd, action = states(2 * E)
    with torch.no_grad():
        ens.step(q, qd, action)
    copy = ens.member(1)
    with torch.inference_mode():
        out, ref = copy.step(q, qd, action), members[1].step(q, qd, action)
    torch.testing.assert_close(out.q, ref.q, **TOL)
    torch.testing.assert_close(out.qd, ref.qd, **TOL)


def test_members_with_a_residual_and_translation_invariance_equal_a_loop() -> None:
    """Every DeLaN option reaches the members: with the residual force and the height
    potential, the ensemble's step and loss are still those of E separate DeLaNs."""
    options = {"residual": True, "translation_invariant": True}
    members = reference_members(**options)
    assert members[0].residual is not None
    ens = DeLaNEnsemble(
        MIXED, actuation(), 0.02, ensemble_size=E, stepping=Stepping(loss="both"), **arch(**options)
    )
    ens.load_members(members)
    q, qd, action = states(2 * E)
    with torch.inference_mode():
        out = ens.step(q, qd, action)
        for b in range(2 * E):
            ref = members[b % E].step(q[b], qd[b], action[b])
            torch.testing.assert_close(out.q[b], ref.q, **TOL)
            torch.testing.assert_close(out.qd[b], ref.qd, **TOL)


def test_tsinf_keeps_leading_dims_and_broadcasts() -> None:
    """(N, P, .) is flattened row-major: particle p of sample n is member (n P + p) % E."""
    members = reference_members()
    ens = ensemble(members)
    q, qd, action = states(4 * E)
    out = ens.step(q[0], qd.reshape(4, E, NV), action.reshape(4, E, NU))  # q broadcast
    assert out.q.shape == (4, E, NQ) and out.qd.shape == (4, E, NV)
    ref = members[1].step(q[0], qd[1], action[1])  # flat index 1 -> (0, 1), member 1
    torch.testing.assert_close(out.qd[0, 1], ref.qd, **TOL)


def test_mean_is_the_members_average_in_velocity_space() -> None:
    members = reference_members()
    ens = ensemble(members, propagation="mean")
    q, qd, action = states(5)
    with torch.inference_mode():
        out = ens.step(q, qd, action)
        refs = [m.step(q, qd, action) for m in members]
    qd_mean = torch.stack([r.qd for r in refs]).mean(0)
    v_mean = torch.stack([differentiate_pos(MIXED, q, r.q, 1.0) for r in refs]).mean(0)
    torch.testing.assert_close(out.qd, qd_mean, **TOL)
    torch.testing.assert_close(out.q, integrate_pos(MIXED, q, v_mean, 1.0), **TOL)
    torch.testing.assert_close(
        out.q[:, :2], torch.stack([r.q[:, :2] for r in refs]).mean(0), **TOL
    )  # slide and hinge: the plain average
    torch.testing.assert_close(out.q[:, 5:9].norm(dim=-1), torch.ones(5), **TOL)  # unit


def test_terms_and_acceleration_stack_the_members() -> None:
    members = reference_members()
    ens = ensemble(members)
    q, qd, action = states(4)
    terms, acc = ens.terms(q, qd), ens.acceleration(q, qd, action)
    assert terms.mass_matrix.shape == (E, 4, NV, NV) and acc.shape == (E, 4, NV)
    for e, m in enumerate(members):
        ref = m.terms(q, qd)
        torch.testing.assert_close(terms.coriolis[e], ref.coriolis, **TOL)
        torch.testing.assert_close(terms.gravity[e], ref.gravity, **TOL)
        torch.testing.assert_close(acc[e], m.acceleration(q, qd, action), **TOL)


def test_loss_and_gradients_equal_the_members_summed() -> None:
    """Without bootstrap: loss = sum_e DeLaN loss_e, metrics averaged, same gradients."""
    members = reference_members()
    ens = ensemble(members, bootstrap=False)
    batch = transitions(32, seed=7)
    out = ens.loss(batch)
    out.loss.backward()
    refs = [m.loss(batch) for m in members]
    torch.testing.assert_close(out.loss, sum(r.loss for r in refs), **TOL)
    for name in ("forward_mse", "inverse_mse"):
        assert out.metrics[name] == pytest.approx(sum(r.metrics[name] for r in refs) / E)
    assert out.metrics["loss"] == pytest.approx(float(out.loss.detach()))
    for r in refs:
        r.loss.backward()
    stacked = dict(ens.members.named_parameters())
    for name, _ in members[0].named_parameters():
        for e, m in enumerate(members):
            torch.testing.assert_close(stacked[name].grad[e], m.get_parameter(name).grad, **TOL)


def test_bootstrap_trains_each_member_on_its_own_seeded_resample() -> None:
    members = reference_members()
    ens = ensemble(members, seed=5)
    batch = transitions(32, seed=7)
    out = ens.loss(batch)
    idx = torch.randint(32, (E, 32), generator=torch.Generator().manual_seed(5))
    expected = sum(m.loss(batch[idx[e]]).loss for e, m in enumerate(members))
    torch.testing.assert_close(out.loss, expected, **TOL)
    ens.eval()  # validation: every member on the whole batch
    torch.testing.assert_close(
        ens.loss(batch).loss, sum(m.loss(batch).loss for m in members), **TOL
    )


# ------------------------------------------------------------------- propagation


def test_ts1_is_reproducible_and_draws_several_members() -> None:
    ens = ensemble(propagation="ts1")
    q, qd, action = states(40)
    with torch.inference_mode():
        per_member = ens.step_members(q, qd, action).qd  # (E, B, NV)
        first = ens.step(q, qd, action, generator=torch.Generator().manual_seed(3))
        again = ens.step(q, qd, action, generator=torch.Generator().manual_seed(3))
        gen = torch.Generator().manual_seed(3)
        draws = [ens.step(q, qd, action, generator=gen).qd for _ in range(2)]
    torch.testing.assert_close(first.qd, again.qd, atol=0.0, rtol=0.0)
    # every element is one member's prediction; all members are used
    match = (per_member - first.qd).abs().amax(-1) < 1e-12  # (E, B)
    assert match.sum(0).eq(1).all()
    assert match.any(1).all()
    assert not torch.equal(draws[0], draws[1])  # a fresh draw on every call


def test_every_member_mass_matrix_is_spd() -> None:
    """Every member's M = L L^T is SPD; with extreme weights diag(L) keeps its floor."""
    ens = DeLaNEnsemble(MIXED, actuation(), control_dt=0.02, ensemble_size=4, **ARCH)
    q, qd, _ = states(64)
    M = ens.mass_matrix(3.0 * q)  # (E, B, n, n)
    assert M.shape == (4, 64, NV, NV)
    torch.testing.assert_close(M, M.transpose(-1, -2), atol=1e-12, rtol=0.0)
    assert torch.linalg.eigvalsh(M).min() > 0.0
    assert (torch.linalg.cholesky_ex(M).info == 0).all()
    with torch.no_grad():
        for p in ens.parameters():
            p.mul_(50.0)
    L = ens.terms(10.0 * q, qd).cholesky  # (E, B, n, n)
    assert torch.equal(L, torch.tril(L))
    assert torch.diagonal(L, dim1=-2, dim2=-1).min() >= 1e-3  # diag_shift


# ---------------------------------------------------------------------- training


def test_gradients_reach_every_member_and_differ_under_bootstrap() -> None:
    """Identical members: only their bootstrap resamples tell their gradients apart."""
    same = reference_members()[:1] * E
    batch = transitions(32, seed=7)
    grads = {}
    for bootstrap in (True, False):
        ens = ensemble(same, bootstrap=bootstrap, seed=0)
        ens.loss(batch).loss.backward()
        grads[bootstrap] = {n: p.grad for n, p in ens.members.named_parameters()}
    for name, g in grads[True].items():
        flat = g.reshape(E, -1)
        assert (flat.abs().amax(1) > 0).all(), name  # every member gets a gradient
        assert all(not torch.allclose(flat[0], flat[e]) for e in range(1, E)), name
        torch.testing.assert_close(grads[False][name][1], grads[False][name][0], **TOL)


def test_fit_normalization_gives_every_member_a_single_delans_statistics() -> None:
    ens = ensemble()
    data = transitions(64, seed=11)
    single = reference_members()[0]
    ens.fit_normalization(data)
    single.fit_normalization(data)
    theirs = dict(single.named_buffers())
    for name, buf in ens.members.named_buffers():
        expected = theirs[name].expand_as(buf) if buf.is_floating_point() else theirs[name]
        torch.testing.assert_close(buf, expected, atol=0.0, rtol=0.0)


def test_tiny_fit_on_pendulum_data_reduces_the_loss() -> None:
    system = make_env_parts("pendulum").system
    data = dynamics_dataset(system, 256, torch.Generator().manual_seed(0))
    torch.manual_seed(0)
    ens = DeLaNEnsemble(
        system.layout,
        system.actuation,
        system.control_dt,
        structure=Structure(hidden=16),
        stepping=Stepping(integrator="euler"),
        ensemble_size=E,
        seed=0,
    )
    ens.fit_normalization(data)
    ens.eval()
    before = float(ens.loss(data).loss.detach())
    optimizer = torch.optim.Adam(ens.parameters(), lr=1e-2)
    cfg = FitConfig(batch_size=64, max_epochs=8, patience=None, val_fraction=0.25)
    report = fit_model(ens, optimizer, data, cfg, torch.Generator().manual_seed(0))
    ens.eval()
    assert report.epochs_run == 8
    assert float(ens.loss(data).loss.detach()) < 0.6 * before


# ----------------------------------------------------------- modules, devices, config


def test_state_dict_round_trip() -> None:
    ens = ensemble()
    state = ens.state_dict()
    assert state["members.dynamics.field.trunk.head.weight"].shape[0] == E
    assert not any(name.endswith(("rows", "gather", "plain_q")) for name in state)
    buffer = io.BytesIO()
    torch.save(state, buffer)
    buffer.seek(0)
    torch.manual_seed(9)
    both = Stepping(loss="both")
    other = DeLaNEnsemble(MIXED, actuation(), 0.02, ensemble_size=E, stepping=both, **ARCH)
    other.load_state_dict(torch.load(buffer, weights_only=True))
    q, qd, action = states(2 * E)
    torch.testing.assert_close(
        other.step(q, qd, action).q, ens.step(q, qd, action).q, atol=0.0, rtol=0.0
    )
    for e in range(E):  # and a member taken out is a working standalone DeLaN
        torch.testing.assert_close(
            other.member(e).step(q, qd, action).qd, ens.step_members(q, qd, action).qd[e], **TOL
        )


def test_float32_inference_mode_and_planning_objective() -> None:
    ens = ensemble().float()
    q, qd, action = (x.float() for x in states(2 * E))
    with torch.inference_mode():
        out = ens.step(q, qd, action)
    assert out.q.dtype == torch.float32 and torch.isfinite(out.q).all()
    task = make_env_parts("pendulum").task
    system = make_env_parts("pendulum").system
    pend = DeLaNEnsemble(
        system.layout, system.actuation, system.control_dt, ensemble_size=E, **ARCH
    ).float()
    objective = model_objective_factory(pend, task, particles=E)(torch.zeros(1), torch.zeros(1))
    returns = objective(torch.zeros(4, 3, 1))
    assert returns.shape == (4,) and torch.isfinite(returns).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("propagation", ["tsinf", "ts1", "mean"])
def test_cuda_matches_cpu(propagation: str) -> None:
    ens = ensemble(propagation=propagation)
    gpu = ensemble(propagation=propagation).cuda()
    q, qd, action = states(2 * E + 1)
    gen = torch.Generator(device="cuda").manual_seed(0)
    with torch.inference_mode():
        out = gpu.step(q.cuda(), qd.cuda(), action.cuda(), generator=gen)
        per_member = ens.step_members(q, qd, action).qd
    assert out.q.device.type == "cuda"
    if propagation == "tsinf":
        expected = per_member[torch.arange(2 * E + 1) % E, torch.arange(2 * E + 1)]
        torch.testing.assert_close(out.qd.cpu(), expected, atol=1e-8, rtol=1e-8)
    loss = gpu.loss(transitions().to("cuda")).loss
    loss.backward()
    assert torch.isfinite(loss)


def test_bad_arguments_are_named() -> None:
    with pytest.raises(ValueError, match="propagation"):
        DeLaNEnsemble(MIXED, actuation(), 0.02, propagation="ts2", **ARCH)
    with pytest.raises(ValueError, match="ensemble_size"):
        DeLaNEnsemble(MIXED, actuation(), 0.02, ensemble_size=0, **ARCH)
    with pytest.raises(ValueError, match="integrator"):
        DeLaNEnsemble(MIXED, actuation(), 0.02, stepping=Stepping(integrator="leapfrog"))
    ens = ensemble()
    with pytest.raises(ValueError, match="propagation"):
        ens.propagation = "expectation"
    with pytest.raises(ValueError, match="members"):
        ens.load_members(reference_members()[:2])


def test_config_builds_the_ensemble_and_checks_particles() -> None:
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        cfg = compose(config_name="config", overrides=["model=delan_ensemble", "env=pendulum"])
        bad = compose(config_name="config", overrides=["model=delan_ensemble", "model.particles=7"])
    validate_train_config(cfg)
    with pytest.raises(ConfigError, match="particles"):
        validate_train_config(bad)
    model = build_model(cfg.model, make_env_parts("pendulum").system)
    assert isinstance(model, DeLaNEnsemble)
    assert model.ensemble_size == cfg.model.ensemble_size == 5
    assert model.propagation == "tsinf" and model.bootstrap
    assert model.member(0).velocity_margin == cfg.model.velocity_margin
