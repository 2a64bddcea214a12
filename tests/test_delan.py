"""DeLaN's structure: SPD mass matrix, exact Coriolis terms, energy, inverse/forward duality."""

import pytest
import torch

from mbrl_delan.models.delan import DeLaN, Stepping
from mbrl_delan.models.integrators import integrate
from mbrl_delan.models.structure import Structure
from mbrl_delan.systems.system import HINGE, SLIDE, JointLayout


@pytest.fixture(autouse=True)
def float64():
    """These tests compare with exact derivatives: run them in float64, then restore."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


def layout(n: int, slide_first: bool = False) -> JointLayout:
    types = tuple(SLIDE if (slide_first and i == 0) else HINGE for i in range(n))
    return JointLayout(
        types=types, qpos_adr=tuple(range(n)), dof_adr=tuple(range(n)), limited=(False,) * n
    )


def model(
    n: int = 3, nu: int | None = None, seed: int = 0, slide_first: bool = True, **kw
) -> DeLaN:
    torch.manual_seed(seed)
    nu = n if nu is None else nu
    B = torch.randn(n, nu)
    structure = Structure(hidden=32, layers=2, **kw)
    m = DeLaN(layout(n, slide_first=slide_first), B, control_dt=0.01, structure=structure)
    with torch.no_grad():  # random biases too, so no symmetry of the initialisation helps
        for layer in m.modules():
            if isinstance(layer, torch.nn.Linear):
                layer.bias.normal_(0.0, 0.5)
    return m.double()


def random_state(n: int, batch: int = 64, scale: float = 2.0):
    g = torch.Generator().manual_seed(1)
    return scale * torch.randn(batch, n, generator=g), scale * torch.randn(batch, n, generator=g)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mass_matrix_symmetric_positive_definite(seed: int) -> None:
    """Random weights (independent initialisations) and random inputs: M is SPD."""
    torch.manual_seed(seed)
    m = DeLaN(layout(6, slide_first=True), torch.eye(6), control_dt=0.01).double()
    q, qd = random_state(6, batch=512, scale=10.0)
    t = m.terms(q, qd)
    M, L = t.mass_matrix, t.cholesky
    assert torch.allclose(M, M.transpose(-1, -2), atol=1e-12)
    assert torch.linalg.eigvalsh(M).min() > 0.0
    factor, info = torch.linalg.cholesky_ex(M)
    assert (info == 0).all()
    torch.testing.assert_close(factor, L)


def test_cholesky_diagonal_floor_holds_for_extreme_weights() -> None:
    """Whatever the weights, diag(L) >= shift and L is lower-triangular, so M = L L^T is PD."""
    m = model(4)
    with torch.no_grad():
        for p in m.parameters():
            p.mul_(50.0)
    q, qd = random_state(4, batch=256, scale=5.0)
    L = m.terms(q, qd).cholesky
    assert torch.equal(L, torch.tril(L))
    assert torch.diagonal(L, dim1=-2, dim2=-1).min() >= m.dynamics.field.diag_shift


def reference_terms(m: DeLaN, q, qd):
    """Coriolis and gravity by autograd over the full Jacobian of M(q) (the naive way)."""

    def mass(qi):
        return m.terms(qi, torch.zeros_like(qi)).mass_matrix

    def potential(qi):
        return m.terms(qi, torch.zeros_like(qi)).potential_energy

    cs, gs = [], []
    for qi, vi in zip(q, qd, strict=True):
        dM = torch.autograd.functional.jacobian(mass, qi)  # (n, n, n): dM_ij / dq_k
        m_dot = dM @ vi
        grad_kin = torch.einsum("i,ijk,j->k", vi, dM, vi)
        cs.append(m_dot @ vi - 0.5 * grad_kin)
        gs.append(torch.autograd.functional.jacobian(potential, qi))
    return torch.stack(cs), torch.stack(gs)


TREE8 = (-1, 0, 1, 0, 3, 4, 0, 6)  # three branches off DoF 0, as a humanoid's limbs


@pytest.mark.parametrize(
    ("n", "slide_first", "parents"),
    [(3, True, None), (1, False, None), (1, True, None), (8, False, None), (8, False, TREE8)],
)
def test_coriolis_and_gravity_match_autograd(n: int, slide_first: bool, parents) -> None:
    """Also with one DoF (a hinge; a slide), where the pullback reuses the forward tangent,
    and with 8, whose factor's head computes L's entries only (dense, and a tree's)."""
    m = model(n, slide_first=slide_first, dof_parents=parents)
    q, qd = random_state(n, batch=8)
    t = m.terms(q, qd)
    c_ref, g_ref = reference_terms(m, q, qd)
    torch.testing.assert_close(t.coriolis, c_ref, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(t.gravity, g_ref, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("parents", [None, TREE8])
def test_entry_head_equals_matrix_head(monkeypatch, parents) -> None:
    """The factor's head over L's entries (more than `MATRIX_HEAD_MAX_N` DoFs) and the
    matrix-layout head give the same terms, torques and weight gradients."""
    from mbrl_delan.models import field

    m = model(8, dof_parents=parents)
    q, qd = random_state(8, batch=16)
    qdd = torch.randn(16, 8, generator=torch.Generator().manual_seed(2))

    def outputs() -> list[torch.Tensor]:
        m.zero_grad()
        t = m.terms(q, qd)
        tau = m.dynamics.inverse_dynamics(q, qd, qdd)
        tau.square().sum().backward()
        grads = [p.grad.clone() for p in m.parameters() if p.grad is not None]
        return [t.mass_matrix, t.coriolis, t.gravity, tau, *grads]

    by_entries = outputs()
    monkeypatch.setattr(field, "MATRIX_HEAD_MAX_N", 8)
    for a, b in zip(by_entries, outputs(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_coriolis_is_quadratic_in_velocity_and_power_neutral() -> None:
    """c(q, k qd) = k^2 c(q, qd), and qd^T (c - 1/2 Mdot qd) = 0 (skew symmetry of Mdot - 2C)."""
    torch.manual_seed(0)
    m = DeLaN(layout(3), torch.eye(3), control_dt=0.01).double()
    q, qd = random_state(3)
    c1 = m.terms(q, qd).coriolis
    c3 = m.terms(q, 3.0 * qd).coriolis
    torch.testing.assert_close(c3, 9.0 * c1)
    # d/dt T = qd^T M qdd + 1/2 qd^T Mdot qd; with M qdd = -c (no other forces) dT/dt must be 0.
    dt = 1e-6
    t0 = m.terms(q, qd)
    qdd = torch.linalg.solve(t0.mass_matrix, -t0.coriolis.unsqueeze(-1)).squeeze(-1)
    t_plus = m.terms(q + dt * qd, qd + dt * qdd).kinetic_energy
    t_minus = m.terms(q - dt * qd, qd - dt * qdd).kinetic_energy
    power_scale = (qd * t0.coriolis).abs().sum(-1)  # size of each term that must cancel
    assert (((t_plus - t_minus) / (2 * dt)).abs() / power_scale).max() < 1e-5


def test_forward_of_inverse_is_identity() -> None:
    m = model(4)
    q, qd = random_state(4)
    qdd = torch.randn_like(q)
    tau = m.dynamics.inverse_dynamics(q, qd, qdd)
    torch.testing.assert_close(m.dynamics.forward_dynamics(q, qd, tau), qdd, rtol=1e-8, atol=1e-8)
    tau2 = m.dynamics.inverse_dynamics(q, qd, m.dynamics.forward_dynamics(q, qd, tau))
    torch.testing.assert_close(tau2, tau, rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("armature", [None, (0.05, 0.02)])
def test_energy_conserved_in_passive_rk4_rollout(armature) -> None:
    m = model(2, dissipation=False, armature=armature)
    q, qd = random_state(2, batch=16, scale=1.0)
    zero_tau = torch.zeros_like(qd)

    def energy(q_, qd_):
        t = m.terms(q_, qd_)
        return t.kinetic_energy + t.potential_energy

    def accel(q_, qd_):
        return m.dynamics.forward_dynamics(q_, qd_, zero_tau)

    e0 = energy(q, qd)
    with torch.no_grad():  # no graph through 1,000 steps
        for _ in range(1000):
            s = integrate(m.layout, accel, q, qd, dt=1e-3, method="rk4")
            q, qd = s.q, s.qd
    drift = (energy(q, qd) - e0).abs() / (e0.abs() + m.terms(q, qd).kinetic_energy.abs())
    assert drift.max() < 1e-6


def test_dissipation_never_adds_energy() -> None:
    m = model(3)
    with torch.no_grad():
        m.dynamics.dissipation.raw_viscous.normal_()
        m.dynamics.dissipation.raw_coulomb.normal_()
    _, qd = random_state(3, batch=512, scale=3.0)
    power = (qd * m.dynamics.dissipation(qd)).sum(-1)
    assert power.min() >= 0.0
    assert power.max() > 0.0


def test_runs_without_autograd() -> None:
    """Planning runs under inference_mode: the derivatives are explicit, not autograd."""
    m = model(3)
    q, qd = random_state(3)
    with torch.inference_mode():
        s = m.step(q, qd, torch.zeros(q.shape[0], 3))
    assert torch.isfinite(s.q).all() and torch.isfinite(s.qd).all()


def test_bad_arguments_are_named() -> None:
    with pytest.raises(ValueError, match="integrator"):
        DeLaN(layout(2), torch.eye(2), 0.01, stepping=Stepping(integrator="leapfrog"))
    with pytest.raises(ValueError, match="diag_shift"):
        DeLaN(layout(2), torch.eye(2), 0.01, Structure(diag_shift=0.0))
    with pytest.raises(ValueError, match="coulomb_lead needs Coulomb friction"):
        Structure(coulomb=False, coulomb_lead=True)
    with pytest.raises(ValueError, match="coulomb_lead acts in joint axes"):
        Structure(yaw_invariant=True, coulomb_lead=True)


def test_planner_survives_a_model_that_returns_inf_and_nan() -> None:
    """Non-finite returns count as the worst, never poison the plan."""
    from mbrl_delan.planners.mppi import MPPIPlanner

    planner = MPPIPlanner(
        horizon=5,
        action_low=[-1.0],
        action_high=[1.0],
        num_samples=64,
        iterations=5,
        temperature=0.1,
    )

    def objective(actions):
        ret = -(actions - 0.5).square().sum(dim=(-1, -2))
        ret[::3] = float("nan")
        ret[1::3] = float("inf") * -1
        return ret

    result = planner.plan(objective, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(result.mean).all()
    assert abs(float(result.mean[0, 0]) - 0.5) < 0.15  # it still optimises on the finite ones


def test_load_mechanics_copies_m_v_friction_keeps_b_and_names_misfits() -> None:
    two = layout(2)
    torch.manual_seed(0)
    source = DeLaN(two, torch.eye(2), 0.01, Structure(hidden=8)).double()  # action: both torques
    with torch.no_grad():
        for p in source.parameters():
            p.add_(0.3 * torch.randn_like(p))
    with_residual = Structure(hidden=8, residual=True)
    target = DeLaN(two, torch.tensor([[0.0], [2.0]]), 0.01, with_residual).double()
    target.load_mechanics(source.state_dict())
    q, qd = torch.randn(5, 2, dtype=torch.float64), torch.randn(5, 2, dtype=torch.float64)
    for name in ("mass_matrix", "coriolis", "gravity", "dissipation"):
        torch.testing.assert_close(
            getattr(target.terms(q, qd), name), getattr(source.terms(q, qd), name)
        )
    assert torch.equal(target.dynamics.actuation, torch.tensor([[0.0], [2.0]], dtype=torch.float64))
    assert bool(target.mechanics_loaded) and "mechanics_loaded" in target.state_dict()
    wider = DeLaN(two, torch.eye(2), 0.01, Structure(hidden=16))
    with pytest.raises(
        ValueError, match=r"other shape: .*hidden\.0\.bias \(8,\) \(this model: \(16,\)\)"
    ):
        wider.load_mechanics(source.state_dict())


def test_armature_adds_a_known_diagonal_to_m() -> None:
    """M = L L^T + diag(a): the rest of the equations as without it, forward(inverse) = id,
    M's eigenvalues at least min(a) (energy: the test above)."""
    a = torch.tensor([0.05, 0.01, 0.02], dtype=torch.float64)
    plain, with_a = model(3, dissipation=False), model(3, dissipation=False, armature=a)
    q, qd = random_state(3)
    t0, t1 = plain.terms(q, qd), with_a.terms(q, qd)
    torch.testing.assert_close(t1.mass_matrix, t0.mass_matrix + torch.diag(a))
    torch.testing.assert_close(t1.mass_matrix, t1.cholesky @ t1.cholesky.mT)
    torch.testing.assert_close(t1.coriolis, t0.coriolis)
    torch.testing.assert_close(t1.gravity, t0.gravity)
    torch.testing.assert_close(t1.kinetic_energy, t0.kinetic_energy + 0.5 * (a * qd * qd).sum(-1))
    assert float(torch.linalg.eigvalsh(t1.mass_matrix).min()) >= float(a.min()) - 1e-12
    qdd = torch.randn_like(q)
    tau = with_a.dynamics.inverse_dynamics(q, qd, qdd)
    torch.testing.assert_close(with_a.dynamics.forward_dynamics(q, qd, tau), qdd)
    with pytest.raises(ValueError, match="armature must be 3 finite values >= 0"):
        model(3, armature=[0.1, -0.1, 0.0])


@pytest.mark.parametrize("n", [1, 3])
def test_spring_potential_is_the_quadratic_and_its_force_matches_autograd(n: int) -> None:
    """With ``spring_potential`` and the network's V head at zero, V = 1/2 x^T K x + b^T x
    exactly with x = q - c (K the symmetric part of the learned matrix in the data's units,
    c the data's mean) and g = K x + b; with the network's V too, g still equals autograd's
    dV/dq (one DoF included, off the scalar path). A unit of W_ii pushes one torque std f_i
    at one position std d_i."""
    m = model(n, spring_potential=True)
    field = m.dynamics.field
    q, qd = random_state(n, batch=8)
    q_data = 0.3 + 2.0 * torch.rand(500, n, dtype=torch.float64) * torch.linspace(0.5, 1.5, n)
    torque_std = torch.linspace(0.1, 30.0, n, dtype=torch.float64)
    with torch.no_grad():
        field.energy_scale.fill_(30.0)
        field.set_spring_units(q_data, torque_std)
        field.spring_stiffness.copy_(torch.randn(n, n))
        field.spring_offset.copy_(torch.randn(n))
    c_ref, g_ref = reference_terms(m, q, qd)
    torch.testing.assert_close(m.terms(q, qd).gravity, g_ref, rtol=1e-9, atol=1e-10)
    with torch.no_grad():
        field.trunk.head.weight[field.v_row].zero_()
        field.trunk.head.bias[field.v_row].zero_()
    K = field.joint_springs()
    torch.testing.assert_close(K, K.T)
    W, spread = field.spring_stiffness.detach(), q_data.std(dim=0)
    torch.testing.assert_close(K.diagonal() * spread, W.diagonal() * torque_std)
    terms = m.terms(q, torch.zeros_like(qd))
    x = q - q_data.mean(dim=0)
    b = field.spring_offset.detach() * torque_std
    torch.testing.assert_close(terms.gravity, x @ K + b, rtol=1e-9, atol=1e-10)
    quadratic = 0.5 * ((x @ K) * x).sum(-1) + x @ b
    torch.testing.assert_close(terms.potential_energy, quadratic, rtol=1e-9, atol=1e-10)


def test_spring_weights_saved_without_units_load_on_the_raw_coordinates() -> None:
    """A state dict from before the springs had units (no scale, force scale or centre)
    loads with K = E (W + W^T) / 2 on q itself, as it was fitted, whole or as mechanics."""
    m = model(3, spring_potential=True)
    field = m.dynamics.field
    with torch.no_grad():
        field.energy_scale.fill_(7.0)
        field.spring_stiffness.copy_(torch.randn(3, 3))
    state = {k: v for k, v in m.state_dict().items() if not k.endswith(
        ("spring_scale", "spring_force_scale", "spring_centre"))}  # fmt: skip
    fresh = model(3, spring_potential=True)
    fresh.dynamics.field.set_spring_units(torch.rand(50, 3, dtype=torch.float64) + 1.0,
                                          torch.ones(3, dtype=torch.float64))  # fmt: skip
    fresh.load_state_dict(state)
    W = field.spring_stiffness.detach()
    torch.testing.assert_close(fresh.dynamics.field.joint_springs(), 3.5 * (W + W.T))
    mechanics = model(3, spring_potential=True)
    mechanics.dynamics.field.set_spring_units(torch.rand(50, 3, dtype=torch.float64) + 1.0,
                                              torch.ones(3, dtype=torch.float64))  # fmt: skip
    mechanics.load_mechanics(state)
    torch.testing.assert_close(mechanics.dynamics.field.joint_springs(), 3.5 * (W + W.T))
