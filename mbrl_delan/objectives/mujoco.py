"""The MuJoCo objective (the oracle): returns of action sequences under MuJoCo's true dynamics.

Rolls out a batch of open-loop action sequences with `mujoco.rollout` (multi-threaded,
MjData reused across calls), holds each control for `system.frame_skip` MuJoCo steps, and
scores the reached states with the task's torch reward. This is the upper bound every
learned-model result is compared with.

A task that reads more of a state than q and qd (a `SensedTask`: the humanoid's balance cost
reads the centre of mass) may have MuJoCo compute it during the rollouts: it adds sensors to
the planning model and scores their values, instead of the torch kinematics of every reached
state after them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import mujoco
import numpy as np
import torch
from mujoco import rollout as mj_rollout
from torch import Tensor

from mbrl_delan.objectives.base import ObjectiveFactory, discounted_masked_return
from mbrl_delan.systems.system import State, System
from mbrl_delan.tasks.base import Task

FULLPHYSICS = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
INTEGRATORS = {
    "euler": mujoco.mjtIntegrator.mjINT_EULER,
    "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST,
    "implicit": mujoco.mjtIntegrator.mjINT_IMPLICIT,
    "rk4": mujoco.mjtIntegrator.mjINT_RK4,
}
QPOS = int(mujoco.mjtState.mjSTATE_QPOS)
QVEL = int(mujoco.mjtState.mjSTATE_QVEL)


def mujoco_threads() -> int:
    """MuJoCo's rollout threads: as many as torch's intra-op threads, which every entry
    point's ``threads`` sets (null: torch's default, one per core); one meaning for both."""
    return torch.get_num_threads()


@dataclass(frozen=True)
class PlanPhysics:
    """How the oracle's own MjModel steps while it plans; the env keeps its own physics.

    substeps: MuJoCo steps per control step (None: the env's frame_skip); the planning
        timestep is control_dt / substeps.
    integrator: one of `INTEGRATORS` (None: the MJCF's).
    """

    substeps: int | None = None
    integrator: str | None = None

    def __post_init__(self) -> None:
        if self.substeps is not None and self.substeps < 1:
            raise ValueError(f"oracle substeps must be >= 1, got {self.substeps}")
        if self.integrator is not None and self.integrator not in INTEGRATORS:
            raise ValueError(
                f"oracle integrator must be one of {sorted(INTEGRATORS)}, got {self.integrator!r}"
            )

    def model(self, system: System) -> tuple[mujoco.MjModel, int]:
        """The planning MjModel of `system` and its MuJoCo steps per control step."""
        return self.apply(system.mj_model(), system)

    def apply(self, model: mujoco.MjModel, system: System) -> tuple[mujoco.MjModel, int]:
        """`model` (a model of `system`, changed in place) stepping at this physics, and its
        MuJoCo steps per control step."""
        substeps = self.substeps or system.frame_skip
        model.opt.timestep = system.control_dt / substeps
        if self.integrator is not None:
            model.opt.integrator = INTEGRATORS[self.integrator]
        return model, substeps


ENV_PHYSICS = PlanPhysics()  # the env's own steps and integrator


def state_offset(model: mujoco.MjModel, component: int) -> int:
    """Offset of one mjtState component inside a FULLPHYSICS state vector."""
    lower = FULLPHYSICS & (component - 1)
    return mujoco.mj_stateSize(model, lower)


@runtime_checkable
class SensedTask(Protocol):
    """A task whose reward the oracle scores from sensors of its planning model."""

    def add_sensors(self, spec: mujoco.MjSpec) -> None:
        """Append the sensors the reward reads to the planning model's spec."""

    def sensed_reward(self, sensed: Tensor, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """The reward from the sensor values (..., nsensordata) of the reached states."""


def sensed_model(system: System, task: SensedTask) -> mujoco.MjModel:
    """`system`'s MjModel with `task`'s sensors (and the sites they need) appended."""
    spec = mujoco.MjSpec.from_file(str(system.xml_path))
    task.add_sensors(spec)
    return spec.compile()


class HeldControlRollout:
    """MuJoCo rollouts of piecewise-constant controls, each held for `frame_skip` physics
    steps, with `mujoco.rollout` (multi-threaded, MjData reused across calls).

    States are FULLPHYSICS vectors (nstate,). Call `close()` to stop the thread pool early; it
    is also closed when the object is garbage-collected.
    """

    def __init__(self, model: mujoco.MjModel, frame_skip: int, nthread: int = 1) -> None:
        if frame_skip < 1 or nthread < 1:
            raise ValueError(f"frame_skip and nthread must be >= 1, got {frame_skip}, {nthread}")
        self.model, self.frame_skip = model, frame_skip
        self.nstate = mujoco.mj_stateSize(model, FULLPHYSICS)
        self.qpos_at, self.qvel_at = state_offset(model, QPOS), state_offset(model, QVEL)
        self._template = mujoco.MjData(model)
        self._datas = [mujoco.MjData(model) for _ in range(nthread)]
        self._pool: mj_rollout.Rollout | None = mj_rollout.Rollout(
            nthread=nthread if nthread > 1 else 0
        )

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None

    def __del__(self) -> None:
        self.close()

    def full_state(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """FULLPHYSICS state (nstate,) at time 0 with qpos = q (nq,), qvel = qd (nv,)."""
        data = self._template
        mujoco.mj_resetData(self.model, data)
        data.qpos[:], data.qvel[:] = q, qd
        state = np.empty(self.nstate, dtype=np.float64)
        mujoco.mj_getState(self.model, data, state, FULLPHYSICS)
        return state

    def qv(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Views (q (..., nq), qd (..., nv)) of FULLPHYSICS states (..., nstate)."""
        q = state[..., self.qpos_at : self.qpos_at + self.model.nq]
        return q, state[..., self.qvel_at : self.qvel_at + self.model.nv]

    def __call__(self, states: np.ndarray, ctrl: np.ndarray) -> np.ndarray:
        """Hold ctrl (N, T, nu) from states (N, nstate), or one state (nstate,) for all N.
        -> the states after each control step (N, T, nstate)."""
        return self._run(states, ctrl, sensed=False)[0]

    def with_sensors(self, states: np.ndarray, ctrl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`__call__`'s states and the model's sensor values at each of them (N, T,
        nsensordata). MuJoCo computes a step's sensors from the state it starts from, so the
        rollout takes one more step (the last control held) for those of the last state."""
        return self._run(states, ctrl, sensed=True)

    def _run(self, states: np.ndarray, ctrl: np.ndarray, sensed: bool
             ) -> tuple[np.ndarray, np.ndarray | None]:  # fmt: skip
        if self._pool is None:
            raise RuntimeError("the MuJoCo rollout was closed")
        skip, horizon = self.frame_skip, ctrl.shape[1]
        control = np.repeat(ctrl, skip, axis=1)  # (N, T*skip, nu)
        if sensed:
            control = np.concatenate([control, control[:, -1:]], axis=1)
        control = np.ascontiguousarray(control)
        n, nstep = control.shape[0], control.shape[1]
        init = np.ascontiguousarray(np.broadcast_to(states, (n, self.nstate)))
        out = np.empty((n, nstep, self.nstate), dtype=np.float64)
        sensors = np.empty((n, nstep, self.model.nsensordata)) if sensed else None
        self._pool.rollout(self.model, self._datas, init, control, state=out, sensordata=sensors)
        reached = out[:, skip - 1 : horizon * skip : skip]
        return reached, None if sensors is None else sensors[:, skip::skip]


@dataclass
class OracleRollout:
    """States reached by a batch of rollouts and the controls actually applied."""

    states: State  # q (N, H, nq), qd (N, H, nv), float64, after each control step
    actions: Tensor  # (N, H, nu) float64, clipped to the control range
    sensors: Tensor | None = None  # (N, H, nsensordata) at those states (a `SensedTask`'s)


class MujocoObjectiveFactory(ObjectiveFactory):
    """Builds oracle objectives for start states; owns the MjModel, MjData and threads.

    Use as `factory(q0, qd0)(actions)`. `model`: the MjModel to plan on and its steps per
    control step (None: the system's at `physics`, with the task's sensors for a
    `SensedTask`). Call `close()` (or use `with`) to stop the thread pool early; it is also
    closed when the factory is garbage-collected.
    """

    def __init__(
        self,
        system: System,
        task: Task,
        nthread: int | None = None,
        discount: float = 1.0,
        physics: PlanPhysics = ENV_PHYSICS,
        model: tuple[mujoco.MjModel, int] | None = None,
    ) -> None:
        if nthread is None:
            nthread = mujoco_threads()
        if nthread < 1:
            raise ValueError(f"nthread must be >= 1, got {nthread}")
        if not 0 < discount <= 1:
            raise ValueError(f"discount must be in (0, 1], got {discount}")
        self.system = system
        self.task = task
        self.discount = discount
        self.sensed = model is None and isinstance(task, SensedTask)
        if self.sensed:
            model = physics.apply(sensed_model(system, task), system)
        self.model, substeps = model or physics.model(system)
        self.sim = HeldControlRollout(self.model, substeps, nthread)
        self.ctrl_low = system.ctrl_low.numpy()
        self.ctrl_high = system.ctrl_high.numpy()

    @property
    def time_indexed(self) -> bool:
        """Its task depends on the episode step: call it with `step=`."""
        return self.task.time_indexed

    def __call__(self, q0: Tensor, qd0: Tensor, step: int = 0) -> MujocoObjective:
        """The objective from state (q0, qd0) at episode step `step` (time-indexed tasks)."""
        return MujocoObjective(self, self.initial_state(q0, qd0), step)

    def __enter__(self) -> MujocoObjectiveFactory:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.sim.close()

    def initial_state(self, q0: Tensor, qd0: Tensor) -> np.ndarray:
        """FULLPHYSICS state vector at time 0 with qpos=q0, qvel=qd0. (nstate,)"""
        as_np = lambda x: x.detach().to("cpu", torch.float64).numpy()  # noqa: E731
        return self.sim.full_state(as_np(q0), as_np(qd0))

    def rollout(self, initial_state: np.ndarray, actions: Tensor) -> OracleRollout:
        """Roll out actions (N, H, nu) from one FULLPHYSICS state. -> OracleRollout"""
        if actions.ndim != 3 or actions.shape[-1] != self.system.nu:
            raise ValueError(
                f"actions must be (N, H, nu={self.system.nu}), got {tuple(actions.shape)}"
            )
        ctrl = np.clip(
            actions.detach().to("cpu", torch.float64).numpy(), self.ctrl_low, self.ctrl_high
        )  # (N, H, nu)
        if self.sensed:
            states, sensors = self.sim.with_sensors(initial_state, ctrl)
        else:
            states, sensors = self.sim(initial_state, ctrl), None
        q, qd = self.sim.qv(states)  # (N, H, nq), (N, H, nv)
        return OracleRollout(
            states=State(
                q=torch.from_numpy(np.ascontiguousarray(q)),
                qd=torch.from_numpy(np.ascontiguousarray(qd)),
            ),
            actions=torch.from_numpy(ctrl),
            sensors=None if sensors is None else torch.from_numpy(sensors),
        )

    def returns(self, initial_state: np.ndarray, actions: Tensor, step: int = 0) -> Tensor:
        """Masked, discounted task returns of actions (N, H, nu), float64 on CPU, the first
        action taken at episode step `step`. -> (N,)"""
        result = self.rollout(initial_state, actions)
        q, qd = result.states.q, result.states.qd
        steps = step + torch.arange(actions.shape[1])  # (H,)
        if result.sensors is not None:
            rewards = self.task.sensed_reward(result.sensors, q, qd, result.actions)  # (N, H)
        else:
            rewards = self.task.reward_at(q, qd, result.actions, steps)  # (N, H)
        terminated = self.task.terminated_at(q, qd, steps)  # (N, H)
        return discounted_masked_return(rewards.to(torch.float64), terminated, self.discount)


class MujocoObjective:
    """Objective for one start state: actions (N, H, nu) -> returns (N,) on their device."""

    def __init__(
        self, factory: MujocoObjectiveFactory, initial_state: np.ndarray, step: int = 0
    ) -> None:
        self.factory = factory
        self.initial_state = initial_state  # (nstate,) FULLPHYSICS
        self.step = step  # episode step of the first action

    def rollout(self, actions: Tensor) -> OracleRollout:
        return self.factory.rollout(self.initial_state, actions)

    def __call__(self, actions: Tensor) -> Tensor:
        returns = self.factory.returns(self.initial_state, actions, self.step)
        dtype = actions.dtype if actions.is_floating_point() else torch.float64
        return returns.to(device=actions.device, dtype=dtype)


def mujoco_objective_factory(
    system: System,
    task: Task,
    nthread: int | None = None,
    discount: float = 1.0,
    physics: PlanPhysics = ENV_PHYSICS,
) -> MujocoObjectiveFactory:
    """The oracle: (q0 (nq,), qd0 (nv,)) -> objective over (N, H, nu) actions, true dynamics
    (or MuJoCo's with a coarser step or cheaper integrator: `physics`).

    nthread: MuJoCo rollout threads (None: `mujoco_threads`, as many as torch's).
    """
    return MujocoObjectiveFactory(system, task, nthread, discount, physics)
