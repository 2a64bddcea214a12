"""The names `python -m mbrl_delan.bench` accepts (its suites: `conf.bench_schema.SUITE_SCHEMAS`):
cases, tasks and robots of the suites, so that the bench config's schema checks them without
importing a suite (`mbrl_delan.benchmarks` re-exports them)."""

# world-model cases of suite planner (here so the entry point can check names without
# importing the suite): DeLaN on the pendulum and on Humanoid-v5's layout, the MLP ensemble on
# the pendulum, and MuJoCo's true pendulum dynamics (the oracle); the two DeLaN cases again
# with every control step `torch.compile`d (`accel.compile=true`), and on CUDA with each
# rollout replayed from a CUDA graph, eager or compiled (`accel.cuda_graph=true`)
PLANNER_MODELS = (
    "pendulum_delan",
    "humanoid_delan",
    "pendulum_ensemble",
    "pendulum_oracle",
    "pendulum_delan_compiled",
    "humanoid_delan_compiled",
    "pendulum_delan_graph",
    "humanoid_delan_graph",
    "pendulum_delan_compiled_graph",
    "humanoid_delan_compiled_graph",
)
# suite planner: <env>_<model>, a plugin's model on a registered env (the pendulum, a plugin's)


def plugin_case(env: str, model: str) -> str:
    """Suite planner's case name of a plugin's `model` on `env`."""
    return f"{env}_{model}"


def split_plugin_case(name: str, envs: tuple[str, ...]) -> tuple[str, str]:
    """(env, model) of a plugin case `name`, its env the longest of `envs` it starts with."""
    env = max((e for e in envs if name.startswith(f"{e}_")), key=len)
    return env, name.removeprefix(f"{env}_")


COMPILED_SUFFIX = "_compiled"
GRAPH_SUFFIX = "_graph"
# world models of suite humanoid: DeLaN + residual, DeLaN + residual + the structured contact
# model, the DeLaN ensemble, the MLP ensemble
HUMANOID_MODELS = ("delan", "delan_contact", "delan_ensemble", "ensemble")
# and, on demand only (`models=[...]`): DeLaN without the residual, with or without contacts
HUMANOID_MODEL_VARIANTS = ("delan_plain", "delan_contact_only")
# tasks on which suite humanoid runs the oracle planner for one episode
HUMANOID_ORACLE_TASKS = ("humanoid_stand", "humanoid_walk", "cmu_track")
ORACLE_PLANNERS = ("mppi", "cem", "icem", "predictive", "ilqr")  # suite humanoid's oracles
ILQR_TASKS = ("cmu_track",)  # suite humanoid: tasks of its tracking iLQR oracle
# suite realtime: its tasks and the dynamics each is planned on
REALTIME_TASKS = ("humanoid_stand", "humanoid_walk", "pendulum")
REALTIME_DYNAMICS = ("mujoco", "delan", "tree", "tree_delan", "ensemble")
# suite fidelity's envs
FIDELITY_ENVS = ("humanoid_stand", "humanoid_stand_exo", "humanoid_stand_tendon")
# suite fidelity's cases: MuJoCo at the oracle's physics, perturbed copies of it, the white-box
# model's documented wrong start, MuJoCo's rigid body with the contact model, and the learned
# models fitted on the loop's data (`benchmarks/fidelity.py`)
FIDELITY_CASES = (
    "mujoco", "mass_x0.5", "mass_x0.8", "mass_x1.25", "mass_x1.5", "mass_x2", "mass_random",
    "com_2cm", "gear_x0.8", "gear_x0.65", "gear_x0.5", "damping_x2",
    "friction_0.2", "contact_3x_softer", "contact_10x_softer", "foot_x0.7", "contacts_off",
    "exo_springs", "exo_friction", "exo",
    "whitebox_start", "rigid_contact_start",
    "tree", "tree_delan", "delan", "white_box", "ensemble",
)  # fmt: skip

# suite own_arm: the shipped arms (`mbrl_delan.systems.arms.ARMS`) and the fits' models
OWN_ARM_ROBOTS = ("panda", "iiwa14", "ur5e", "slim7", "light6")
OWN_ARM_MODELS = ("delan", "tree_delan", "mlp", "white_box")
# ... the arms' friction kinds (`systems.arms.FRICTION_KINDS`) and the excitation designs
# (`data.excitation.DESIGNS`)
OWN_ARM_FRICTION = ("none", "frictionloss", "coulomb_viscous")
OWN_ARM_DESIGNS = ("fourier", "sinusoids", "point_to_point")
OWN_ARM_STRUCTURES = ("none", "counterbalance", "coupling")
