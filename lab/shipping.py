"""Shipping an expert: what the expert trainers (lab/ars.py, lab/sac.py) share.

A run keeps its best evaluated policy in an expert file (default experts/<env>.npz), with
the provenance that expert.load_expert reads back: the trainer, the command of every
session, seed, hyperparameters, env steps, wall time and the evaluation that chose it. A
fresh run never replaces an expert with a worse one: it starts from the bar that the
file's recorded evaluation sets.
"""

from __future__ import annotations

import dataclasses
import math
import shlex
from pathlib import Path

import numpy as np

import expert
from harness import UserError


def say(line: str) -> None:
    """The trainers' log: stdout, flushed, so that a log file follows the run."""
    print(line, flush=True)


def command_line(module: str, argv: list[str]) -> str:
    """The command that ran this session, as the expert file records it."""
    return shlex.join(["python", "-m", module, *map(str, argv)])


def bar_to_beat(env_id: str, path: Path, log=say) -> float:
    """The evaluation a fresh run must beat to write `path`: the one recorded in the expert
    already there, or -inf (no file, or one that does not load)."""
    try:
        recorded = expert.load_expert(env_id, path).metadata.get("eval_return_mean")
    except UserError:
        return -math.inf
    if recorded is None:
        return -math.inf
    log(f"{path} exists (eval return {recorded:.1f}); it is replaced only by a better evaluation")
    return float(recorded)


def ship(
    policy: expert.ExpertPolicy, path: Path, returns: np.ndarray, trainer: str, run, seed, config
) -> None:
    """Write `policy`, evaluated with `returns`, to the expert file with its provenance:
    the `trainer`, the run's counters (`run`: its commands, interactions and wall_seconds,
    as lab.ars.ARSState and lab.sac.Progress hold them), `seed` and the hyperparameters
    (`config`, a dataclass)."""
    policy.save(
        path,
        trainer=trainer,
        commands=list(run.commands),
        seed=seed,
        hyperparameters=dataclasses.asdict(config),
        env_steps=run.interactions,
        wall_seconds=round(run.wall_seconds, 1),
        eval_return_mean=float(returns.mean()),
        eval_return_std=float(returns.std()),
        eval_episodes=len(returns),
    )
