"""DeLaN at extreme inputs: finite outputs, bounded features, and data-set safety limits."""

import pytest
import torch
from tensordict import TensorDict

from mbrl_delan import keys
from mbrl_delan.models.delan import DeLaN
from mbrl_delan.models.features import PLAIN_BOUND, QFeatures
from mbrl_delan.models.structure import Structure
from mbrl_delan.systems.system import FREE, HINGE, SLIDE, JointLayout

# a cart (slide), a pole (hinge) and a floating body (free joint): every feature kind
MIXED = JointLayout(
    types=(SLIDE, HINGE, FREE),
    qpos_adr=(0, 1, 2),
    dof_adr=(0, 1, 2),
    limited=(False, False, False),
)
NQ, NV = MIXED.nq, MIXED.nv


def _model(dtype: torch.dtype = torch.float32, seed: int = 0) -> DeLaN:
    torch.manual_seed(seed)
    actuation = torch.zeros(NV, 2)
    actuation[0, 0] = actuation[2, 1] = 1.0  # the pole and most of the body: unactuated
    return DeLaN(MIXED, actuation, control_dt=0.02).to(dtype)


def _quat(batch: int, g: torch.Generator) -> torch.Tensor:
    quat = torch.randn(batch, 4, generator=g)
    return quat / quat.norm(dim=-1, keepdim=True)


def _extreme_states(batch: int = 256) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Slide and root positions at 1e4, hinge angles at 1e4 rad, speeds of 1e3, big torques."""
    g = torch.Generator().manual_seed(0)
    q = torch.zeros(batch, NQ)
    q[:, 0] = 1e4 * torch.randn(batch, generator=g)  # cart
    q[:, 1] = 1e4 * torch.randn(batch, generator=g)  # pole angle
    q[:, 2:5] = 1e4 * torch.randn(batch, 3, generator=g)  # root position
    q[:, 5:9] = _quat(batch, g)
    q[: batch // 4, 5:9] *= 1e-9  # near-zero (unnormalised) quaternions
    qd = 1e3 * torch.randn(batch, NV, generator=g)
    action = 1e3 * torch.randn(batch, 2, generator=g)
    return q, qd, action


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_untrained_model_step_is_finite_at_extreme_states(dtype: torch.dtype) -> None:
    """Without any data the default limits (|qd| <= 100) keep every output finite."""
    model = _model(dtype)
    q, qd, action = (x.to(dtype) for x in _extreme_states())
    with torch.inference_mode():
        nxt = model.step(q, qd, action)
        for _ in range(20):  # and it stays finite when rolled out
            nxt = model.step(nxt.q, nxt.qd, action)
    assert torch.isfinite(nxt.q).all() and torch.isfinite(nxt.qd).all()
    assert nxt.qd.abs().max() <= 100.0


def test_without_the_velocity_clamp_the_same_states_overflow() -> None:
    """The clamp is what keeps the step finite: with it lifted, float32 overflows."""
    model = _model(torch.float32)
    model.velocity_limit.fill_(float("inf"))
    q, qd, action = _extreme_states()
    with torch.inference_mode():
        nxt = model.step(q, qd, action)
        for _ in range(20):
            nxt = model.step(nxt.q, nxt.qd, action)
    assert not (torch.isfinite(nxt.q).all() and torch.isfinite(nxt.qd).all())


def _data(n: int = 512) -> TensorDict:
    g = torch.Generator().manual_seed(3)
    q = torch.zeros(n, NQ)
    q[:, 0] = 2.0 + 0.5 * torch.randn(n, generator=g)
    q[:, 1] = torch.randn(n, generator=g)
    q[:, 2:5] = torch.randn(n, 3, generator=g)
    q[:, 5:9] = _quat(n, g)
    qd = torch.randn(n, NV, generator=g)
    return TensorDict(
        {
            keys.Q: q,
            keys.QD: qd,
            keys.ACTION: torch.randn(n, 2, generator=g),
            keys.NEXT_Q: q.clone(),
            keys.NEXT_QD: 1.5 * qd,
        },
        batch_size=[n],
    )


def test_fit_normalization_sets_velocity_limit_and_feature_statistics() -> None:
    model = _model(torch.float64)
    data = _data().to(torch.float64)
    model.fit_normalization(data)
    largest = torch.cat([data[keys.QD], data[keys.NEXT_QD]]).abs().amax(0)
    torch.testing.assert_close(model.velocity_limit, model.velocity_margin * largest)
    features = model.dynamics.field.features
    plain = torch.cat([data[keys.Q], data[keys.NEXT_Q]])[:, features.plain_q]
    torch.testing.assert_close(features.plain_mean, plain.mean(0))
    torch.testing.assert_close(features.plain_std, plain.std(0))
    assert features.plain_mean[0] == pytest.approx(2.0, abs=0.1)  # the cart's mean position
    q, qd, action = (x.double() for x in _extreme_states())
    with torch.inference_mode():
        nxt = model.step(q, qd, action)
    assert (nxt.qd.abs() <= model.velocity_limit).all()


def test_unactuated_dofs_get_the_set_scale_not_the_floor() -> None:
    """tau = 0 on unactuated DoFs: their scale is unactuated_torque_scale x the largest std."""
    model = _model(torch.float64)
    data = _data().to(torch.float64)
    tau = model.dynamics.generalized_force(data[keys.ACTION])
    for factor in (1.0, 10.0):
        model.unactuated_torque_scale = factor
        model.fit_normalization(data)
        actuated = tau[:, [0, 2]].std(0)
        expected = torch.full((NV,), factor * float(actuated.max()), dtype=torch.float64)
        expected[[0, 2]] = actuated
        torch.testing.assert_close(model.tau_scale, expected)


def test_plain_features_are_bounded_and_their_derivatives_exact() -> None:
    """Standardised plain features saturate at +-PLAIN_BOUND; jvp and vjp equal autograd."""
    torch.set_default_dtype(torch.float64)
    try:
        features = QFeatures(MIXED)
        features.standardize(_data()[keys.Q].double())
        q, _, _ = _extreme_states(8)
        q = q.double()
        assert features(q)[:, 2 * features.n_periodic :][:, : features.n_plain].abs().max() <= (
            PLAIN_BOUND
        )
        q = _data(8)[keys.Q].double()  # moderate states for the derivative check
        v = torch.randn(8, NV, dtype=torch.float64)
        cot = torch.randn(8, features.n_features, dtype=torch.float64)
        # plain coordinates and hinge angles add v in q; compare on those velocity entries
        mask = torch.zeros(NV, dtype=torch.float64)
        mask[:5] = 1.0
        v = v * mask
        eps_q = torch.zeros(8, NQ, dtype=torch.float64)
        eps_q[:, :5] = v[:, :5]
        jvp_auto = torch.func.jvp(features, (q,), (eps_q,))[1]
        torch.testing.assert_close(features.jvp(q, v), jvp_auto)
        grad_auto = torch.func.vjp(features, q)[1](cot)[0][:, :5]
        torch.testing.assert_close(features.vjp(q, cot)[:, :5], grad_auto)
    finally:
        torch.set_default_dtype(torch.float32)


def test_unit_scales_keep_the_equations_exact() -> None:
    """With row and energy scales set (M = D L~ L~^T D, V = s V~), Coriolis and gravity still
    equal autograd over M(q) and V(q), and the diagonal floor scales with D."""
    torch.set_default_dtype(torch.float64)
    try:
        torch.manual_seed(0)
        layout = JointLayout(
            types=(HINGE,) * 3, qpos_adr=(0, 1, 2), dof_adr=(0, 1, 2), limited=(False,) * 3
        )
        model = DeLaN(
            layout, torch.eye(3), control_dt=0.01, structure=Structure(hidden=16, dissipation=False)
        )
        field = model.dynamics.field
        field.row_scale.copy_(torch.tensor([5.0, 0.3, 1.7]))
        field.energy_scale.fill_(40.0)
        g = torch.Generator().manual_seed(2)
        q, qd = torch.randn(4, 3, generator=g), torch.randn(4, 3, generator=g)
        terms = model.terms(q, qd)
        for i in range(4):

            def mass(x: torch.Tensor) -> torch.Tensor:
                return model.terms(x[None], torch.zeros(1, 3)).mass_matrix[0]

            def potential(x: torch.Tensor) -> torch.Tensor:
                return model.terms(x[None], torch.zeros(1, 3)).potential_energy[0]

            dM = torch.autograd.functional.jacobian(mass, q[i])  # (3, 3, 3): dM_jk / dq_l
            v = qd[i]
            coriolis = (dM @ v) @ v - 0.5 * torch.einsum("j,jkl,k->l", v, dM, v)
            torch.testing.assert_close(terms.coriolis[i], coriolis)
            gravity = torch.autograd.functional.jacobian(potential, q[i])
            torch.testing.assert_close(terms.gravity[i], gravity)
        diag = torch.diagonal(terms.cholesky, dim1=-2, dim2=-1)
        assert (diag >= field.row_scale * field.diag_shift).all()
        torch.testing.assert_close(terms.mass_matrix, terms.cholesky @ terms.cholesky.mT)
    finally:
        torch.set_default_dtype(torch.float32)


def test_inertia_scaling_sets_units_from_the_data() -> None:
    """D_i^2 = std(tau_i) / std(qdd_i); an unactuated DoF gets the others' geometric mean."""
    model = DeLaN(
        MIXED, torch.eye(NV)[:, [0, 2]], control_dt=0.02, structure=Structure(inertia_scaling=True)
    ).double()
    data = _data().to(torch.float64)
    data[keys.QDD] = 3.0 * torch.randn(data.shape[0], NV, dtype=torch.float64)
    model.fit_normalization(data)
    tau = model.dynamics.generalized_force(data[keys.ACTION])
    inertia = tau[:, [0, 2]].std(0) / data[keys.QDD][:, [0, 2]].std(0)
    field = model.dynamics.field
    torch.testing.assert_close(field.row_scale[[0, 2]], inertia.sqrt())
    torch.testing.assert_close(field.row_scale[1], inertia.log().mean().exp().sqrt())
    assert float(field.energy_scale) == pytest.approx(float(tau.std(0).max()))


def test_held_still_coordinates_are_only_centred() -> None:
    """A plain coordinate that does not move in the data gets std 1, not a tiny std that
    would multiply its feature derivative (and DeLaN's Coriolis terms) by ~1 / std."""
    features = QFeatures(MIXED)
    q = _data()[keys.Q].double()
    q[:, 0] = 0.7 + 1e-12 * torch.randn(q.shape[0], dtype=torch.float64)  # cart held still
    features.standardize(q)
    assert float(features.plain_std[0]) == 1.0
    assert float(features.plain_mean[0]) == pytest.approx(0.7)
    assert float(features.plain_std[1]) == pytest.approx(float(q[:, 4].std()))  # root height


def test_inertia_scaling_treats_round_off_motion_as_held_still() -> None:
    """A DoF whose qdd and qd are round-off (a joint held still in the data) but whose torque
    varies gets std(tau) over the others' geometric-mean qdd std as its inertia unit, not
    std(tau) / 1e-14, and the others' geometric-mean viscous unit; the viscous unit uses
    rms(qd)."""
    model = DeLaN(
        MIXED, torch.eye(NV), control_dt=0.02, structure=Structure(inertia_scaling=True)
    ).double()
    data = _data().to(torch.float64)
    n = data.shape[0]
    g = torch.Generator().manual_seed(5)
    data[keys.ACTION] = torch.randn(n, NV, generator=g, dtype=torch.float64)
    data[keys.QDD] = 3.0 * torch.randn(n, NV, generator=g, dtype=torch.float64)
    data[keys.QDD][:, 1] *= 1e-14
    data[keys.QD][:, 1] *= 1e-15
    data[keys.QD][:, 3] += 4.0  # a mean speed: the viscous unit follows rms, not std
    model.fit_normalization(data)
    tau, qdd, qd = data[keys.ACTION], data[keys.QDD], data[keys.QD]
    others = [i for i in range(NV) if i != 1]
    inertia = tau[:, others].std(0) / qdd[:, others].std(0)
    field, friction = model.dynamics.field, model.dynamics.dissipation
    torch.testing.assert_close(field.row_scale[others], inertia.sqrt())
    typical_qdd = qdd[:, others].std(0).log().mean().exp()
    torch.testing.assert_close(field.row_scale[1] ** 2, tau[:, 1].std() / typical_qdd)
    viscous = tau[:, others].std(0) / qd[:, others].pow(2).mean(0).sqrt()
    torch.testing.assert_close(friction.viscous_scale[others], viscous)
    torch.testing.assert_close(friction.viscous_scale[1], viscous.log().mean().exp())
    torch.testing.assert_close(friction.coulomb_scale, tau.std(0))
