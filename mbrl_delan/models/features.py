"""Input features of q with their exact forward- and reverse-mode derivatives in velocity space.

Per joint (MuJoCo layout):
- unlimited hinge: (sin q, cos q);
- limited hinge, slide: q standardised with the training data's mean and std (set by
  `standardize`; a coordinate that does not move in the data is only centred) and softly
  bounded, b tanh(z / b) with b = `PLAIN_BOUND`: about z within
  the data, never beyond +-b, so a far-away position cannot blow up the network;
- ball: the 9 entries of its rotation matrix R (smooth, and blind to the quaternion's sign);
- free: the root height z and R; the x/y position is left out (the physics does not depend
  on it), unless `translation_invariant=False`; `root_height=False` also leaves z out (for
  models whose only dependence on the height is gravity's linear potential, or none).
  `yaw_invariant=True` keeps only R's last row, e_z^T R (the world's vertical in the root's
  frame: its tilt), which does not change when the body turns about the vertical.

DeLaN differentiates the features along a generalized velocity. Angular velocities of ball
and free joints are body-frame (quasi-velocities), so the derivative of R along omega is
R [omega]x, the derivative of q (+) eps v at eps = 0 (`integrate_pos`). `jvp` carries a
velocity to the features' rate of change; `vjp` brings a cotangent on the features back to
velocity space. Both are a few elementwise operations.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from mbrl_delan.systems.forward_kinematics import quat_to_mat as rotation_matrix
from mbrl_delan.systems.system import BALL, FREE, HINGE, JointLayout

PLAIN_BOUND = 5.0  # plain features saturate at +-5 standard deviations of the data
PLAIN_MIN_STD = 1e-3  # a plain coordinate with a smaller std in the data is held still


def skew(v: Tensor) -> Tensor:
    """(..., 3) -> (..., 3, 3) with skew(v) u = v x u."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    rows = ((o, -z, y), (z, o, -x), (-y, x, o))
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def unskew_of_rt(R: Tensor, G: Tensor) -> Tensor:
    """The omega-cotangent of a cotangent G on R, for dR = R [omega]x. (..., 3, 3) -> (..., 3)."""
    A = R.transpose(-1, -2) @ G
    return torch.stack(
        (A[..., 2, 1] - A[..., 1, 2], A[..., 0, 2] - A[..., 2, 0], A[..., 1, 0] - A[..., 0, 1]),
        dim=-1,
    )


class QFeatures(nn.Module):
    """phi(q): (..., nq) -> (..., n_features), with jvp/vjp in velocity space (nv)."""

    def __init__(
        self,
        layout: JointLayout,
        translation_invariant: bool = True,
        bound_plain: bool = True,
        root_height: bool = True,
        freeze_still: bool = False,
        yaw_invariant: bool = False,
    ) -> None:
        """`bound_plain=False` gives the plain coordinates as they are (for models that
        standardise their inputs themselves); `root_height=False` leaves a free joint's
        height out (with `translation_invariant`: no position of the root at all).
        `freeze_still`: a plain coordinate that does not move in the data given to
        `standardize` becomes a constant feature 0 with zero derivative (``plain_still``
        marks it): nothing the network computes depends on it. `yaw_invariant`: a free
        joint's features are its tilt (and height), not its heading (needs
        `translation_invariant`)."""
        super().__init__()
        if yaw_invariant and not translation_invariant:
            raise ValueError("yaw_invariant features need translation_invariant=True")
        periodic, plain_q, plain_v, rotations, positions = [], [], [], [], []
        tilts = []
        for jtype, qa, va, limited in zip(
            layout.types, layout.qpos_adr, layout.dof_adr, layout.limited, strict=True
        ):
            if jtype == HINGE and not limited:
                periodic.append((qa, va))
            elif jtype == FREE:
                coords = ((2,) if root_height else ()) if translation_invariant else (0, 1, 2)
                positions += [(qa + k, va + k) for k in coords]
                (tilts if yaw_invariant else rotations).append((qa + 3, va + 3))
            elif jtype == BALL:
                rotations.append((qa, va))
            else:  # slide, limited hinge
                plain_q.append(qa)
                plain_v.append(va)
        plain_q += [p[0] for p in positions]
        plain_v += [p[1] for p in positions]
        self._index("periodic_q", [p[0] for p in periodic])
        self._index("periodic_v", [p[1] for p in periodic])
        self._index("plain_q", plain_q)
        self._index("plain_v", plain_v)
        self._index("rot_q", [[r[0] + k for k in range(4)] for r in rotations], (0, 4))
        self._index("rot_v", [[r[1] + k for k in range(3)] for r in rotations], (0, 3))
        self._index("tilt_q", [[r[0] + k for k in range(4)] for r in tilts], (0, 4))
        self._index("tilt_v", [[r[1] + k for k in range(3)] for r in tilts], (0, 3))
        self.n_periodic, self.n_plain, self.n_rot = len(periodic), len(plain_q), len(rotations)
        self.n_tilt = len(tilts)
        self.nq, self.nv = layout.nq, layout.nv
        self.n_features = 2 * self.n_periodic + self.n_plain + 9 * self.n_rot + 3 * self.n_tilt
        self.bound_plain, self.freeze_still = bound_plain, freeze_still
        self.register_buffer("plain_mean", torch.zeros(self.n_plain))
        self.register_buffer("plain_std", torch.ones(self.n_plain))
        if freeze_still:  # 1: held still in the data, frozen
            self.register_buffer("plain_still", torch.zeros(self.n_plain))
        self._index("velocity_order", self._velocity_order())

    @torch.no_grad()
    def standardize(self, q: Tensor) -> None:
        """Set the plain features' mean and std from positions (N, nq).

        A coordinate whose std is below `PLAIN_MIN_STD` does not move in the data (a joint
        held still): it is only centred (std 1), so its feature's derivative stays O(1)
        instead of 1 / PLAIN_MIN_STD (which would blow up DeLaN's Coriolis terms)."""
        plain = _take(q.reshape(-1, q.shape[-1]), self.plain_q).to(self.plain_mean.dtype)
        if self.n_plain and plain.shape[0] > 1:
            std = plain.std(dim=0)  # (n_plain,)
            self.plain_mean.copy_(plain.mean(dim=0))
            self.plain_std.copy_(torch.where(std >= PLAIN_MIN_STD, std, torch.ones_like(std)))
            if self.freeze_still:
                self.plain_still.copy_((std < PLAIN_MIN_STD).to(self.plain_still))

    def _plain(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Bounded standardised plain features and their derivative per unit of q. (..., m)"""
        if not self.bound_plain:
            plain = _take(q, self.plain_q)
            return plain, torch.ones_like(plain)
        z = (_take(q, self.plain_q) - self.plain_mean) / self.plain_std
        bounded = torch.tanh(z / PLAIN_BOUND)
        value, slope = PLAIN_BOUND * bounded, (1.0 - bounded * bounded) / self.plain_std
        if self.freeze_still:
            moving = 1.0 - self.plain_still
            return value * moving, slope * moving
        return value, slope

    def _index(self, name: str, values: list, empty_shape: tuple[int, ...] = (0,)) -> None:
        t = torch.tensor(values, dtype=torch.long) if values else torch.zeros(empty_shape).long()
        self.register_buffer(name, t, persistent=False)

    def _velocity_order(self) -> list[int]:
        """Each velocity index's place in [periodic, plain, rotation, tilt, zero] cotangents."""
        placed = (
            self.periodic_v.tolist()
            + self.plain_v.tolist()
            + self.rot_v.flatten().tolist()
            + self.tilt_v.flatten().tolist()
        )
        where = {v: i for i, v in enumerate(placed)}
        return [where.get(v, len(placed)) for v in range(self.nv)]

    def _rotations(self, q: Tensor, index: Tensor | None = None) -> Tensor:
        """(..., nq) -> (..., K, 3, 3) of the joints in `index` (K, 4) (default `rot_q`)."""
        index = self.rot_q if index is None else index
        return rotation_matrix(_take(q, index.flatten()).unflatten(-1, (index.shape[0], 4)))

    def forward(self, q: Tensor) -> Tensor:
        """(..., nq) -> (..., n_features)."""
        qp = _take(q, self.periodic_q)
        parts = [torch.sin(qp), torch.cos(qp), self._plain(q)[0]]
        if self.n_rot:
            parts.append(self._rotations(q).flatten(-3))
        if self.n_tilt:
            parts.append(self._rotations(q, self.tilt_q)[..., 2, :].flatten(-2))
        return torch.cat(parts, dim=-1)

    def jvp(self, q: Tensor, v: Tensor) -> Tensor:
        """d phi(q (+) eps v) / d eps at 0: (..., nq), (..., nv) -> (..., n_features)."""
        qp, vp = _take(q, self.periodic_q), _take(v, self.periodic_v)
        parts = [
            torch.cos(qp) * vp,
            -torch.sin(qp) * vp,
            self._plain(q)[1] * _take(v, self.plain_v),
        ]
        if self.n_rot:
            omega = _take(v, self.rot_v.flatten()).unflatten(-1, (self.n_rot, 3))
            parts.append((self._rotations(q) @ skew(omega)).flatten(-3))
        if self.n_tilt:  # e_z^T R [omega]x
            omega = _take(v, self.tilt_v.flatten()).unflatten(-1, (self.n_tilt, 3))
            rate = self._rotations(q, self.tilt_q)[..., 2:3, :] @ skew(omega)  # (..., K, 1, 3)
            parts.append(rate.flatten(-3))
        return torch.cat(parts, dim=-1)

    def vjp(self, q: Tensor, cotangent: Tensor) -> Tensor:
        """Cotangent on the features -> cotangent in velocity space: (..., nf) -> (..., nv)."""
        k, m = self.n_periodic, self.n_plain
        qp = _take(q, self.periodic_q)
        c_sin, c_cos = cotangent[..., :k], cotangent[..., k : 2 * k]
        parts = [
            torch.cos(qp) * c_sin - torch.sin(qp) * c_cos,
            self._plain(q)[1] * cotangent[..., 2 * k : 2 * k + m],
        ]
        r = 2 * k + m + 9 * self.n_rot
        if self.n_rot:
            G = cotangent[..., 2 * k + m : r].unflatten(-1, (self.n_rot, 3, 3))
            parts.append(unskew_of_rt(self._rotations(q), G).flatten(-2))
        if self.n_tilt:  # a cotangent on R's last row only
            row = cotangent[..., r:].unflatten(-1, (self.n_tilt, 1, 3))
            G = torch.cat([torch.zeros_like(row), torch.zeros_like(row), row], dim=-2)
            parts.append(unskew_of_rt(self._rotations(q, self.tilt_q), G).flatten(-2))
        parts.append(cotangent.new_zeros(cotangent.shape[:-1] + (1,)))
        return _take(torch.cat(parts, dim=-1), self.velocity_order)


def _take(x: Tensor, index: Tensor) -> Tensor:
    """x[..., index] for a 1-d index (index_select: faster than advanced indexing)."""
    return x.index_select(-1, index)
