"""`humanoid_stand_tendon` (`systems.external.BANDS`): each band's force on its joints is the
analytic band's, -k (L - rest) c_j with L = sum_j c_j q_j; the env is registered with the
bands in its physics only; the fidelity suite's `coupled_stiffness_error` is zero for the
env's own potential and large for the plain MJCF's, which lacks the coupling."""

from __future__ import annotations

from types import SimpleNamespace

import mujoco
import numpy as np
import torch

from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.models.base import RigidBody
from mbrl_delan.models.inertial import rigid_body_at
from mbrl_delan.systems.external import BANDS, humanoid_v5_tendon_xml, humanoid_v5_xml
from mbrl_delan.training.fidelity import RigidBodyTruth, _coupled_stiffness_figures, leg_joints
from tests.test_exoskeleton import spring_force


def _random_pose(model: mujoco.MjModel, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    qpos = model.qpos0.copy()
    for j in range(model.njnt):
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
            qpos[model.jnt_qposadr[j]] = rng.uniform(-0.6, 0.6)
    return qpos


def test_each_band_pulls_its_joints_as_the_analytic_band() -> None:
    plain = mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))
    banded = mujoco.MjModel.from_xml_path(str(humanoid_v5_tendon_xml()))
    np.testing.assert_allclose(banded.body_mass, plain.body_mass, rtol=1e-5)  # XML digits
    np.testing.assert_allclose(banded.jnt_stiffness, plain.jnt_stiffness, rtol=1e-5)
    for seed in range(3):
        qpos = _random_pose(plain, seed)
        added = spring_force(banded, qpos) - spring_force(plain, qpos)
        expected = np.zeros(plain.nv)
        for band in BANDS:
            joints = [(plain.joint(name), c) for name, c in band.joints]
            length = sum(c * qpos[j.qposadr[0]] for j, c in joints)
            for j, c in joints:
                expected[j.dofadr[0]] -= band.stiffness * (length - band.rest) * c
        np.testing.assert_allclose(added, expected, atol=1e-9)
        coupled = [v for v in range(plain.nv) if expected[v] != 0]
        assert len(coupled) == 5  # both hips' flexion, both knees, the abdomen's flexion


def test_the_env_simulates_the_bands_and_gives_its_models_the_plain_mjcf() -> None:
    parts = make_env_parts("humanoid_stand_tendon")
    own = parts.system.mj_model().ntendon  # Humanoid-v5's two, without springs
    assert parts.physics.mj_model().ntendon == own + len(BANDS)
    assert not parts.system.mj_model().tendon_stiffness.any()


class _MujocoPotential:
    """A stand-in world model whose rigid body is MuJoCo's of `model`."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model

    def rigid_body(self, q: torch.Tensor) -> RigidBody:
        mass, force = rigid_body_at(self.model, q.numpy())
        return RigidBody(torch.from_numpy(mass), torch.from_numpy(force), torch.eye(1))


def test_coupled_stiffness_error_is_zero_for_the_env_and_large_without_the_bands() -> None:
    parts = make_env_parts("humanoid_stand_tendon")
    physics, plain = parts.physics.mj_model(), parts.system.mj_model()
    q = torch.from_numpy(np.stack([_random_pose(physics, s) for s in range(4)]))
    truth = RigidBodyTruth.of(parts.physics, q, parts.system)
    assert truth.legs is not None and len(leg_joints(physics)) == 9  # abdomen_y, 2 x (3 + 1)
    place = SimpleNamespace(device="cpu", dtype=torch.float64)
    own = _coupled_stiffness_figures(_MujocoPotential(physics), truth, place)
    assert own["coupled_stiffness_error"] < 1e-6
    missing = _coupled_stiffness_figures(_MujocoPotential(plain), truth, place)
    assert missing["coupled_stiffness_error"] > 0.2
    assert RigidBodyTruth.of(make_env_parts("humanoid_stand").physics, q).legs is None
