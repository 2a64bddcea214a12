"""Stand-in for your robot's logs: a MuJoCo arm tracking smooth random paths, saved in the
schema `python -m mbrl_delan.fit data=arrays` reads (`mbrl_delan.data.arrays`).

    python examples/own_robot/log_arm.py arm3 arm3.npz
    python examples/own_robot/log_arm.py arm3 arm3_more.csv --trajectories 4 --seed 1

Each trajectory is PD tracking of a cubic-spline path through random knots
(`mbrl_delan.data.synthetic.trajectory_dataset`); the file holds q, qd, qdd, tau, t,
trajectory and MuJoCo's parts of tau (tau_inertial, tau_coriolis, tau_gravity). Drop the
qdd field (``--no-qdd``) to have the fit compute it from qd, as for a robot without
acceleration estimates.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import torch

from mbrl_delan.data.arrays import save_arrays
from mbrl_delan.data.synthetic import trajectory_dataset
from mbrl_delan.systems.system import load_system

log = logging.getLogger("log_arm")


def main(argv: list[str] | None = None) -> Path:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("system", help="a shipped MJCF (arm2, arm3) or an .xml file")
    p.add_argument("out", type=Path, help="the data file: .npz, .pt or .csv")
    p.add_argument("--trajectories", type=int, default=22)
    p.add_argument("--steps", type=int, default=160, help="control steps per trajectory")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-qdd", action="store_true", help="leave qdd out of the file")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    system = load_system(args.system)
    data = trajectory_dataset(
        system, args.trajectories, args.steps, torch.Generator().manual_seed(args.seed)
    )
    if args.no_qdd:
        del data["qdd"]
    path = save_arrays(data, args.out)
    log.info(
        "%s: %d samples of %s (%d trajectories)",
        path,
        data.shape[0],
        system.name,
        args.trajectories,
    )
    return path


if __name__ == "__main__":
    main()
