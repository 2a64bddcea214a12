"""Torch forward kinematics against MuJoCo's own `mj_kinematics` on both humanoids."""

import mujoco
import numpy as np
import pytest
import torch

from mbrl_delan.systems.external import humanoid_cmu_xml, humanoid_v5_xml
from mbrl_delan.systems.forward_kinematics import ForwardKinematics, quat_rotate
from mbrl_delan.systems.system import asset_path


def random_q(model: mujoco.MjModel, rng: np.random.Generator) -> np.ndarray:
    """qpos0 moved by up to 1.5 rad per hinge, a random root pose (unnormalised quaternion)."""
    q = model.qpos0.copy()
    for j in range(model.njnt):
        adr, kind = model.jnt_qposadr[j], model.jnt_type[j]
        if kind == mujoco.mjtJoint.mjJNT_FREE:
            q[adr : adr + 3] = rng.normal(0.0, 1.0, 3)
            q[adr + 3 : adr + 7] = rng.normal(0.0, 1.0, 4) * rng.uniform(0.5, 2.0)
        elif kind == mujoco.mjtJoint.mjJNT_BALL:
            q[adr : adr + 4] = rng.normal(0.0, 1.0, 4)
        else:
            q[adr] += rng.uniform(-1.5, 1.5)
    return q


def mujoco_poses(model: mujoco.MjModel, q: np.ndarray) -> tuple[np.ndarray, ...]:
    data = mujoco.MjData(model)
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    return data.xpos.copy(), data.xquat.copy(), data.site_xpos.copy()


def same_rotation(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """|<a, b>| = 1 for unit quaternions of the same rotation (q and -q)."""
    return (a * b).sum(-1).abs()


@pytest.mark.parametrize("xml", [humanoid_v5_xml, humanoid_cmu_xml], ids=["humanoid_v5", "cmu"])
def test_matches_mujoco_kinematics_on_humanoids(xml) -> None:
    model = mujoco.MjModel.from_xml_path(str(xml()))
    fk = ForwardKinematics.from_mujoco(model)
    rng = np.random.default_rng(0)
    qs = np.stack([random_q(model, rng) for _ in range(8)])
    poses = fk(torch.from_numpy(qs))  # one batched call
    assert poses.xpos.shape == (8, model.nbody, 3) and poses.site_xpos.shape[-2] == model.nsite
    for i, q in enumerate(qs):
        xpos, xquat, site_xpos = (torch.from_numpy(x) for x in mujoco_poses(model, q))
        torch.testing.assert_close(poses.xpos[i], xpos, rtol=0, atol=1e-5)
        alignment = same_rotation(poses.xquat[i], xquat)
        torch.testing.assert_close(alignment, torch.ones_like(alignment), rtol=0, atol=1e-5)
        torch.testing.assert_close(poses.site_xpos[i], site_xpos, rtol=0, atol=1e-5)


def test_slide_joints_and_float32() -> None:
    model = mujoco.MjModel.from_xml_path(str(asset_path("cartpole")))
    fk = ForwardKinematics.from_mujoco(model)
    q = random_q(model, np.random.default_rng(1))
    xpos, _, _ = mujoco_poses(model, q)
    poses = fk(torch.from_numpy(q).float())
    assert poses.xpos.dtype == torch.float32
    torch.testing.assert_close(poses.xpos, torch.from_numpy(xpos).float(), rtol=0, atol=1e-5)


def test_quat_rotate_quarter_turn_about_z() -> None:
    quarter = torch.tensor([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)], dtype=torch.float64)
    out = quat_rotate(quarter, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(out, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))


BALL_SLIDE_XML = """
<mujoco>
  <worldbody>
    <body pos="0 0 1">
      <joint type="slide" axis="1 0 0"/>
      <joint type="hinge" axis="0 1 0" pos="0 0 0.1"/>
      <geom type="capsule" size="0.05 0.2"/>
      <body pos="0 0.3 0">
        <joint type="ball" pos="0 0 0.05"/>
        <geom type="sphere" size="0.05"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize(
    "model",
    [
        pytest.param(
            lambda: mujoco.MjModel.from_xml_path(str(humanoid_v5_xml())), id="humanoid_v5"
        ),
        pytest.param(lambda: mujoco.MjModel.from_xml_path(str(humanoid_cmu_xml())), id="cmu"),
        pytest.param(lambda: mujoco.MjModel.from_xml_string(BALL_SLIDE_XML), id="ball_slide"),
    ],
)
def test_dof_axes_give_mujocos_point_jacobians(model) -> None:
    """J(p) from each DoF's axis (translations: the axis; rotations: axis x (p - anchor), over
    the DoFs above p's body) equals `mj_jac` at a point of every body."""
    model = model()
    fk = ForwardKinematics.from_mujoco(model)
    q = random_q(model, np.random.default_rng(2))
    poses, axes = fk.dof_axes(torch.from_numpy(q))
    assert axes.axis.shape == axes.anchor.shape == (model.nv, 3)
    torch.testing.assert_close(poses.xpos, fk(torch.from_numpy(q)).xpos)
    data = mujoco.MjData(model)
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    rotational = torch.tensor(fk.rotational)
    for body in range(1, model.nbody):
        point = torch.from_numpy(data.xpos[body] + np.array([0.05, -0.02, 0.1]))
        turn = torch.linalg.cross(axes.axis, point - axes.anchor, dim=-1)
        above = torch.tensor([_is_above(fk.parent, d, body) for d in fk.dof_body])
        columns = torch.where(rotational[:, None], turn, axes.axis) * above[:, None]
        jacp = np.zeros((3, model.nv))
        mujoco.mj_jac(model, data, jacp, None, point.numpy(), body)
        np.testing.assert_allclose(columns.T.numpy(), jacp, atol=1e-10)


def _is_above(parent: list[int], ancestor: int, body: int) -> bool:
    while body > 0:
        if body == ancestor:
            return True
        body = parent[body]
    return False


def test_the_first_bodies_alone_match_the_whole_tree() -> None:
    model = mujoco.MjModel.from_xml_path(str(humanoid_cmu_xml()))
    fk = ForwardKinematics.from_mujoco(model)
    q = torch.from_numpy(random_q(model, np.random.default_rng(3)))
    whole, first = fk(q), fk(q, nbody=5)
    assert first.xpos.shape == (5, 3) and first.site_xpos.shape == (0, 3)
    torch.testing.assert_close(first.xpos, whole.xpos[:5])
    torch.testing.assert_close(first.xquat, whole.xquat[:5])


@pytest.mark.slow
@pytest.mark.parametrize("compiled", [False, True])
def test_constants_first_built_under_inference_mode_serve_autograd(compiled: bool) -> None:
    """A tree first used while planning (inference mode, eager or compiled, as a resumed run
    plans before it fits) then in a fit: the positions' gradient flows."""
    from mbrl_delan.accelerate import compile_dynamics

    model = mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))
    fk = ForwardKinematics.from_mujoco(model)
    q0 = torch.tensor(model.qpos0, dtype=torch.float32).expand(4, -1).clone()
    plan = lambda q: fk.dof_axes(q)[0].xpos  # noqa: E731
    with torch.inference_mode():
        (compile_dynamics(plan) if compiled else plan)(q0)
    q = q0.clone().requires_grad_(True)
    fk.dof_axes(q)[0].xpos[..., 2].sum().backward()
    assert q.grad is not None and torch.isfinite(q.grad).all()


def test_traces_whole_once_constants_are_placed() -> None:
    """Planning compiles the kinematics as one graph: the constants' inference-mode check
    (see `placed`) must not break it once they exist, as they do from the second step on."""
    model = mujoco.MjModel.from_xml_path(str(humanoid_v5_xml()))
    fk = ForwardKinematics.from_mujoco(model)
    q = torch.tensor(model.qpos0, dtype=torch.float32).expand(4, -1).clone()
    with torch.inference_mode():
        fk.dof_axes(q)  # places the constants
        explained = torch._dynamo.explain(lambda q: fk.dof_axes(q)[0].xpos)(q)
    assert explained.graph_break_count == 0, explained.break_reasons
