"""TensorDict keys used across the package. Every key is spelled here and only here."""

Q = "q"  # generalized positions, MuJoCo qpos, (..., nq)
QD = "qd"  # generalized velocities, MuJoCo qvel, (..., nv)
QDD = "qdd"  # generalized accelerations, (..., nv)
TAU = "tau"  # generalized forces, (..., nv)
ACTION = "action"  # actuator controls, (..., nu)
REWARD = "reward"  # (..., 1)
DONE = "done"  # (..., 1) bool
TERMINATED = "terminated"  # (..., 1) bool
TRUNCATED = "truncated"  # (..., 1) bool
NEXT = "next"

NEXT_Q = (NEXT, Q)
NEXT_QD = (NEXT, QD)
NEXT_REWARD = (NEXT, REWARD)
NEXT_DONE = (NEXT, DONE)
NEXT_TERMINATED = (NEXT, TERMINATED)
NEXT_TRUNCATED = (NEXT, TRUNCATED)

EPISODE = "episode"  # index of the episode a transition belongs to, (..., 1) int64
STEP_COUNT = "step_count"  # TorchRL's StepCounter key
IS_INIT = "is_init"  # TorchRL's InitTracker key: True on the first step of an episode
