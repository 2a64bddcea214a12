"""A rigid body's ten inertial parameters in MuJoCo's terms and as a pseudo-inertia.

pi = [m, h_x, h_y, h_z, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz]: a body's mass, first moment
(mass times centre of mass) and rotational inertia about its frame's origin, in its frame.
Its pseudo-inertia ``J = [[tr(I)/2 1 - I, h], [h^T, m]]`` is positive definite exactly when pi
is physically consistent (positive mass, inertia about the centre of mass positive definite
and satisfying the triangle inequalities); ``J = U U^T`` with U upper triangular and a
positive diagonal parametrises every consistent pi (log-Cholesky).
"""

from __future__ import annotations

import mujoco
import numpy as np

CONSISTENT_EIG = 1e-8  # a projected pseudo-inertia's eigenvalues at least this share of its largest


def moving_bodies(model: mujoco.MjModel) -> list[int]:
    """The bodies a joint moves (any with a jointed ancestor or joint of its own)."""
    moving = np.zeros(model.nbody, dtype=bool)
    for b in range(1, model.nbody):
        moving[b] = model.body_jntnum[b] > 0 or moving[model.body_parentid[b]]
    return np.flatnonzero(moving).tolist()


def inertial_parameters(model: mujoco.MjModel, body: int) -> np.ndarray:
    """A body's pi (module docstring) from MuJoCo's mass, ipos, inertia and iquat. (10,)"""
    mass, com = float(model.body_mass[body]), model.body_ipos[body]
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, model.body_iquat[body])
    rot = rot.reshape(3, 3)
    inertia = rot @ np.diag(model.body_inertia[body]) @ rot.T  # about the centre of mass
    inertia = inertia + mass * (com @ com * np.eye(3) - np.outer(com, com))  # about the origin
    return np.array([mass, *(mass * com), *_six(inertia)])


def set_inertial_parameters(model: mujoco.MjModel, body: int, pi: np.ndarray) -> None:
    """Write a body's pi (10,) into MuJoCo's mass, ipos, inertia (principal) and iquat."""
    mass = float(pi[0])
    com = pi[1:4] / mass
    inertia = _matrix(pi[4:]) - mass * (com @ com * np.eye(3) - np.outer(com, com))
    principal, axes = np.linalg.eigh(inertia)
    if np.linalg.det(axes) < 0:
        axes[:, 0] *= -1
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, axes.flatten())
    model.body_mass[body], model.body_ipos[body] = mass, com
    model.body_inertia[body], model.body_iquat[body] = principal, quat
    model.body_sameframe[body] = mujoco.mjtSameFrame.mjSAMEFRAME_NONE  # the frames now differ


def _six(inertia: np.ndarray) -> list[float]:
    return [inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2],
            inertia[1, 2]]  # fmt: skip


def _matrix(six: np.ndarray) -> np.ndarray:
    """The symmetric 3x3 of [xx, yy, zz, xy, xz, yz] (..., 6) -> (..., 3, 3)."""
    xx, yy, zz, xy, xz, yz = np.moveaxis(six, -1, 0)
    rows = [np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)]
    return np.stack(rows, -2)


def pseudo_inertia(pi: np.ndarray) -> np.ndarray:
    """J = [[tr(I)/2 1 - I, h], [h^T, m]] of pi (..., 10) -> (..., 4, 4)."""
    inertia = _matrix(pi[..., 4:])
    sigma = 0.5 * np.trace(inertia, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) - inertia
    top = np.concatenate([sigma, pi[..., 1:4, None]], -1)
    bottom = np.concatenate([pi[..., None, 1:4], pi[..., None, :1]], -1)
    return np.concatenate([top, bottom], -2)


def _pi_of_pseudo(J: np.ndarray) -> np.ndarray:
    sigma = J[..., :3, :3]
    inertia = np.trace(sigma, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) - sigma
    six = np.stack([inertia[..., i, j] for i, j in _SIX_INDEX], -1)
    return np.concatenate([J[..., 3:, 3], J[..., :3, 3], six], -1)


_SIX_INDEX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
_UPPER = np.triu_indices(4, 1)


def pi_from_cholesky(theta: np.ndarray) -> np.ndarray:
    """pi of J = U U^T, U upper triangular with diagonal exp(theta[:4]) and the entries above
    it theta[4:] (row by row): every theta is physically consistent. (..., 10) -> (..., 10)"""
    U = np.zeros((*theta.shape[:-1], 4, 4))
    idx = np.arange(4)
    U[..., idx, idx] = np.exp(theta[..., :4])
    U[..., _UPPER[0], _UPPER[1]] = theta[..., 4:]
    return _pi_of_pseudo(U @ np.swapaxes(U, -1, -2))


def cholesky_of_pi(pi: np.ndarray) -> np.ndarray:
    """theta of `pi_from_cholesky` for a pi (10,) whose J is projected onto the positive
    definite matrices first (eigenvalues at least `CONSISTENT_EIG` of the largest)."""
    eig, vec = np.linalg.eigh(pseudo_inertia(pi))
    eig = np.maximum(eig, CONSISTENT_EIG * eig.max())
    J = (vec * eig) @ vec.T
    flip = np.arange(3, -1, -1)  # J = U U^T, U upper: the lower factor of J reversed
    U = np.linalg.cholesky(J[np.ix_(flip, flip)])[np.ix_(flip, flip)]
    return np.concatenate([np.log(np.diag(U)), U[_UPPER]])


def physically_consistent(pi: np.ndarray) -> bool:
    """Whether a body's pseudo-inertia J (of pi (10,)) is positive definite."""
    return bool(np.linalg.eigvalsh(pseudo_inertia(pi))[0] > 0)


def rigid_body_at(model: mujoco.MjModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's M (S, nv, nv) and the force that holds the body still against gravity and
    its joints' springs, ``qfrc_bias - qfrc_passive`` at rest (S, nv), at configurations q
    (S, nq)."""
    data = mujoco.MjData(model)
    mass = np.zeros((q.shape[0], model.nv, model.nv))
    force = np.zeros((q.shape[0], model.nv))
    for i, qpos in enumerate(q):
        data.qpos[:], data.qvel[:] = qpos, 0.0
        mujoco.mj_forward(model, data)
        mujoco.mj_fullM(model, data, mass[i])
        force[i] = data.qfrc_bias - data.qfrc_passive
    return mass, force


def dof_stiffness(model: mujoco.MjModel) -> np.ndarray:
    """Each DoF's joint spring stiffness (MuJoCo's ``jnt_stiffness``; hinges and slides, 0 on
    free and ball joints). (nv,)"""
    scalar = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    joint = model.dof_jntid
    return np.where(np.isin(model.jnt_type[joint], scalar), model.jnt_stiffness[joint], 0.0)
