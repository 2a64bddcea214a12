"""Overrides for the smallest `python -m mbrl_delan.train` run the tests make (seconds)."""

TINY_TRAIN = [
    "logger=none",
    "threads=1",
    "env.episode_len=15",
    "env.horizon=5",
    "planner.num_samples=32",
    "planner.iterations=1",
    "budget.eval_episodes=1",
    "budget.oracle_episodes=1",
    "budget.final_eval_episodes=1",
    "budget.eval_every=1",
    "fit.max_epochs=5",
    "model.hidden=16",
]
