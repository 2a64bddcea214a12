"""Suite `delan`: the speed of DeLaN's dynamics against a naive DeLaN and MuJoCo itself.

For each nv in the suite's `nv` the system is a serial chain of nv unlimited hinges (every
feature periodic: sin and cos), the model `DeLaN` with its constructor's defaults (hidden 64,
2 layers, softplus, RK4) in float32, and for each batch size:

- `fwd_dyn_per_s`: `model.dynamics.forward_dynamics(q, qd, tau)` under inference mode,
  evaluations (samples) per second = batch * calls / seconds.
- `inv_dyn_per_s`: the same for `inverse_dynamics(q, qd, qdd)`.
- `train_samples_per_s`: one optimiser step (forward loss through `model.step`, backward,
  Adam step), samples per second = batch / seconds per step.
- `naive_fwd_dyn_per_s`: `naive_forward_dynamics`, the reference DeLaN's way (the full
  Jacobian dM/dq by autograd, then c and a dense solve).
- `flops_fraction`: FLOP/s achieved by `forward_dynamics` (`forward_dynamics_flops` per
  sample times `fwd_dyn_per_s`) divided by the FLOP/s of a large float32 matmul measured in
  the same run (`matmul_flops_per_s`, recorded too).

and MuJoCo's own rate on a system of the same nv (`mujoco_system`): `mujoco_fwd_per_s`
(`mj_forward` in a Python loop on one MjData) and, for batch > 1,
`mujoco_rollout_steps_per_s` (`mujoco.rollout` of `batch` states one `mj_step` each, on
as many threads as torch uses).

A figure whose single call is predicted (from trial calls at smaller batches) to take more than
`max_call_s`, or whose main tensors would exceed `max_memory_bytes`, is recorded with
`value: null` and a `note`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import torch
from mujoco import rollout as mj_rollout
from tensordict import TensorDict
from torch import Tensor
from torch.func import grad, jacfwd, vmap
from torch.nn import functional as F

from mbrl_delan import keys
from mbrl_delan.accelerate import compile_dynamics
from mbrl_delan.benchmarks import (
    BenchSettings,
    Timing,
    host_fields,
    single_call_seconds,
    synchronizer,
    time_call,
)
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.bench_schema import DelanSuiteConfig
from mbrl_delan.models.delan import DeLaN
from mbrl_delan.models.field import LagrangianNetwork
from mbrl_delan.systems.external import humanoid_cmu_xml
from mbrl_delan.systems.system import HINGE, JointLayout

log = logging.getLogger(__name__)

SUITE = "delan"
DTYPE = torch.float32
PILOT_BATCH = 16  # batch of the trial call that predicts a large call's time
CONTROL_DT = 0.01
HUMANOID_NV = 62


# ----------------------------------------------------------------------------- the model


def chain_layout(nv: int) -> JointLayout:
    """A serial chain of nv unlimited hinges: q and qd both of size nv, all features periodic."""
    if nv < 1:
        raise ValueError(f"nv must be >= 1, got {nv}")
    idx = tuple(range(nv))
    return JointLayout(types=(HINGE,) * nv, qpos_adr=idx, dof_adr=idx, limited=(False,) * nv)


def chain_model(nv: int, seed: int = 0) -> DeLaN:
    """DeLaN with its constructor's defaults on `chain_layout(nv)`, fully actuated (B = I)."""
    torch.manual_seed(seed)
    return DeLaN(chain_layout(nv), torch.eye(nv), control_dt=CONTROL_DT)


def _network(model: DeLaN) -> LagrangianNetwork:
    field = model.dynamics.field
    if not isinstance(field, LagrangianNetwork):
        raise TypeError(f"expected a LagrangianNetwork field, got {type(field).__name__}")
    return field


def forward_dynamics_flops(nv: int, n_features: int, hidden: int, layers: int) -> int:
    """FLOPs of one sample of `LagrangianDynamics.forward_dynamics` (a multiply-add is 2).

    With f = n_features, h = hidden, l = layers and o = nv + nv (nv - 1) / 2 + 1 trunk
    outputs (diagonal and strictly lower entries of L, and V):

        pass  = 2 (f h + (l - 1) h^2 + h o)      one pass through the trunk's matmuls
        FLOPs = 3 pass + 11 nv^2

    3 passes: the forward pass, its tangent along qd (same matmuls) and one reverse pass
    (c and g share it). 11 nv^2: four dense matrix-vector products (L^T qd, Ldot^T qd,
    Ldot w, L wdot; 2 nv^2 each), the cotangent qd w^T (nv^2) and two triangular solves
    (nv^2 each). No nv^3 term: the Cholesky factor comes from the network. Elementwise work
    (activations, features, softplus of the diagonal, dissipation) is not counted, so this
    is a lower bound of the work done.
    """
    outputs = nv + nv * (nv - 1) // 2 + 1
    one_pass = 2 * (n_features * hidden + (layers - 1) * hidden * hidden + hidden * outputs)
    return 3 * one_pass + 11 * nv * nv


def model_flops(model: DeLaN) -> int:
    """`forward_dynamics_flops` for this model's sizes."""
    trunk = _network(model).trunk
    return forward_dynamics_flops(
        nv=model.layout.nv,
        n_features=trunk.hidden[0].in_features,
        hidden=trunk.hidden[0].out_features,
        layers=len(trunk.hidden),
    )


def naive_forward_dynamics(model: DeLaN, q: Tensor, qd: Tensor, tau: Tensor) -> Tensor:
    """qdd the way the reference DeLaN computes it: (B, n), (B, n), (B, n) -> (B, n).

    M(q) = L L^T from the same network (forward pass only), the full Jacobian
    dM/dq (B, n, n, n) by forward-mode autograd, then
    c = (dM/dq . qd) qd - 1/2 qd^T (dM/dq) qd, g = dV/dq by reverse-mode autograd, the same
    dissipation, and a dense `torch.linalg.solve` with M. Scalar joints only (q in velocity
    space), which the hinge chain is.
    """
    net = _network(model)
    n = net.n

    def mass(qi: Tensor) -> tuple[Tensor, Tensor]:
        out = net.trunk(net.features(qi)).out
        L = torch.diag_embed(F.softplus(out[:n]) + net.diag_shift)
        L = L.index_put((net.rows, net.cols), out[n : net.v_row])
        M = L @ L.T
        return M, M

    def potential(qi: Tensor) -> Tensor:
        return net.trunk(net.features(qi)).out[net.v_row]

    dM, M = vmap(jacfwd(mass, has_aux=True))(q)  # dM[b, i, j, k] = d M_ij / d q_k
    g = vmap(grad(potential))(q)
    m_dot = torch.einsum("bijk,bk->bij", dM, qd)
    c = (m_dot @ qd.unsqueeze(-1)).squeeze(-1) - 0.5 * torch.einsum("bi,bijk,bj->bk", qd, dM, qd)
    dissipation = model.dynamics.dissipation
    d = torch.zeros_like(qd) if dissipation is None else dissipation(qd)
    return torch.linalg.solve(M, (tau - c - g - d).unsqueeze(-1)).squeeze(-1)


def naive_bytes(nv: int, batch: int, element_size: int) -> int:
    """Rough peak memory of `naive_forward_dynamics`: about six (B, n, n, n) tensors."""
    return 6 * batch * nv**3 * element_size


# ----------------------------------------------------------------------------- inputs


@dataclass
class Inputs:
    """One batch of states and forces. All (batch, nv)."""

    q: Tensor
    qd: Tensor
    tau: Tensor
    qdd: Tensor

    def head(self, batch: int) -> Inputs:
        return Inputs(self.q[:batch], self.qd[:batch], self.tau[:batch], self.qdd[:batch])

    @property
    def batch(self) -> int:
        return self.q.shape[0]


def random_inputs(
    nv: int, batch: int, device: torch.device, dtype: torch.dtype = DTYPE, seed: int = 0
) -> Inputs:
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(4, batch, nv, generator=g, dtype=torch.float64)
    x = x.to(device=device, dtype=dtype)
    return Inputs(q=3.0 * x[0], qd=x[1], tau=x[2], qdd=x[3])


# ----------------------------------------------------------------------------- callables

Make = Callable[[Inputs], Callable[[], object]]


def _fwd(model: DeLaN) -> Make:
    def make(x: Inputs) -> Callable[[], object]:
        def call() -> Tensor:
            with torch.inference_mode():
                return model.dynamics.forward_dynamics(x.q, x.qd, x.tau)

        return call

    return make


def _compiled_fwd(model: DeLaN) -> Make:
    """`forward_dynamics` through `compile_dynamics` (static shapes; compiled per batch)."""
    compiled = compile_dynamics(model.dynamics.forward_dynamics)

    def make(x: Inputs) -> Callable[[], object]:
        def call() -> Tensor:
            with torch.inference_mode():
                return compiled(x.q, x.qd, x.tau)

        return call

    return make


def _inv(model: DeLaN) -> Make:
    def make(x: Inputs) -> Callable[[], object]:
        def call() -> Tensor:
            with torch.inference_mode():
                return model.dynamics.inverse_dynamics(x.q, x.qd, x.qdd)

        return call

    return make


def _naive(model: DeLaN) -> Make:
    def make(x: Inputs) -> Callable[[], object]:
        def call() -> Tensor:
            with torch.inference_mode():
                return naive_forward_dynamics(model, x.q, x.qd, x.tau)

        return call

    return make


def _train(model: DeLaN, optimizer: torch.optim.Optimizer) -> Make:
    """One Adam step on the forward (next-state) loss through `model.step`."""

    def make(x: Inputs) -> Callable[[], object]:
        batch = TensorDict(
            {
                keys.Q: x.q,
                keys.QD: x.qd,
                keys.ACTION: x.tau,
                keys.NEXT_Q: x.q + CONTROL_DT * x.qd,
                keys.NEXT_QD: x.qd + CONTROL_DT * x.qdd,
            },
            batch_size=[x.batch],
        )

        def call() -> None:
            optimizer.zero_grad(set_to_none=True)
            model.loss(batch).loss.backward()
            optimizer.step()

        return call

    return make


# ----------------------------------------------------------------------------- measuring


@dataclass
class Measured:
    """A timed callable, or why it was skipped."""

    timing: Timing | None
    note: str | None = None


def _measure(
    make: Make,
    x: Inputs,
    bench: BenchSettings,
    sync: Callable[[], None],
    memory_bytes: int = 0,
) -> Measured:
    """Time `make(x)`, unless its memory or its predicted call time is over the limits."""
    if memory_bytes > bench.max_memory_bytes:
        gib = memory_bytes / 1024**3
        return Measured(None, f"skipped: needs about {gib:.1f} GiB (max_memory_gb)")
    predicted = _predict_call_s(make, x, bench.max_call_s, sync)
    if predicted > bench.max_call_s:
        return Measured(None, f"skipped: one call predicted {predicted:.1f} s > max_call_s")
    return Measured(time_call(make(x), bench.timing, sync))


def _predict_call_s(make: Make, x: Inputs, max_call_s: float, sync: Callable[[], None]) -> float:
    """Seconds of one call at the full batch, extrapolated linearly from trial calls.

    Trial batches 16, 128, 1024, ...: a small batch overestimates (fixed overheads), so a
    prediction over `max_call_s` is checked again at 8x the batch, as long as that trial
    call is itself predicted to fit in `max_call_s`. 0.0 when the batch is already small.
    """
    pilot = PILOT_BATCH
    while pilot < x.batch:
        seconds = single_call_seconds(make(x.head(pilot)), sync)
        predicted = seconds * x.batch / pilot
        following = min(x.batch, 8 * pilot)
        if predicted <= max_call_s or seconds * following / pilot > max_call_s:
            return predicted
        pilot = following
    return 0.0


def _record(
    case: str,
    metric: str,
    unit: str,
    device: torch.device | str,
    fields: dict[str, Any],
    measured: Measured,
    work_per_call: float,
) -> BenchRecord:
    extra = dict(fields)
    value = None
    if measured.timing is not None:
        value = work_per_call / measured.timing.seconds_per_call
        extra.update(measured.timing.fields())
    if measured.note is not None:
        extra["note"] = measured.note
    return BenchRecord(SUITE, case, metric, value, unit, str(device), extra)


def matmul_flops_per_s(size: int, bench: BenchSettings) -> tuple[float, Timing]:
    """FLOP/s of a square float32 matmul of side `size` (2 s^3 FLOPs a call)."""
    g = torch.Generator().manual_seed(0)
    a, b = (torch.randn(size, size, generator=g).to(bench.device, DTYPE) for _ in range(2))
    out = torch.empty(size, size, device=bench.device, dtype=DTYPE)
    timing = time_call(lambda: torch.mm(a, b, out=out), bench.timing, synchronizer(bench.device))
    return 2.0 * size**3 / timing.seconds_per_call, timing


def _model_records(
    model: DeLaN,
    nv: int,
    batch: int,
    compiled: bool,
    bench: BenchSettings,
    peak: float,
    host: dict[str, Any],
) -> Iterator[BenchRecord]:
    """The figures of one chain and batch (`compiled`: the compiled forward dynamics too)."""
    sync = synchronizer(bench.device)
    x = random_inputs(nv, batch, bench.device)
    case = f"chain{nv}-b{batch}"
    trunk = _network(model).trunk
    fields = dict(
        nv=nv,
        batch=batch,
        dtype=str(DTYPE).removeprefix("torch."),
        system="chain",
        hidden=trunk.hidden[0].out_features,
        layers=len(trunk.hidden),
        **host,
    )
    fwd = _measure(_fwd(model), x, bench, sync)
    yield _record(case, "fwd_dyn_per_s", "evals/s", bench.device, fields, fwd, batch)
    yield _flops_record(case, model, fwd, peak, bench, fields)
    if compiled:
        yield _compiled_record(model, x, bench, case, fields)
    inv = _measure(_inv(model), x, bench, sync)
    yield _record(case, "inv_dyn_per_s", "evals/s", bench.device, fields, inv, batch)
    element = torch.empty((), dtype=DTYPE).element_size()
    naive = _measure(_naive(model), x, bench, sync, naive_bytes(nv, batch, element))
    yield _record(case, "naive_fwd_dyn_per_s", "evals/s", bench.device, fields, naive, batch)
    state = {k: v.clone() for k, v in model.state_dict().items()}
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-5)
    train = _measure(_train(model, optimizer), x, bench, sync)
    model.load_state_dict(state)  # the other figures see the same weights for every batch
    train_fields = {**fields, "integrator": model.integrator, "loss": model.loss_kind}
    yield _record(
        case, "train_samples_per_s", "samples/s", bench.device, train_fields, train, batch
    )


def _compiled_record(
    model: DeLaN, x: Inputs, bench: BenchSettings, case: str, fields: dict[str, Any]
) -> BenchRecord:
    """`compiled_fwd_dyn_per_s`, with the compile time (first call) in the record."""
    sync = synchronizer(bench.device)
    call = _compiled_fwd(model)(x)  # no trial batches: each new shape would recompile
    start = time.perf_counter()
    call()
    sync()
    compile_s = time.perf_counter() - start
    measured = Measured(time_call(call, bench.timing, sync))
    extra = {**fields, "compile_seconds": compile_s}
    return _record(
        case, "compiled_fwd_dyn_per_s", "evals/s", bench.device, extra, measured, x.batch
    )


def _flops_record(
    case: str,
    model: DeLaN,
    fwd: Measured,
    peak: float,
    bench: BenchSettings,
    fields: dict[str, Any],
) -> BenchRecord:
    flops = model_flops(model)
    extra = {**fields, "flops_per_sample": flops, "matmul_flops_per_s": peak}
    value = None
    if fwd.timing is None:
        extra["note"] = "skipped: fwd_dyn_per_s was not measured"
    else:
        achieved = flops * fields["batch"] / fwd.timing.seconds_per_call
        extra["achieved_flops_per_s"] = achieved
        value = achieved / peak
    return BenchRecord(SUITE, case, "flops_fraction", value, "fraction", str(bench.device), extra)


# ----------------------------------------------------------------------------- MuJoCo


def chain_mjcf(nv: int, link_length: float = 0.1, radius: float = 0.02) -> str:
    """MJCF of a serial chain of nv hinge links (capsules), axes alternating y and x,
    a motor on every hinge, contacts disabled."""
    if nv < 1:
        raise ValueError(f"nv must be >= 1, got {nv}")
    bodies, closing, motors = [], [], []
    for i in range(nv):
        axis = "0 1 0" if i % 2 == 0 else "1 0 0"
        pos = "0 0 0" if i == 0 else f"0 0 {-link_length}"
        bodies.append(
            f'<body name="link{i}" pos="{pos}"><joint name="j{i}" type="hinge" axis="{axis}"/>'
            f'<geom type="capsule" fromto="0 0 0 0 0 {-link_length}" size="{radius}"/>'
        )
        closing.append("</body>")
        motors.append(f'<motor joint="j{i}" gear="1"/>')
    return (
        f'<mujoco model="chain{nv}"><option timestep="0.002"><flag contact="disable"/></option>'
        f"<worldbody>{''.join(bodies)}{''.join(closing)}</worldbody>"
        f"<actuator>{''.join(motors)}</actuator></mujoco>"
    )


@dataclass
class MujocoSystem:
    model: mujoco.MjModel
    name: str
    note: str | None = None


def humanoid_cmu_path() -> Path | None:
    """dm_control's suite/humanoid_CMU.xml when dm_control is installed, else None."""
    try:
        return humanoid_cmu_xml()
    except (ModuleNotFoundError, FileNotFoundError):
        return None


def mujoco_system(nv: int, humanoid: bool = True) -> MujocoSystem:
    """The MuJoCo model timed against DeLaN at this nv (contacts disabled in every case).

    nv = 62 with `humanoid`: dm_control's CMU humanoid (free root + 56 hinges), else a chain.
    """
    if nv == HUMANOID_NV and humanoid:
        path = humanoid_cmu_path()
        if path is None:
            system = MujocoSystem(mujoco.MjModel.from_xml_string(chain_mjcf(nv)), "chain")
            system.note = "dm_control not installed: humanoid_CMU replaced by a 62-link chain"
        else:
            system = _load_humanoid(path, nv)
    else:
        system = MujocoSystem(mujoco.MjModel.from_xml_string(chain_mjcf(nv)), "chain")
    system.model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    return system


def _load_humanoid(path: Path, nv: int) -> MujocoSystem:
    try:
        model = mujoco.MjModel.from_xml_path(str(path))
    except ValueError as err:
        chain = mujoco.MjModel.from_xml_string(chain_mjcf(nv))
        return MujocoSystem(chain, "chain", f"humanoid_CMU failed to load ({err}); 62-link chain")
    if model.nv != nv:
        chain = mujoco.MjModel.from_xml_string(chain_mjcf(nv))
        return MujocoSystem(chain, "chain", f"humanoid_CMU has nv={model.nv}; 62-link chain")
    return MujocoSystem(model, "humanoid_CMU", "dm_control humanoid_CMU.xml, contacts disabled")


def _random_data(model: mujoco.MjModel, seed: int = 0) -> mujoco.MjData:
    """MjData at qpos0 perturbed, random velocities and controls."""
    rng = np.random.default_rng(seed)
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0 + 0.3 * rng.standard_normal(model.nq)
    mujoco.mj_normalizeQuat(model, data.qpos)
    data.qvel[:] = rng.standard_normal(model.nv)
    data.ctrl[:] = 0.1 * rng.standard_normal(model.nu)
    mujoco.mj_forward(model, data)
    return data


def _rollout_call(
    model: mujoco.MjModel, data: mujoco.MjData, batch: int, runner: mj_rollout.Rollout
) -> Callable[[], object]:
    """`batch` states, one `mj_step` each, through `mujoco.rollout` (outputs preallocated)."""
    spec = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
    size = mujoco.mj_stateSize(model, spec)
    state0 = np.empty(size)
    mujoco.mj_getState(model, data, state0, spec)
    initial = np.tile(state0, (batch, 1))
    control = np.tile(data.ctrl.copy(), (batch, 1, 1))
    out = np.empty((batch, 1, size))
    sensors = np.empty((batch, 1, model.nsensordata))
    datas = [mujoco.MjData(model) for _ in range(max(runner.nthread, 1))]

    def call() -> None:
        runner.rollout(model, datas, initial, control, state=out, sensordata=sensors)

    return call


def _mujoco_records(
    nv: int, options: DelanSuiteConfig, bench: BenchSettings, host: dict[str, Any]
) -> Iterator[BenchRecord]:
    system = mujoco_system(nv, options.humanoid)
    model, data = system.model, _random_data(system.model)
    case = f"mj-{system.name}{nv}"
    threads = host["threads"]
    fields = dict(nv=nv, dtype="float64", system=system.name, mujoco_version=mujoco.__version__)
    fields.update(host)
    if system.note is not None:
        fields["note"] = system.note
    loop = Measured(time_call(lambda: mujoco.mj_forward(model, data), bench.timing))
    loop_fields = {**fields, "batch": 1, "method": "python_loop", "threads": 1}
    yield _record(case, "mujoco_fwd_per_s", "evals/s", "cpu", loop_fields, loop, 1)
    with mj_rollout.Rollout(nthread=threads if threads > 1 else 0) as runner:
        for batch in (b for b in options.batch if b > 1):
            call = _rollout_call(model, data, batch, runner)
            measured = Measured(time_call(call, bench.timing))
            extra = {**fields, "batch": batch, "method": "rollout", "threads": threads}
            yield _record(
                f"{case}-b{batch}",
                "mujoco_rollout_steps_per_s",
                "steps/s",
                "cpu",
                extra,
                measured,
                batch,
            )


# ----------------------------------------------------------------------------- the suite


QUICK = {"nv": [2], "batch": [4], "matmul_size": 256, "compile_batch": []}  # quick=true


def run_delan_suite(options: DelanSuiteConfig, bench: BenchSettings) -> Iterator[BenchRecord]:
    """Every figure of the suite, one record at a time (see the module docstring)."""
    if bench.quick:
        options = replace(options, **QUICK)
    host = host_fields(bench.device)
    peak, timing = matmul_flops_per_s(options.matmul_size, bench)
    yield BenchRecord(
        SUITE,
        f"matmul{options.matmul_size}",
        "matmul_flops_per_s",
        peak,
        "FLOP/s",
        str(bench.device),
        {"dtype": "float32", "size": options.matmul_size, **host, **timing.fields()},
    )
    for nv in options.nv:
        model = chain_model(nv).to(device=bench.device, dtype=DTYPE)
        for batch in options.batch:
            log.info("delan suite: nv=%d batch=%d", nv, batch)
            compiled = batch in options.compile_batch
            yield from _model_records(model, nv, batch, compiled, bench, peak, host)
        yield from _mujoco_records(nv, options, bench, host)
