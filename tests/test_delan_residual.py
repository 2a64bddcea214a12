"""DeLaN's residual force: zero at the start, and it holds what the Lagrangian terms cannot."""

import torch

from mbrl_delan import keys
from mbrl_delan.data.synthetic import inverse_dynamics_dataset
from mbrl_delan.models.delan import DeLaN, Stepping
from mbrl_delan.models.structure import Structure
from mbrl_delan.systems.system import load_system


def make(system, residual: bool, loss: str = "forward", dissipation: bool = True) -> DeLaN:
    torch.manual_seed(0)
    structure = Structure(hidden=32, residual=residual, dissipation=dissipation)
    return DeLaN(
        system.layout, torch.eye(system.nv), system.control_dt, structure, Stepping(loss=loss)
    ).double()


def test_a_fresh_residual_is_zero_so_the_model_is_the_lagrangian_one() -> None:
    system = load_system("acrobot")
    plain, with_residual = make(system, False), make(system, True)
    g = torch.Generator().manual_seed(1)
    q, qd, a = (torch.randn(16, k, generator=g, dtype=torch.float64) for k in (2, 2, 2))
    torch.testing.assert_close(with_residual.step(q, qd, a).qd, plain.step(q, qd, a).qd)
    assert with_residual.residual is not None and plain.residual is None


def test_residual_learns_a_constant_torque_a_periodic_potential_cannot() -> None:
    """A pendulum pushed by a constant 2 N m that the actions do not include: a constant
    generalized force is no gradient of a periodic V(q), so only the residual can hold it."""
    system = load_system("pendulum")
    data = inverse_dynamics_dataset(system, 512, torch.Generator().manual_seed(0))
    data[keys.ACTION] = data["tau"] - 2.0  # tau = B a + 2: the 2 N m is not commanded
    final = {}
    for residual in (False, True):
        model = make(system, residual, loss="inverse", dissipation=False)
        model.fit_normalization(data)
        opt = torch.optim.Adam(model.parameters(), lr=3e-3)
        for _ in range(300):
            opt.zero_grad()
            out = model.loss(data)
            out.loss.backward()
            opt.step()
        final[residual] = float(model.loss(data).loss.detach())
    assert final[True] < 0.1 * final[False], final
