"""Where a learned model's planning time goes: the eager path's operator time split into parts.

`profile_parts` runs a call (one replanning cycle of the planner on a model) once under
`torch.profiler` with Python stacks: each operator's self time goes to the part of the
innermost package function on its call chain that `PART_RULES` names (helpers no rule names,
such as the quaternion arithmetic, count for their caller). The shares are of the operators'
time: the interpreter's and the dispatcher's time between operators is not split out (the
profiler's own cost per operator is of its order). Only CPU time is split; on CUDA an
operator's CPU time is its launch.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable

from torch.autograd.profiler_util import FunctionEvent
from torch.profiler import ProfilerActivity, profile

PACKAGE = "mbrl_delan/"
OTHER = "other"  # operators under no function a rule names

# (file under the package, its functions ("": every function of the file), part); the first
# rule that matches a frame names its part
PART_RULES: tuple[tuple[str, str, str], ...] = (
    ("models/contact.py", "implicit_acceleration _solve", "solve"),
    ("models/contact.py", "", "contact"),
    ("models/lagrangian.py", "forward_dynamics _solve with_armature", "solve"),
    (
        "models/lagrangian.py",
        "_dissipation forward slope viscous lead velocity _coulomb lead_inertia _sech2",
        "passive",
    ),
    (
        "models/lagrangian.py",
        "_add_euler_poincare _bias_and_jet root_frame_jet pullback _velocity_products terms",
        "network",
    ),
    ("models/field.py", "", "network"),
    ("models/features.py", "", "network"),
    ("models/kernels.py", "", "network"),
    ("models/tangent_mlp.py", "", "network"),
    ("models/ensemble.py", "", "network"),
    ("models/delan_ensemble.py", "", "network"),
    # forward kinematics counts for its caller: the model's tree, its contacts, or the cost
    ("models/tree.py", "kinematics _frames _paths", "kinematics"),
    ("models/delan.py", "_shared_frames", "kinematics"),
    (
        "models/tree.py",
        "mass_matrix world_inertia pseudo_inertia inertial armature total_mass",
        "mass_matrix",
    ),
    ("models/tree.py", "bias coriolis gravity _generalized", "bias"),
    ("models/tree.py", "passive spring spring_stiffness damping", "passive"),
    ("models/integrators.py", "", "integrator"),
    ("systems/posarith.py", "integrate_pos", "integrator"),
    ("models/delan.py", "step accel _clamp_velocity", "integrator"),
    ("tasks/", "", "cost"),
    ("objectives/", "", "cost"),
    ("planners/", "", "planner"),
)
PARTS = (
    "kinematics",
    "mass_matrix",
    "bias",
    "passive",
    "contact",
    "solve",
    "network",
    "integrator",
    "cost",
    "planner",
    OTHER,
)


def frame_part(name: str) -> str | None:
    """The part of a profiler's Python frame ``.../mbrl_delan/<file>(<line>): <function>``,
    or None when no rule names it."""
    if PACKAGE not in name:
        return None
    where = name.rsplit(PACKAGE, 1)[1]
    path, _, function = where.partition(": ")
    path = path.split("(", 1)[0]
    for prefix, functions, part in PART_RULES:
        if path.startswith(prefix) and (not functions or function in functions.split()):
            return part
    return None


def event_part(event: FunctionEvent) -> str:
    """The part of an operator: its innermost enclosing frame that a rule names."""
    parent = event.cpu_parent
    while parent is not None:
        if parent.is_python_function:
            part = frame_part(parent.name)
            if part is not None:
                return part
        parent = parent.cpu_parent
    return OTHER


def profile_parts(call: Callable[[], object]) -> dict[str, float]:
    """Each of `PARTS`' share of the operators' time in one `call` (module docstring); `call`
    should have run once before (its first-call costs are not its parts)."""
    with profile(activities=[ProfilerActivity.CPU], with_stack=True) as stacked:
        call()
    by_part: dict[str, float] = defaultdict(float)
    for event in stacked.events():
        if not event.is_python_function:
            by_part[event_part(event)] += event.self_cpu_time_total
    total = sum(by_part.values()) or 1.0
    return {part: by_part.get(part, 0.0) / total for part in PARTS}
