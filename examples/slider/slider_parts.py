"""A worked example of a user's own parts, registered from outside the package.

A slider (one slide joint with a motor) whose task is to reach x = 1 (the task option
``env.task.target``), a linear world model,
random shooting, a linear inverse-dynamics model and a data kind for the fit (a slide's
simulated log). Run them through the loop, and the inverse model through the fit, from the
repository's root:

    python -m mbrl_delan.train plugins=[examples.slider.slider_parts] \\
        'hydra.searchpath=[file://examples/slider/conf]' env=slider model=linear planner=shooting
    python -m mbrl_delan.fit plugins=[examples.slider.slider_parts] \\
        'hydra.searchpath=[file://examples/slider/fit_conf]' model=linear_inverse \\
        data=slide_log

See docs/architecture.md, "How to add an env / a task / a model / a planner".
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from mbrl_delan.data.arrays import SPLITS
from mbrl_delan.data.inverse_data import FitSystem, fields_inverse_data
from mbrl_delan.models.base import LossOutput, ModelConfig, WorldModel
from mbrl_delan.models.inverse import InverseDynamicsModel
from mbrl_delan.planners.base import (
    PlannerConfig,
    SamplingDistribution,
    SamplingPlanner,
    SamplingSettings,
    sampling_builder,
)
from mbrl_delan.registry import (
    DataKind,
    register_env,
    register_fit_data,
    register_inverse_model,
    register_model,
    register_planner,
)
from mbrl_delan.rules import rule
from mbrl_delan.systems.system import State
from mbrl_delan.tasks.base import Task


class ReachOne(Task):
    name = "reach_one"

    def __init__(self, episode_len=20, target=1.0):
        self.episode_len, self.target = episode_len, target

    def reward(self, q, qd, action):
        return torch.exp(-((q[..., 0] - self.target) ** 2))

    def initial_state(self, batch_shape, generator):
        q = 0.1 * torch.randn((*batch_shape, 1), generator=generator, dtype=torch.float64)
        return State(q, torch.zeros_like(q))


@register_env("slider", asset=Path(__file__).with_name("slider.xml"), frame_skip=2,
              options={"target": 1.0})  # fmt: skip
def make_task(system, episode_len, options):  # options: the registered ones, env.task.<name>=
    return ReachOne(episode_len or 20, float(options["target"]))


class LinearModel(WorldModel):
    """Next state = state + a linear function of (q, qd, action)."""

    deterministic = True

    def __init__(self, nq, nu):
        super().__init__()
        self.nq = nq
        self.delta = nn.Linear(2 * nq + nu, 2 * nq)

    def step(self, q, qd, action, generator=None):
        d = self.delta(torch.cat([q, qd, action], -1))
        return State(q + d[..., : self.nq], qd + d[..., self.nq :])

    def loss(self, batch):
        pred = self.step(batch["q"], batch["qd"], batch["action"])
        err = (pred.q - batch["next", "q"]).pow(2).mean() + (pred.qd - batch["next", "qd"]).pow(
            2
        ).mean()
        return LossOutput(err, {"mse": float(err.detach())})


@dataclass
class LinearConfig(ModelConfig):
    lr: float = rule(0.01, low=0, above=True)


@register_model("linear", schema=LinearConfig)
def build_linear(cfg, system):
    return LinearModel(system.nq, system.nu)


@dataclass
class ShootingSettings(SamplingSettings):
    init_std: float = rule(0.5, low=0, above=True)


class RandomShooting(SamplingPlanner):
    """Keeps the best of N random sequences around the last mean."""

    Settings = ShootingSettings

    def _initial_distribution(self, mean):
        return SamplingDistribution(mean, self.init_std.to(mean).expand_as(mean).clone())

    def _update(self, dist, samples, returns):
        return SamplingDistribution(samples[returns.argmax()], dist.std)


@dataclass
class ShootingConfig(ShootingSettings, PlannerConfig):
    """planner=shooting: its settings, then the loop's (horizon, replan_every, ...)."""


register_planner("shooting", schema=ShootingConfig)(sampling_builder(RandomShooting))


class LinearInverse(InverseDynamicsModel):
    """tau = W [q, qd, qdd] + b: exact for slides with viscous friction and a constant force."""

    def __init__(self, nq, nv, std_floor):
        super().__init__(nv, std_floor)
        self.torque = nn.Linear(nq + 2 * nv, nv)

    def predict_torque(self, q, qd, qdd):
        return self.torque(torch.cat([q, qd, qdd], -1))


@dataclass
class LinearInverseConfig:
    name: str = "linear_inverse"


@register_inverse_model("linear_inverse", schema=LinearInverseConfig)
def build_linear_inverse(cfg, context):  # context: mbrl_delan.conf.inverse.InverseContext
    return LinearInverse(context.layout.nq, context.layout.nv, context.std_floor)


@dataclass
class SlideLogConfig:
    name: str = "slide_log"
    samples: int = rule(600, low=10)
    seed: int = rule(0, low=0)
    force: float = 1.0  # the constant force on the slide (N)


def read_slide_log(cfg):  # the data group -> mbrl_delan.data.inverse_data.InverseData
    """A slide of mass 2 with viscous friction 0.5 and a constant force: tau = 2 qdd + 0.5 qd
    + force, in 6 trajectories of random states."""
    q, qd, qdd = np.random.default_rng(cfg.seed).uniform(-1, 1, (3, cfg.samples, 1))
    trajectory = np.arange(cfg.samples) * 6 // cfg.samples
    fields = {"q": q, "qd": qd, "qdd": qdd, "tau": 2 * qdd + 0.5 * qd + cfg.force,
              "dt": np.array(0.01), "trajectory": trajectory}  # fmt: skip
    source = {"format": "slide_log", "seed": cfg.seed, "force": cfg.force}
    return fields_inverse_data("slide_log", fields, FitSystem.of(["slide"]), source)


register_fit_data(
    "slide_log",
    DataKind(
        read=read_slide_log,
        check=lambda cfg: None,  # no rules between its keys beyond the schema's ranges
        splits=lambda cfg: SPLITS,
        tau="the slide's force: 2 qdd + 0.5 qd + force",
        summary=lambda provenance: {"seed": provenance["seed"], "force": provenance["force"]},
    ),
    SlideLogConfig,
)
