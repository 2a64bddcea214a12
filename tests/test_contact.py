"""The structured contact model: its point Jacobians against MuJoCo's `mj_jac`, and the laws
it promises (no force without contact, a non-negative normal force, friction inside its cone,
no energy gained in a passive drop)."""

import dataclasses
import math

import mujoco
import numpy as np
import pytest
import torch

from mbrl_delan.conf.builders import build_model
from mbrl_delan.conf.checks import compose_train_config
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.models.contact import (
    GRAVITY,
    HOLD_DEPTH,
    PENETRATION_UNIT,
    ContactLaw,
    ContactModel,
    ContactPoints,
    ImplicitTerms,
    JointLimits,
    implicit_acceleration,
)
from mbrl_delan.systems.external import humanoid_v5_xml
from mbrl_delan.systems.posarith import integrate_pos
from mbrl_delan.systems.system import load_system

BALL_XML = """
<mujoco>
  <option gravity="0 0 -9.81"/>
  <worldbody>
    <geom type="plane" size="5 5 0.1"/>
    <body pos="0 0 0.5">
      <freejoint/>
      <geom type="sphere" size="0.1" mass="1"/>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def humanoid() -> tuple[mujoco.MjModel, ContactModel]:
    model = mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))
    return model, ContactModel.from_mujoco(model).double()


def random_state(model: mujoco.MjModel, n: int, height: float, seed: int) -> tuple:
    """n states near qpos0 with the root at `height` m, random joint angles and velocities."""
    g = torch.Generator().manual_seed(seed)
    q = torch.from_numpy(model.qpos0.copy()).repeat(n, 1)
    q[:, 7:] += 0.5 * (2 * torch.rand(n, model.nq - 7, generator=g, dtype=torch.float64) - 1)
    q[:, 3:7] += 0.2 * torch.randn(n, 4, generator=g, dtype=torch.float64)
    q[:, 3:7] /= q[:, 3:7].norm(dim=-1, keepdim=True)
    q[:, 2] = height
    qd = 2.0 * torch.randn(n, model.nv, generator=g, dtype=torch.float64)
    return q, qd


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def test_points_and_jacobians_match_mujoco(humanoid) -> None:
    model, contact = humanoid
    q, _ = random_state(model, 4, 1.0, seed=0)
    position, jacobian = contact.kinematics(q)  # (4, P, 3), (4, P, 3, nv)
    data = mujoco.MjData(model)
    for i in range(q.shape[0]):
        data.qpos[:] = q[i].numpy()
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        for p, body in enumerate(contact.points.body):
            offset = np.asarray(contact.points.offset[p])
            expected = data.xpos[body] + data.xmat[body].reshape(3, 3) @ offset
            np.testing.assert_allclose(position[i, p].numpy(), expected, atol=1e-12)
            jacp = np.zeros((3, model.nv))
            mujoco.mj_jac(model, data, jacp, None, expected, body)
            np.testing.assert_allclose(jacobian[i, p].numpy(), jacp, atol=1e-12)


def test_points_are_the_geoms_that_touch_the_floor(humanoid) -> None:
    model, contact = humanoid
    feet = [
        mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in ("right_foot", "left_foot")
    ]
    assert all(f in contact.points.body for f in feet)
    assert contact.points.floor == 0.0
    mass = model.body_mass.sum()
    assert contact.points.weight == pytest.approx(9.81 * mass, rel=1e-6)


def test_no_force_without_contact(humanoid) -> None:
    model, contact = humanoid
    q, qd = random_state(model, 16, 3.0, seed=1)  # every point at least 1 m above the floor
    assert torch.equal(contact(q, qd), torch.zeros_like(qd))


def test_normal_force_non_negative_and_friction_inside_the_cone(humanoid) -> None:
    model, contact = humanoid
    q, qd = random_state(model, 64, 0.9, seed=2)  # feet, legs and hands through the floor
    state = contact.contact_state(q, qd)
    normal, tangential = state.force[..., 2], state.force[..., :2].norm(dim=-1)
    depth = contact.points.floor + contact.radius - state.position[..., 2]
    assert bool((depth > 0).any()) and bool((depth <= 0).any())
    assert bool((normal >= 0).all())
    assert bool((normal[depth <= 0] == 0).all()) and bool((normal[depth > 0] > 0).any())
    mu = contact.point_law(normal)["friction"].detach()  # (P,)
    assert bool((tangential <= mu * normal * (1 + 1e-12)).all())
    # friction opposes the slip
    slip = (state.force[..., :2] * state.velocity[..., :2]).sum(-1)
    assert bool((slip <= 0).all())


def test_normal_force_grows_with_depth_and_resists_approach(humanoid) -> None:
    _, contact = humanoid
    p = len(contact.points.body)
    radius = contact.radius
    depths = torch.tensor([0.001, 0.005, 0.01, 0.02], dtype=torch.float64)
    position = torch.zeros(4, p, 3, dtype=torch.float64)
    position[..., 2] = radius - depths[:, None]
    still = contact.point_forces(position, torch.zeros_like(position))[..., 2]
    assert bool((still.diff(dim=0) > 0).all())
    moving = torch.zeros_like(position)
    moving[..., 2] = -0.3
    approaching = contact.point_forces(position, moving)[..., 2]
    leaving = contact.point_forces(position, -moving)[..., 2]
    assert bool((approaching > still).all()) and bool((leaving < still).all())


def test_a_passive_drop_gains_no_energy(tmp_path) -> None:
    """A ball dropped with spin and sideways speed onto the floor: its mechanical energy
    (kinetic with MuJoCo's mass matrix, plus m g z) never rises above the start, and the
    bounce and the friction take some of it."""
    path = tmp_path / "ball.xml"
    path.write_text(BALL_XML)
    model = mujoco.MjModel.from_xml_string(BALL_XML)
    system = load_system(path)
    contact = ContactModel.from_mujoco(model).double()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    M = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, M)
    mass_matrix = torch.from_numpy(M)  # constant for one free body
    weight = float(model.body_mass[1]) * 9.81
    gravity = torch.tensor([0, 0, -weight, 0, 0, 0], dtype=torch.float64)

    def energy(q: torch.Tensor, qd: torch.Tensor) -> float:
        return float(0.5 * qd @ mass_matrix @ qd + weight * q[2])

    q = torch.from_numpy(model.qpos0.copy())
    qd = torch.tensor([1.0, 0.0, 0.0, 0.0, 5.0, 0.0], dtype=torch.float64)
    start, dt, touched = energy(q, qd), 2e-4, False
    energies = []
    with torch.no_grad():
        for _ in range(int(0.6 / dt)):  # semi-implicit Euler; the bounce is at 0.29 s
            force = contact(q, qd)
            touched |= bool(force.abs().sum() > 0)
            qd = qd + dt * torch.linalg.solve(mass_matrix, gravity + force)
            q = integrate_pos(system.layout, q, qd, dt)
            energies.append(energy(q, qd))
    assert touched
    assert max(energies) <= start * (1 + 1e-3)
    assert energies[-1] < 0.95 * start


def test_delan_adds_the_contact_force() -> None:
    cfg = compose_train_config(["env=humanoid_stand", "model=delan", "env.model_contacts=true"])
    parts = make_env_parts("humanoid_stand", None, 10)
    model = build_model(cfg.model, parts.system).double()
    assert isinstance(model.contact, ContactModel)
    q, qd = random_state(parts.system.mj_model(), 8, 1.0, seed=3)
    action = torch.rand(8, parts.system.nu, dtype=torch.float64)
    own = model.dynamics.generalized_force(action) + model.contact(q, qd)
    residual = model.tau_scale * model.residual(q, qd, action, model.velocity_limit / 3.0)
    torch.testing.assert_close(model.applied_force(q, qd, action), own + residual)
    assert isinstance(model.contact.points, ContactPoints)


def test_the_contact_law_learns_through_a_delan_step() -> None:
    """A forward step from states through the floor gives the law's constants a finite,
    non-zero gradient (they are fitted with the rest of the model)."""
    cfg = compose_train_config(["env=humanoid_stand", "model=delan", "env.model_contacts=true"])
    parts = make_env_parts("humanoid_stand", None, 10)
    model = build_model(cfg.model, parts.system)
    q, qd = random_state(parts.system.mj_model(), 8, 0.95, seed=4)
    nxt = model.step(q.float(), qd.float(), torch.zeros(8, parts.system.nu))
    assert bool(torch.isfinite(nxt.q).all() and torch.isfinite(nxt.qd).all())
    nxt.qd.square().sum().backward()
    for name, param in model.contact.named_parameters():
        assert param.grad is not None and bool(torch.isfinite(param.grad).all()), name
        assert float(param.grad.abs().sum()) > 0, name


def test_each_group_has_its_own_constants(humanoid) -> None:
    """Each foot and each hand (the leaf bodies) its own group, the shins and upper arms
    (`limbs`) and the rest (`trunk`) apart; a group's stiffness moves its own points' forces
    and no others'."""
    model, contact = humanoid
    names = set(contact.points.groups)
    assert names == {"right_foot", "left_foot", "right_lower_arm", "left_lower_arm", "limbs",
                     "trunk"}  # fmt: skip
    q, qd = random_state(model, 32, 0.9, seed=5)
    before = contact.contact_state(q, qd).force
    left = contact.points.groups.index("left_foot")
    changed = ContactModel.from_mujoco(model).double()
    with torch.no_grad():
        changed.log_stiffness[left] += 1.0
    after = changed.contact_state(q, qd).force
    own = torch.tensor(contact.points.group) == left
    assert bool((after[:, own] != before[:, own]).any())
    torch.testing.assert_close(after[:, ~own], before[:, ~own], rtol=0, atol=0)


def test_the_start_holds_the_weight_at_a_few_millimetres() -> None:
    """Worked values of `ContactLaw.from_physics`: at HOLD_DEPTH one point carries half the
    weight, and c = 2 omega / g with omega^2 = e g / d (a critically damped stance)."""
    law = ContactLaw.from_physics()
    assert law.stiffness * (HOLD_DEPTH / PENETRATION_UNIT) ** law.exponent == pytest.approx(0.5)
    omega = (law.exponent * GRAVITY / HOLD_DEPTH) ** 0.5
    assert law.damping == pytest.approx(2 * omega / GRAVITY)
    assert law.friction == 1.0


def _ball_drop(stiffness: float, implicit: bool, dt: float, seconds: float = 1.0) -> list[float]:
    """Energies of a ball dropped with spin and sideways speed, stepped by semi-implicit Euler
    at `dt` with the contact taken explicitly (a force) or implicitly."""
    model = mujoco.MjModel.from_xml_string(BALL_XML)
    start = ContactLaw.from_physics()
    law = ContactLaw(stiffness, start.exponent, start.damping, start.friction)
    contact = ContactModel.from_mujoco(model, law).double()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    M = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, M)
    mass_matrix = torch.from_numpy(M)
    weight = float(model.body_mass[1]) * 9.81
    gravity = torch.tensor([0, 0, -weight, 0, 0, 0], dtype=torch.float64)
    layout = load_system_from_string(BALL_XML).layout
    q = torch.from_numpy(model.qpos0.copy())
    qd = torch.tensor([1.0, 0.0, 0.0, 0.0, 5.0, 0.0], dtype=torch.float64)
    energies = [float(0.5 * qd @ mass_matrix @ qd + weight * q[2])]
    with torch.no_grad():
        for _ in range(int(seconds / dt)):
            if implicit:
                qdd = contact.implicit_acceleration(q, qd, dt, mass_matrix, gravity)
            else:
                qdd = torch.linalg.solve(mass_matrix, gravity + contact(q, qd))
            qd = qd + dt * qdd
            q = integrate_pos(layout, q, qd, dt)
            energies.append(float(0.5 * qd @ mass_matrix @ qd + weight * q[2]))
    return energies


def load_system_from_string(xml: str):
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "ball.xml"
        path.write_text(xml)
        return load_system(path)


def test_implicit_drop_at_the_models_own_step_gains_no_energy() -> None:
    """At the humanoid models' own step (7.5 ms) and the start's constants, the implicit
    contact never lifts the ball's energy above the start and the bounce and friction take
    some of it; at rest it sits within a few millimetres of the floor (the start's law)."""
    energies = _ball_drop(ContactLaw.from_physics().stiffness, implicit=True, dt=0.0075)
    assert max(energies) <= energies[0] * (1 + 1e-9)
    assert energies[-1] < 0.95 * energies[0]
    weight, radius = 9.81, 0.1
    rest_height = (energies[-1] - 0.0) / weight  # kinetic ~0 at rest: m g z
    assert radius - 0.02 < rest_height < radius + 1e-3


def test_implicit_contact_is_stable_where_the_explicit_law_diverges() -> None:
    """1000 times the start's stiffness (a sub-millimetre contact) at 7.5 ms: the explicit
    law throws the ball off (energy grows past 10x or overflows), the implicit one does not
    gain energy."""
    stiff = 1000 * ContactLaw.from_physics().stiffness
    explicit = np.array(_ball_drop(stiff, implicit=False, dt=0.0075))
    assert not np.isfinite(explicit).all() or explicit.max() > 10 * explicit[0]
    implicit = _ball_drop(stiff, implicit=True, dt=0.0075)
    assert max(implicit) <= implicit[0] * (1 + 1e-9)


HINGE_XML = """
<mujoco>
  <compiler angle="radian"/>
  <option gravity="0 0 0"/>
  <worldbody>
    <body>
      <joint name="hinge" type="hinge" axis="0 1 0" range="-0.5 0.5" limited="true"/>
      <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.05" mass="1"/>
    </body>
  </worldbody>
  <actuator><motor joint="hinge" gear="2" ctrlrange="-1 1" ctrllimited="true"/></actuator>
</mujoco>
"""


def test_joint_limits_push_back_only_past_a_bound() -> None:
    """A limited hinge: no force inside its range; past either bound a force back into it
    that holds the motor's largest torque (gear 2) at 0.01 rad."""
    model = mujoco.MjModel.from_xml_string(HINGE_XML)
    limits = JointLimits.from_mujoco(model)
    q = torch.tensor([[0.0], [0.49], [0.51], [-0.52]], dtype=torch.float64)
    terms = limits.implicit_terms(q, torch.zeros_like(q), dt=0.0075)
    force = terms.jacobian[..., 2, :] * terms.spring.unsqueeze(-1)  # (4, L=1, nv=1)
    torch.testing.assert_close(
        force.reshape(-1), torch.tensor([0.0, 0.0, -2.0, 4.0], dtype=torch.float64)
    )


def _dense_products(terms: ImplicitTerms, jacobian: torch.Tensor, active: torch.Tensor, dt: float
                    ) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """J^T (f0 - K J qd) and dt J^T K J with the dense Jacobians `jacobian` (..., P, 3, nv)."""
    on = active.to(terms.spring.dtype)
    gain = torch.stack([terms.tangential_gain, terms.tangential_gain, terms.normal_gain], -1)
    gain = gain * on.unsqueeze(-1)
    f0 = torch.zeros_like(terms.velocity)
    f0[..., 2] = terms.spring * on
    force = torch.einsum("...pkv,...pk->...v", jacobian, f0 - gain * terms.velocity)
    added = dt * torch.einsum("...pkv,...pk,...pkw->...vw", jacobian, gain, jacobian)
    return force, added


def test_contact_products_by_chain_equal_the_dense_ones(humanoid) -> None:
    """The humanoid's points grouped by the chains of DoFs that move them (a chain per leg and
    arm): the generalized force, J^T K J and normal velocities equal those of the dense
    Jacobians (checked against `mj_jac` above), with points in and out of the solve."""
    model, contact = humanoid
    assert len(contact.chains) == 4  # the legs and arms; the trunk's points join a leg
    q, qd = random_state(model, 8, 0.9, seed=4)
    dt = 0.0075
    terms = contact.implicit_terms(q, qd, dt)
    _, jacobian = contact.kinematics(q)
    torch.testing.assert_close(terms.velocity, torch.einsum("...pkv,...v->...pk", jacobian, qd))
    active = (terms.spring > 0) & (torch.rand(terms.spring.shape, generator=_gen(4)) < 0.8)
    assert bool(active.any())
    for chained, dense in zip(
        terms.generalized(active, dt), _dense_products(terms, jacobian, active, dt), strict=True
    ):
        torch.testing.assert_close(chained, dense, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(terms.normal_velocity(qd), terms.velocity[..., 2])


def test_joint_terms_equal_their_dense_jacobian_products() -> None:
    """The joint limits' diagonal shortcut gives the dense J^T (f0 - K J qd), dt J^T K J and
    normal velocities of their Jacobian rows, on the humanoid's 17 limited hinges."""
    model = mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))
    limits = JointLimits.from_mujoco(model).double()
    generator = _gen(0)
    q = torch.tensor(model.qpos0).repeat(6, 1)
    q[:, 7:] += 1.2 * torch.randn(6, model.nv - 6, generator=generator, dtype=torch.float64)
    qd = torch.randn(6, model.nv, generator=generator, dtype=torch.float64)
    terms = limits.implicit_terms(q, qd, dt=0.0075)
    assert (terms.spring > 0).any() and not (terms.spring > 0).all()
    active = torch.rand(terms.spring.shape, generator=generator) < 0.7
    rows = torch.nn.functional.one_hot(limits.dofs, model.nv).double()  # (L, nv)
    jacobian = terms.jacobian * rows.unsqueeze(-2)  # each joint's column at its DoF
    dense = _dense_products(terms, jacobian, active, 0.0075)
    for fast, slow in zip(terms.generalized(active, 0.0075), dense, strict=True):
        torch.testing.assert_close(fast, slow, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(
        terms.normal_velocity(qd), torch.einsum("...lv,...v->...l", jacobian[..., 2, :], qd)
    )


def test_weights_saved_with_the_points_in_the_mjcf_order_load() -> None:
    """Weights that hold the points' buffers in the MJCF's order (and the dense mask of the
    DoFs that move them) load: those come from the MJCF, only the law is restored."""
    model = mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))
    contact = ContactModel.from_mujoco(model)
    state = {k: v + 0.1 if v.is_floating_point() else v for k, v in contact.state_dict().items()}
    points = ContactPoints.from_mujoco(model)
    state |= {"body": torch.tensor(points.body), "offset": torch.zeros(len(points.body), 3),
              "moves": torch.ones(len(points.body), model.nv)}  # fmt: skip
    fresh = ContactModel.from_mujoco(model)
    fresh.load_state_dict(state)
    torch.testing.assert_close(fresh.log_stiffness, contact.log_stiffness + 0.1)
    assert torch.equal(fresh.body, contact.body) and torch.equal(fresh.offset, contact.offset)


def test_a_hinge_thrown_into_its_limit_gains_no_energy() -> None:
    """Spun at 20 rad/s into its bound at 7.5 ms steps: stepped implicitly, its kinetic energy
    never rises and it ends inside (or a hair past) its range."""
    model = mujoco.MjModel.from_xml_string(HINGE_XML)
    limits = JointLimits.from_mujoco(model)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    full = np.zeros((1, 1))
    mujoco.mj_fullM(model, data, full)
    inertia = torch.from_numpy(full)
    q, qd, dt = (
        torch.zeros(1, dtype=torch.float64),
        torch.tensor([20.0], dtype=torch.float64),
        0.0075,
    )
    energies = []
    for _ in range(100):
        terms = limits.implicit_terms(q, qd, dt)
        qdd = implicit_acceleration([terms], qd, dt, inertia, torch.zeros(1, dtype=torch.float64))
        qd = qd + dt * qdd
        q = q + dt * qd
        energies.append(float(0.5 * inertia[0, 0] * qd[0] ** 2))
    assert max(energies) <= 0.5 * float(inertia[0, 0]) * 400 * (1 + 1e-9)
    assert -0.5 - 0.05 < float(q[0]) < 0.5 + 0.05


def test_the_friction_slope_an_implicit_step_takes_is_its_derivative() -> None:
    """`Dissipation.slope` (what an implicit step adds to M, times dt) is dd/dqd, per DoF."""
    from mbrl_delan.models.lagrangian import Dissipation

    friction = Dissipation(5, coulomb=True, raw_init=0.3).double()
    qd = torch.tensor([-0.5, -0.004, 0.0, 0.003, 2.0], dtype=torch.float64)
    jacobian = torch.autograd.functional.jacobian(friction, qd)
    torch.testing.assert_close(torch.diag(jacobian), friction.slope(qd))
    assert bool((jacobian - torch.diag(torch.diag(jacobian))).abs().max() == 0)


def test_a_contact_delan_stays_finite_far_off_its_data() -> None:
    """The humanoid DeLaN with implicit contacts and limits, from states sunk up to tens of metres
    into the floor with joints wrenched and velocities of thousands: 30 steps stay finite (the
    law saturates at MAX_DEPTH)."""
    cfg = compose_train_config(["env=humanoid_stand", "model=delan", "model.contacts=true",
                                "model.joint_limits=true", "model.residual=false"])  # fmt: skip
    parts = make_env_parts("humanoid_stand", None, 10)
    torch.manual_seed(0)
    model = build_model(cfg.model, parts.system).float()
    q, qd = random_state(parts.system.mj_model(), 64, 0.9, seed=6)
    g = torch.Generator().manual_seed(0)
    q[:, :3] += 10.0 * torch.randn(64, 3, generator=g, dtype=torch.float64)
    q[:, 7:] += 10.0 * torch.randn(64, q.shape[1] - 7, generator=g, dtype=torch.float64)
    qd = 1000.0 * torch.randn(qd.shape, generator=g, dtype=torch.float64)
    action = torch.rand(64, parts.system.nu, generator=g) - 0.5
    state = model.step(q.float(), qd.float(), action)
    with torch.no_grad():
        for _ in range(29):
            state = model.step(state.q, state.qd, action)
    assert bool(torch.isfinite(state.q).all() and torch.isfinite(state.qd).all())


def test_the_stiff_implicit_solve_in_float32_matches_float64() -> None:
    """A humanoid-size system (inertia units from 0.02 to 40, 0.3 m levers) with normal gains
    of 10^6 N s/m (about 150 times the contact start's), every point pressed into the floor:
    the float32 solve (equilibrated Cholesky) gives float64's accelerations to 1e-3, and those
    satisfy (M + dt J^T K J) qdd = force + J^T (f0 - K J qd)."""
    nv, points, dt = 23, 6, 0.0075
    g = torch.Generator().manual_seed(0)
    a = torch.randn(nv, nv, generator=g, dtype=torch.float64)
    units = torch.logspace(math.log10(0.02), math.log10(40.0), nv, dtype=torch.float64).sqrt()
    mass = units[:, None] * (a @ a.T / nv + 0.05 * torch.eye(nv, dtype=torch.float64)) * units
    jacobian = 0.3 * torch.randn(points, 3, nv, generator=g, dtype=torch.float64)
    terms = ImplicitTerms(
        spring=torch.rand(points, generator=g, dtype=torch.float64) * 1e3,
        normal_gain=torch.full((points,), 1e6, dtype=torch.float64),
        tangential_gain=torch.full((points,), 1e4, dtype=torch.float64),
        jacobian=jacobian,
        velocity=torch.zeros(points, 3, dtype=torch.float64),
        columns=torch.arange(nv).expand(points, nv),  # one chain: every DoF moves every point
        nv=nv,
        chains=((0, points, nv),),
        pairs=torch.arange(nv * nv),
    )
    qd = torch.zeros(nv, dtype=torch.float64)
    push = -1e4 * jacobian[:, 2].sum(0)  # presses every point down
    force = push + torch.randn(nv, generator=g, dtype=torch.float64)
    exact = implicit_acceleration([terms], qd, dt, mass, force)
    floats = ("spring", "normal_gain", "tangential_gain", "jacobian", "velocity")
    f32 = dataclasses.replace(terms, **{k: getattr(terms, k).float() for k in floats})
    single = implicit_acceleration([f32], qd.float(), dt, mass.float(), force.float()).double()
    assert float((single - exact).norm() / exact.norm()) < 1e-3
    pushes = terms.spring - terms.normal_gain * (jacobian[:, 2] @ (qd + dt * exact)) > 0
    assert bool(pushes.all())  # every point stays in the solve
    total, added = terms.generalized(pushes, dt)
    lhs, rhs = (mass + added) @ exact, force + total
    assert float((lhs - rhs).norm() / rhs.norm()) < 1e-10
