"""The exoskeleton of `humanoid_stand_exo` (`systems.external`): its springs act as the sum of
the MJCF's and the added ones, its friction is at every hinge, and the fidelity suite's
edits add either alone."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from mbrl_delan.systems.external import (
    EXOSKELETON,
    add_exoskeleton,
    humanoid_v5_exo_xml,
    humanoid_v5_xml,
)


def spring_force(model: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    """MuJoCo's passive spring force at rest at `qpos`. (nv,)"""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    return data.qfrc_spring.copy()


def test_the_exoskeletons_springs_add_to_the_mjcfs_own() -> None:
    """At random joint angles the env's spring force minus Humanoid-v5's is -k (q - rest) of
    the added springs alone, joint by joint; the masses are the MJCF's and every hinge has
    the exoskeleton's friction."""
    plain = mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))
    exo = mujoco.MjModel.from_xml_path(str(humanoid_v5_exo_xml()))
    rng = np.random.default_rng(0)
    qpos = plain.qpos0.copy()
    hinges = [j for j in range(plain.njnt) if plain.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    for j in hinges:
        qpos[plain.jnt_qposadr[j]] = rng.uniform(-0.5, 0.5)
    added = spring_force(exo, qpos) - spring_force(plain, qpos)
    expected = np.zeros(plain.nv)
    for j in hinges:
        name = mujoco.mj_id2name(plain, mujoco.mjtObj.mjOBJ_JOINT, j)
        for suffix, stiffness, rest in EXOSKELETON.stiffness:
            if name.endswith(suffix):
                angle = qpos[plain.jnt_qposadr[j]]
                expected[plain.jnt_dofadr[j]] = -stiffness * (angle - rest)
    assert np.abs(expected).max() > 50  # the hips' and knees' springs are there
    # the env's MJCF text keeps each weighted rest angle and geom size to its printed digits
    # (about 1e-6 relative)
    np.testing.assert_allclose(added, expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(exo.body_mass, plain.body_mass, rtol=1e-5)
    dofs = plain.jnt_dofadr[hinges]
    np.testing.assert_array_equal(exo.dof_frictionloss[dofs], EXOSKELETON.frictionloss)


@pytest.mark.parametrize(("springs", "friction"), [(True, False), (False, True)])
def test_either_part_of_the_exoskeleton_alone(springs: bool, friction: bool) -> None:
    """`add_exoskeleton` with one part off leaves that part as the MJCF has it."""
    plain = mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))
    spec = mujoco.MjSpec.from_file(str(humanoid_v5_xml()))
    add_exoskeleton(spec, springs=springs, friction=friction)
    edited = spec.compile()
    assert (edited.dof_frictionloss.max() == EXOSKELETON.frictionloss) == friction
    assert (not np.array_equal(edited.jnt_stiffness, plain.jnt_stiffness)) == springs


def test_random_episodes_without_contacts_fall_freely_and_move_the_joints_as_without_gravity(
) -> None:  # fmt: skip
    """The fidelity suite's contact-free data (`random_episodes(..., contacts=False)`): each
    episode lasts `FREE_FALL_STEPS`, the root falls about g t^2 / 2, and the hinges follow
    the same controls exactly as in a copy of the physics without gravity (gravity acts
    alike on every body of a falling one)."""
    import torch

    from mbrl_delan import keys
    from mbrl_delan.benchmarks.fidelity import FREE_FALL_STEPS, random_episodes
    from mbrl_delan.envs import make_env_parts

    parts = make_env_parts("humanoid_stand_exo")
    data = random_episodes(parts, FREE_FALL_STEPS, 0, contacts=False)
    assert data.shape[0] == FREE_FALL_STEPS  # one whole episode: nothing ended it
    seconds = FREE_FALL_STEPS * parts.physics.control_dt
    fall = float(data[keys.Q][0, 2] - data[keys.NEXT_Q][-1, 2])
    assert fall == pytest.approx(0.5 * 9.81 * seconds**2, rel=0.05)
    model = parts.physics.mj_model()
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    model.opt.gravity[:] = 0.0
    state = mujoco.MjData(model)
    state.qpos[:], state.qvel[:] = data[keys.Q][0].numpy(), data[keys.QD][0].numpy()
    for action, q_next in zip(data[keys.ACTION].numpy(), data[keys.NEXT_Q], strict=True):
        state.ctrl[:] = action
        mujoco.mj_step(model, state, nstep=parts.physics.frame_skip)
        torch.testing.assert_close(torch.from_numpy(state.qpos[7:].copy()), q_next[7:],
                                   atol=1e-6, rtol=0)  # fmt: skip
