"""Suite `fidelity`: world models scored on the oracle's own standing states.

One oracle episode of `oracle_steps` control steps (default 300) on ``humanoid_stand`` from
the start of `seed` gives the reference (`training.fidelity.FidelityReference`: its states
every 10th step and a perturbed copy of each, the oracle's actions, MPPI's 64 candidates at
each start with their returns under the env's physics). Each case is then scored by
`fidelity_metrics` (root velocity error after 1 step, head height error after 10 and 30
steps, Spearman rho of the candidates' returns) and by ``steps_survived``: the loop's
planner planning in the case's model and acting in the env for `oracle_steps` control steps
from the oracle's start (all of them: it stood).

Cases (`models`, default all `REFERENCE_CASES`): MuJoCo at the oracle's planning physics
(``mujoco``) and perturbed copies of it (`PERTURBATIONS`), planned on as the oracle is; the
white-box model's documented wrong start (``whitebox_start``); and MuJoCo's rigid body with
the learned models' contact structure at its start (``rigid_contact_start``: `ContactModel`
and `JointLimits`, implicit, 2 x 7.5 ms), planned on in torch. `runs`: train run dirs
whose final world model (checkpoint) is scored too, case ``<model>:<run dir name>``.

The learned models (`FIT_CASES`: ``tree``, ``tree_delan``, ``delan`` with the contact model,
``white_box``, ``ensemble``), named in `models`, are each built as the loop builds them and
fitted once, as the loop's refit does (seed `seed`), on the first `transitions` (default
5,000) transitions of `data_run`'s replay buffer (the loop's own data), or without
`data_run` on episodes of uniformly random actions from the task's starts (with
`data_contacts=false` simulated without contacts: `random_episodes`).

Besides the fidelity figures, every case with a rigid body gets the rigid-body figures of
`training.fidelity.rigid_body_metrics` on the reference's states (``mass_matrix_error``,
``total_mass_error``, ``gravity_error``, ``gravity_identity_residual``,
``actuation_response_error``).

Every record carries `model` (the case), `data` (what the model was fitted on), `metric`,
`env`, `learn_springs` and `spring_potential` (the model config's), the episode's `seed` and
`oracle_steps`, the suite's `overrides`, and the host fields. On an env whose springs the
given MJCF lacks, also ``spring_stiffness_error`` (joint springs, `humanoid_stand_exo`) and
``coupled_stiffness_error`` (tendon springs, `humanoid_stand_tendon`;
`training.fidelity.rigid_body_metrics`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict

from mbrl_delan import keys
from mbrl_delan.benchmarks import FIDELITY_CASES, BenchSettings, host_fields
from mbrl_delan.benchmarks.humanoid import first_transitions, split_run_episodes
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.bench_schema import FidelitySuiteConfig
from mbrl_delan.conf.checks import DTYPES, compose_train_config
from mbrl_delan.envs.real import make_real_env
from mbrl_delan.envs.registry import EnvParts, make_env_parts
from mbrl_delan.models.base import WorldModel, model_placement
from mbrl_delan.models.contact import ContactModel, JointLimits
from mbrl_delan.models.rigid_contact import RigidContactModel
from mbrl_delan.objectives.mujoco import PlanPhysics
from mbrl_delan.systems.external import add_exoskeleton
from mbrl_delan.training.fidelity import (
    CandidateRecorder,
    FidelityReference,
    RigidBodyTruth,
    build_reference,
    fidelity_metrics,
    rigid_body_metrics,
)
from mbrl_delan.training.fit import fit_model
from mbrl_delan.training.loop import run_episode
from mbrl_delan.training.recorder import RUN_CONFIG, WEIGHTS_FILE
from mbrl_delan.training.whitebox import WhiteBoxModel

log = logging.getLogger(__name__)

SUITE = "fidelity"
TASK = "humanoid_stand"  # the default env (`env`: also humanoid_stand_exo, _tendon)
STEPS = 300  # control steps of the oracle's episode and of each case's episode
QUICK_STEPS = 35  # under `quick`: just past the 30-step horizon
FREE_FALL_STEPS = 100  # control steps per episode without contacts (1.5 s: 15 m/s of fall)
UNITS = {
    "root_velocity_error_1step": "m/s", "head_height_error_10step": "cm",
    "head_height_error_30step": "cm", "candidate_rank_rho": "", "steps_survived": "steps",
    "mass_matrix_error": "", "total_mass_error": "", "gravity_error": "",
    "gravity_identity_residual": "", "actuation_response_error": "", "fit_seconds": "s",
    "spring_stiffness_error": "",
    "spring_stiffness_ratio": "",
    "coupled_stiffness_error": "",
}  # fmt: skip
DEFAULT_TRANSITIONS = 5000  # the learned cases' training set
# the learned cases: the train config each is built from (`python -m mbrl_delan.train
# env=humanoid_stand` with these), the DeLaN as the loop's DeLaN with the contact model
FIT_CASES = {
    "tree": ("model=tree",),
    "tree_delan": ("model=tree_delan",),
    "delan": ("model=delan", "model.contacts=true", "model.joint_limits=true",
              "model.residual=false", "model.translation_invariant=true", "model.substeps=1"),
    "white_box": ("model=white_box",),
    "ensemble": ("model=ensemble",),
}  # fmt: skip


SpecEdit = Callable[[mujoco.MjSpec, np.random.Generator], None]  # a change of an MJCF's spec


@dataclass(frozen=True)
class Perturbation:
    """A MuJoCo model off the env's: `multipliers` (a white-box multiplier kind -> factor for
    every multiplier of that kind), `mass_spread` (each body's mass and inertia x U(1 - s,
    1 + s), seeded) and `edit` (a change of the MJCF's spec)."""

    what: str
    multipliers: dict[str, float] = field(default_factory=dict)
    mass_spread: float = 0.0
    edit: SpecEdit | None = None


def _move_com(spec: mujoco.MjSpec, rng: np.random.Generator) -> None:
    """Each body's centre of mass moved 2 cm in a random direction."""
    model = spec.compile()
    for b in range(1, model.nbody):
        body = spec.body(model.body(b).name)
        body.explicitinertial = True
        body.mass, body.inertia = float(model.body_mass[b]), model.body_inertia[b].copy()
        body.iquat = model.body_iquat[b].copy()
        direction = rng.normal(size=3)
        body.ipos = model.body_ipos[b] + 0.02 * direction / np.linalg.norm(direction)
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_AUTO


def _gear(factor: float) -> SpecEdit:
    """An edit that scales every actuator's gear by `factor`."""

    def edit(spec: mujoco.MjSpec, rng: np.random.Generator) -> None:
        for actuator in spec.actuators:
            actuator.gear = np.array(actuator.gear) * factor

    return edit


def _small_feet(spec: mujoco.MjSpec, rng: np.random.Generator) -> None:
    """The feet's sphere geoms x0.7 (Humanoid-v5's geoms named ``*foot*``)."""
    for geom in spec.geoms:
        if "foot" in geom.name and geom.type == mujoco.mjtGeom.mjGEOM_SPHERE:
            geom.size = np.array(geom.size) * 0.7


def _no_contacts(spec: mujoco.MjSpec, rng: np.random.Generator) -> None:
    spec.option.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)


def _exoskeleton(springs: bool, friction: bool) -> SpecEdit:
    """An edit that adds the exoskeleton's springs, its hinge friction or both
    (`systems.external.EXOSKELETON`; on `humanoid_stand_exo`, both is the env's physics)."""

    def edit(spec: mujoco.MjSpec, rng: np.random.Generator) -> None:
        add_exoskeleton(spec, springs=springs, friction=friction)

    return edit


PERTURBATIONS = {
    "mujoco": Perturbation("the oracle's planning physics"),
    "mass_x0.5": Perturbation("every mass and inertia x0.5", {"mass": 0.5}),
    "mass_x0.8": Perturbation("every mass and inertia x0.8", {"mass": 0.8}),
    "mass_x1.25": Perturbation("every mass and inertia x1.25", {"mass": 1.25}),
    "mass_x1.5": Perturbation("every mass and inertia x1.5", {"mass": 1.5}),
    "mass_x2": Perturbation("every mass and inertia x2", {"mass": 2.0}),
    "mass_random": Perturbation("each body's mass and inertia x U(0.5, 1.5)", mass_spread=0.5),
    "com_2cm": Perturbation("each centre of mass moved 2 cm", edit=_move_com),
    "gear_x0.8": Perturbation("every actuator gear x0.8", edit=_gear(0.8)),
    "gear_x0.65": Perturbation("every actuator gear x0.65", edit=_gear(0.65)),
    "gear_x0.5": Perturbation("every actuator gear x0.5", edit=_gear(0.5)),
    "damping_x2": Perturbation("hinge damping x2", {"damping": 2.0}),
    "friction_0.2": Perturbation("floor friction 0.2 (true 1)", {"friction": 0.2}),
    "contact_3x_softer": Perturbation("contact solref time constant x3", {"timeconst": 3.0}),
    "contact_10x_softer": Perturbation("contact solref time constant x10", {"timeconst": 10.0}),
    "foot_x0.7": Perturbation("foot spheres x0.7", edit=_small_feet),
    "contacts_off": Perturbation("no contacts", edit=_no_contacts),
    "exo_springs": Perturbation(
        "the exoskeleton's hip and knee springs added",
        edit=_exoskeleton(springs=True, friction=False),
    ),
    "exo_friction": Perturbation(
        "the exoskeleton's 5 N m hinge friction added",
        edit=_exoskeleton(springs=False, friction=True),
    ),
    "exo": Perturbation(
        "the exoskeleton's springs and friction added",
        edit=_exoskeleton(springs=True, friction=True),
    ),
}
WHITEBOX_START = "whitebox_start"  # the white-box model's documented wrong start, no data
# MuJoCo's rigid body (contacts and limits off) with the learned-contact structure at its
# start: `ContactModel` and `JointLimits`, implicit (`models/rigid_contact.py`)
RIGID_CONTACT = "rigid_contact_start"
REFERENCE_CASES = (*PERTURBATIONS, WHITEBOX_START, RIGID_CONTACT)
ALL_CASES = (*REFERENCE_CASES, *FIT_CASES)
CASE_NOTES = {
    WHITEBOX_START: "the white-box model's documented wrong start",
    RIGID_CONTACT: "rigid body exact, contact law at its start, joint limits implicit",
}
assert ALL_CASES == FIDELITY_CASES, "benchmarks.FIDELITY_CASES lists the same cases"


def perturbed_model(
    cfg: DictConfig, parts: EnvParts, name: str, seed: int, nthread: int
) -> WorldModel:
    """The MuJoCo model of reference case `name`, stepping at the oracle's physics."""
    system = parts.system
    if name == RIGID_CONTACT:
        model = system.mj_model()
        contact = ContactModel.from_mujoco(model).double()
        return RigidContactModel(system, contact, cfg.env.oracle_substeps or system.frame_skip,
                                 JointLimits.from_mujoco(model))  # fmt: skip
    physics = PlanPhysics(cfg.env.oracle_substeps, cfg.env.oracle_integrator)
    spec = mujoco.MjSpec.from_file(str(system.xml_path))
    rng = np.random.default_rng(seed)
    if name == WHITEBOX_START:
        model = WhiteBoxModel(system, spec, physics=physics, nthread=nthread)
        model.set_multipliers(model.white.documented_start())
        return model
    p = PERTURBATIONS[name]
    if p.edit is not None:
        p.edit(spec, rng)
    model = WhiteBoxModel(system, spec, physics=physics, nthread=nthread)
    theta = model.theta.copy()
    for i, m in enumerate(model.white.multipliers):
        theta[i] *= p.multipliers.get(m.kind, 1.0)
        if m.kind == "mass" and p.mass_spread:
            theta[i] *= rng.uniform(1 - p.mass_spread, 1 + p.mass_spread)
    model.set_multipliers(theta)
    return model


def reference_episode(
    cfg: DictConfig, parts: EnvParts, steps: int, seed: int, nthread: int
) -> FidelityReference:
    """The oracle's episode from the start of `seed` with its candidates recorded."""
    from mbrl_delan.conf.loop import build_oracle

    oracle = build_oracle(cfg, parts.physics, parts.task)
    recorder = CandidateRecorder(oracle.objective_factory)
    oracle.objective_factory = recorder
    env = make_real_env(parts.task.name, seed=seed, episode_len=parts.task.episode_len)
    try:
        rollout = run_episode(env, oracle, seed, steps)
    finally:
        env.close()
        recorder.close()
    log.info("fidelity: the oracle's reference episode kept %d of %d steps", len(rollout), steps)
    return build_reference(rollout, recorder, parts.physics, parts.task, seed=seed,
                           nthread=nthread)  # fmt: skip


def steps_survived(
    cfg: DictConfig, parts: EnvParts, model: WorldModel, steps: int, seed: int
) -> int:
    """Control steps the loop's planner keeps the humanoid up, planning in `model` and acting
    in the env from the start of `seed` (at most `steps`)."""
    from mbrl_delan.conf.loop import build_policy

    generator = torch.Generator().manual_seed(seed)
    policy = build_policy(cfg, parts.system, parts.task, model, generator)
    env = make_real_env(parts.task.name, seed=seed, episode_len=parts.task.episode_len)
    try:
        return int(run_episode(env, policy, seed, steps).shape[0])
    finally:
        env.close()
        close = getattr(policy.objective_factory, "close", None)
        if close is not None:
            close()


def _run_model(run_dir: str) -> tuple[DictConfig, WorldModel, str]:
    """A train run's config, final world model and what it was fitted on."""
    from mbrl_delan.runs import load_run

    run = load_run(run_dir)
    if run.kind != "train":
        raise ValueError(f"runs: {run_dir} is a fit run; the suite scores world models")
    steps = (run.summary or {}).get("env_steps", "?")
    data = f"{steps} env steps of the loop ({Path(run_dir).name})"
    return run.config, run.model, data


def _planning_overrides(overrides: Sequence[str]) -> list[str]:
    """The suite's overrides the reference episode reads: all but the models' keys (a key
    one model has, e.g. tree_delan's `residual_penalty`, is not the default model's)."""
    return [o for o in overrides if not o.lstrip("+~").startswith("model.")]


def run_fidelity_suite(options: FidelitySuiteConfig, bench: BenchSettings) -> Iterator[BenchRecord]:
    seed = options.seed or 0
    steps = options.oracle_steps or (QUICK_STEPS if bench.quick else STEPS)
    nthread = max(1, torch.get_num_threads())
    task = options.env or TASK
    cfg = compose_train_config([f"env={task}", *_planning_overrides(options.overrides)])
    parts = make_env_parts(task, None, None)
    reference = reference_episode(cfg, parts, steps, seed, nthread)
    host = host_fields(torch.device("cpu"))
    base = dict(env=task, seed=seed, oracle_steps=steps, starts=int(reference.q.shape[0]),
                data_contacts=options.data_contacts,
                candidate_starts=int(reference.candidate_starts.numel()),
                overrides=list(options.overrides))  # fmt: skip
    cases = REFERENCE_CASES if options.models is None else options.models
    data: TensorDict | None = None
    for name in (c for c in cases if c in FIT_CASES):
        if data is None:
            data, described = training_data(options, parts, seed)
        case_cfg = compose_train_config([f"env={task}", *FIT_CASES[name], f"seed={seed}",
                                         *options.overrides])  # fmt: skip
        model, seconds = fitted_model(case_cfg, parts, data, seed)
        if options.save_models is not None:
            keep_model(Path(options.save_models) / f"{name}_s{seed}", case_cfg, model)
        yield from _case(case_cfg, parts, model, name, described, reference, steps, seed,
                         base | host | {"transitions": int(data.shape[0])},
                         {"fit_seconds": seconds})  # fmt: skip
    for name in (c for c in cases if c not in FIT_CASES):
        model = perturbed_model(cfg, parts, name, seed, nthread)
        what = PERTURBATIONS[name].what if name in PERTURBATIONS else CASE_NOTES[name]
        yield from _case(cfg, parts, model, name, "none (MuJoCo: " + what + ")", reference,
                         steps, seed, base | host)  # fmt: skip
    for run_dir in options.runs:
        run_cfg, model, data = _run_model(run_dir)
        name = f"{run_cfg.model.name}:{Path(run_dir).name}"
        yield from _case(run_cfg, parts, model, name, data, reference, steps, seed, base | host)


def keep_model(folder: Path, cfg: DictConfig, model: WorldModel) -> None:
    """A fitted case as a record folder (`config.yaml`, `world_model.pt`), which
    `runs.load_run` reads back (`runs=[...]` scores it again, e.g. with an edited config)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / RUN_CONFIG).write_text(OmegaConf.to_yaml(cfg, resolve=True))
    torch.save(model.state_dict(), folder / WEIGHTS_FILE)
    log.info("fidelity: the fitted model kept in %s", folder)


def training_data(
    options: FidelitySuiteConfig, parts: EnvParts, seed: int
) -> tuple[TensorDict, str]:
    """The learned cases' transitions and what they are: the first `transitions[0]` of
    `data_run`'s buffer, or random-action episodes from the task's starts (seed `seed`)."""
    n = (options.transitions or (DEFAULT_TRANSITIONS,))[0]
    if options.data_run is not None:
        train, _ = split_run_episodes(options.data_run, parts.task.name, 0)
        return (first_transitions(train, n, options.data_run),
                f"the first {n} transitions of {Path(options.data_run).name}")  # fmt: skip
    if not options.data_contacts:
        return (random_episodes(parts, n, seed, contacts=False),
                f"{n} transitions of random actions without contacts (seed {seed})")  # fmt: skip
    return random_episodes(parts, n, seed), f"{n} transitions of random actions (seed {seed})"


def random_episodes(parts: EnvParts, n: int, seed: int, contacts: bool = True) -> TensorDict:
    """n transitions of episodes of uniformly random controls from the task's starts, each
    until the task ends it (float64, time-ordered). Without `contacts` MuJoCo's contacts
    are off: the body falls freely, and its joints move as they would without gravity (it
    acts alike on every body), in episodes of `FREE_FALL_STEPS` the task does not end."""
    system, task = parts.physics, parts.task  # what the env simulates
    model = system.mj_model()
    if not contacts:
        model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    data = mujoco.MjData(model)
    generator = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    low, high = system.ctrl_low.numpy(), system.ctrl_high.numpy()
    rows: list[tuple[np.ndarray, ...]] = []
    while len(rows) < n:
        start = task.initial_state((), generator)
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:] = start.q.numpy(), start.qd.numpy()
        for _ in range(task.episode_len if contacts else FREE_FALL_STEPS):
            q, qd = data.qpos.copy(), data.qvel.copy()
            data.ctrl[:] = rng.uniform(low, high)
            mujoco.mj_step(model, data, nstep=system.frame_skip)
            rows.append((q, qd, data.ctrl.copy(), data.qpos.copy(), data.qvel.copy()))
            ended = contacts and task.terminated(torch.from_numpy(data.qpos),
                                                 torch.from_numpy(data.qvel))  # fmt: skip
            if len(rows) == n or bool(ended):
                break
    q, qd, action, q_next, qd_next = (
        torch.from_numpy(np.stack(c)) for c in zip(*rows, strict=True)
    )
    return TensorDict({keys.Q: q, keys.QD: qd, keys.ACTION: action, keys.NEXT_Q: q_next,
                       keys.NEXT_QD: qd_next}, batch_size=[n])  # fmt: skip


def fitted_model(
    cfg: DictConfig, parts: EnvParts, data: TensorDict, seed: int
) -> tuple[WorldModel, float]:
    """The world model `cfg` names, built and fitted on `data` once as the loop's refit does
    (its identification for the white box), and the fit's seconds."""
    from mbrl_delan.conf.loop import build_fit_config, build_world_model

    torch.manual_seed(seed)
    model = build_world_model(cfg, parts.system, torch.device("cpu"), DTYPES[cfg.dtype])
    place = model_placement(model)
    data = data.to(place.dtype)
    generator = torch.Generator().manual_seed(seed + 1)
    start = time.perf_counter()
    if model.identifies:
        model.identify(data, generator)
    else:
        optimizer = torch.optim.Adam(model.parameters(), lr=cfg.model.lr,
                                     weight_decay=cfg.model.weight_decay)  # fmt: skip
        report = fit_model(model, optimizer, data, build_fit_config(cfg), generator)
        log.info("fidelity: %s fitted in %d epochs", cfg.model.name, report.epochs_run)
    return model, time.perf_counter() - start


def _case(
    cfg: DictConfig, parts: EnvParts, model: WorldModel, name: str, data: str,
    reference: FidelityReference, steps: int, seed: int, fields: dict[str, Any],
    extra: dict[str, float] | None = None,
) -> Iterator[BenchRecord]:  # fmt: skip
    from mbrl_delan.conf.loop import build_policy

    policy = build_policy(cfg, parts.system, parts.task, model, torch.Generator().manual_seed(0))
    try:
        metrics = fidelity_metrics(model, policy.objective_factory, reference, parts.task)
    finally:
        close = getattr(policy.objective_factory, "close", None)
        if close is not None:
            close()
    q = reference.q[: reference.q.shape[0] // 2]  # the unperturbed starts
    metrics |= rigid_body_metrics(model, RigidBodyTruth.of(parts.physics, q, parts.system)) | (
        extra or {}
    )
    metrics["steps_survived"] = steps_survived(cfg, parts, model, steps, seed)
    log.info("fidelity: %s %s", name, {k: round(v, 4) for k, v in metrics.items()})
    springs = {k: bool(cfg.model.get(k, False)) for k in ("learn_springs", "spring_potential")}
    for metric, value in metrics.items():
        yield BenchRecord(SUITE, name, metric, value, UNITS[metric], "cpu",
                          {"model": name, "data": data, **springs, **fields})  # fmt: skip
