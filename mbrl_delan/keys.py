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
NEXT_STEP_COUNT = (NEXT, STEP_COUNT)
IS_INIT = "is_init"  # TorchRL's InitTracker key: True on the first step of an episode
PARTIAL_STEP = "_step"  # TorchRL's mask of the envs of a batch that a partial step moves

# Motion-capture datasets (mbrl_delan.data.mocap)
ROOT_RESIDUAL = "root_residual"  # generalized force on the free root joint, (..., 6)
CLIP = "clip"  # index of the source clip in the dataset's clip list, (..., 1) int64
FRAME = "frame"  # fractional frame number in the source AMC file, (..., 1) float64
TIME = "time"  # seconds since the clip's first frame, (..., 1) float64
SPLIT = "split"  # 0 train, 1 held-out time segment, 2 held-out clip, (..., 1) int64

# Logged robot data (mbrl_delan.data.arrays)
TRAJECTORY = "trajectory"  # index of the trajectory a sample belongs to, (..., 1) int64
TAU_INERTIAL = "tau_inertial"  # the inertial part M(q) qdd of tau, (..., nv)
TAU_CORIOLIS = "tau_coriolis"  # the Coriolis and centripetal part c(q, qd), (..., nv)
TAU_GRAVITY = "tau_gravity"  # the gravity part g(q), (..., nv)
TAU_FRICTION = "tau_friction"  # the joints' friction d(q, qd), (..., nv)
