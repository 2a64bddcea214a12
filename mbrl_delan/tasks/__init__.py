"""Tasks: reward, termination and initial states as torch functions (no simulator calls)."""

from mbrl_delan.tasks.acrobot import AcrobotSwingup
from mbrl_delan.tasks.arm_reach import ArmReach
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.cartpole import CartpoleSwingup
from mbrl_delan.tasks.pendulum import PendulumSwingup

__all__ = [
    "AcrobotSwingup",
    "ArmReach",
    "CartpoleSwingup",
    "PendulumSwingup",
    "Task",
]
