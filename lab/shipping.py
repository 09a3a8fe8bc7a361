"""Shipping an expert: what the expert trainers (lab/ars.py, lab/sac.py) share.

A run keeps its best evaluated policy in an expert file (default experts/<env>.npz), with
the provenance that expert.load_expert reads back: the trainer, the command of every
session, seed, hyperparameters, env steps, wall time and the evaluation that chose it. A
fresh run never replaces an expert with a worse one: it starts from the bar that the
file's recorded evaluation sets.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shlex
from pathlib import Path

import numpy as np

import expert
import harness
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


def save_expert(policy: expert.ExpertPolicy, path: Path, **metadata) -> None:
    """Write `policy` as an expert file that expert.load_expert reads, with its provenance
    (the policy's metadata updated by `metadata`: command, seed, steps, wall time, ...).

    An ARS file holds ``weights``, ``obs_mean``, ``obs_std`` (the format of the first
    shipped experts, which has no ``kind``); a SAC file holds ``kind`` = "sac-mlp",
    the layer ``sizes`` and the network's ``policy/W0``, ``policy/b0``, ... .
    """
    if policy.network is None:
        arrays = dict(weights=policy.weights, obs_mean=policy.obs_mean, obs_std=policy.obs_std)
    else:
        arrays = dict(kind=np.array(expert.SAC_MLP), sizes=np.array(policy.network.sizes))
        arrays |= policy.network.state("policy")
    arrays |= dict(action_low=policy.action_low, action_high=policy.action_high)
    record = json.dumps({**policy.metadata, **metadata}, sort_keys=True)
    harness.save_arrays(
        path, {"env_id": np.array(policy.env_id), **arrays, "metadata": np.array(record)}
    )


def ship(
    policy: expert.ExpertPolicy, path: Path, returns: np.ndarray, trainer: str, run, seed, config
) -> None:
    """Write `policy`, evaluated with `returns`, to the expert file with its provenance:
    the `trainer`, the run's counters (`run`: its commands, interactions and wall_seconds,
    as lab.ars.ARSState and lab.sac.Progress hold them), `seed` and the hyperparameters
    (`config`, a dataclass)."""
    save_expert(
        policy,
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
