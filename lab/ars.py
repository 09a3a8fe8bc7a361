"""ARS V2-t in NumPy: the expert trainer for Hopper, HalfCheetah and Humanoid.

The paper (Sasaki et al., ICLR 2019, Sec. 5.1) trains its experts with TRPO and never ships
them. This project must run offline on a fresh machine, so it trains its own experts here with
Augmented Random Search (Mania, Guy & Recht, 2018, https://arxiv.org/abs/1803.07055),
Algorithm 2, variant V2-t, which needs no autodiff and runs its rollouts in parallel.
Walker2d and Ant are out of its reach within a practical budget on 2 cores; lab/sac.py
trains those.

Symbols of the ARS paper and where they live:

    M          policy matrix, (dim A, dim S)             -> ``weights``
    mu, Sigma  running mean and diagonal covariance of   -> ``ObservationStatistics``
               the states visited during training (V2)
    alpha      step size                                 -> ``ARSConfig.step_size``
    N          directions sampled per iteration          -> ``ARSConfig.directions``
    b          top directions used in the update (V2-t)  -> ``ARSConfig.top``
    nu         exploration noise                         -> ``ARSConfig.noise``
    delta_k    direction, an i.i.d. N(0, 1) matrix       -> ``deltas[k]``
    sigma_R    std of the 2b rewards used in the update  -> ``reward_std``

Policy: ``a = clip(M @ ((s - mu) / sqrt(diag Sigma)), low, high)``, deterministic; the best
evaluated one goes to the expert file (default ``experts/<env>.npz``) in the format that
``expert.load_expert`` reads. The checkpoint (default ``experts/checkpoints/<env>.ckpt.npz``,
git-ignored) holds everything needed to continue exactly.

Run ``python -m lab.ars --env Hopper-v4`` from the repository root; ``--help`` lists every
setting. Errors that a user can cause end in one line ``error: ...`` on stderr and exit
status 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import multiprocessing
import os
import signal
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

import harness
from expert import EXPERTS_DIR, ExpertPolicy, default_expert_path, env_dimensions, make_env
from harness import UserError, positive_int
from lab import shipping

CHECKPOINTS_DIR = EXPERTS_DIR / "checkpoints"
TRAINER = "ARS V2-t (Mania, Guy & Recht 2018, Algorithm 2)"  # in the expert file's record


# ---------------------------------------------------------------------------------------------
# Hyperparameters, per task
# ---------------------------------------------------------------------------------------------


@dataclass
class ARSConfig:
    """Hyperparameters of ARS V2-t; per-task defaults in ``ARS_DEFAULTS`` (rl-zoo ``ars.yml``)."""

    step_size: float = 0.02
    """alpha: step size of the update of M."""
    directions: int = 8
    """N: directions delta_k sampled per iteration (2N rollouts: M + nu delta, M - nu delta)."""
    top: int = 4
    """b: best directions, ranked by max(r+, r-), that enter the update (V2-t)."""
    noise: float = 0.03
    """nu: scale of the exploration perturbations."""
    survival_bonus: float = 0.0
    """Subtracted from every training reward, so that merely staying alive earns nothing."""
    steps: int = 10_000_000
    """Training budget in environment steps (perturbed rollouts only, not evaluations)."""
    eval_every: int = 10
    """Evaluate the unperturbed policy every this many iterations."""
    eval_episodes: int = 5
    """Episodes per evaluation; the best evaluated policy is the one shipped."""


# rl-baselines3-zoo ars.yml, "closest to the original paper", plus budgets.
ARS_DEFAULTS = {
    "Hopper-v4": dict(
        step_size=0.01, directions=8, top=4, noise=0.025, survival_bonus=1.0, steps=7_000_000
    ),
    "HalfCheetah-v4": dict(
        step_size=0.02, directions=32, top=4, noise=0.03, survival_bonus=0.0, steps=12_000_000
    ),
    "Walker2d-v4": dict(
        step_size=0.03, directions=40, top=30, noise=0.025, survival_bonus=1.0, steps=75_000_000
    ),
    "Ant-v4": dict(
        step_size=0.015, directions=60, top=20, noise=0.025, survival_bonus=1.0, steps=75_000_000
    ),
    "Humanoid-v4": dict(
        step_size=0.02, directions=256, top=256, noise=0.0075, survival_bonus=5.0, steps=25_000_000
    ),
}


def ars_config_for(env_id: str, **overrides) -> ARSConfig:
    """Task defaults, then any explicit overrides (``None`` means "not given")."""
    values = {**ARS_DEFAULTS.get(env_id, {})}
    values.update({key: value for key, value in overrides.items() if value is not None})
    return ARSConfig(**values)


def check_config(config: ARSConfig) -> None:
    """Refuse settings that cannot work, with one clear message."""
    positive, count = (0.0, float("inf"), "()"), (1, float("inf"), "[)")
    harness.check_numbers(
        config,
        {
            "step_size": positive,
            "noise": positive,
            **dict.fromkeys(("directions", "top", "steps", "eval_every", "eval_episodes"), count),
        },
    )
    if config.top > config.directions:
        raise UserError(f"--top {config.top} must be at most --directions {config.directions}")


# ---------------------------------------------------------------------------------------------
# Rollouts, in worker processes
# ---------------------------------------------------------------------------------------------


class ObservationStatistics:
    """Running mu and diag(Sigma) of all states visited in training (ARS V2).

    Kept as (count, mean, sum of squared deviations) and merged with Chan et al.'s parallel
    formula, so that merging per-rollout statistics in a fixed order is exact and deterministic.
    """

    def __init__(self, dim: int):
        self.count = 0
        self.mean = np.zeros(dim)
        self.squared_deviations = np.zeros(dim)

    def merge(self, count: int, mean: np.ndarray, squared_deviations: np.ndarray) -> None:
        if count == 0:
            return
        total = self.count + count
        delta = mean - self.mean
        self.mean = self.mean + delta * count / total
        self.squared_deviations = (
            self.squared_deviations + squared_deviations + delta**2 * self.count * count / total
        )
        self.count = total

    def std(self) -> np.ndarray:
        """sqrt(diag Sigma); 1 where a coordinate has not varied yet (so it stays unscaled)."""
        if self.count < 2:
            return np.ones_like(self.mean)
        variance = self.squared_deviations / (self.count - 1)
        return np.where(variance > 1e-8, np.sqrt(variance), 1.0)


# Each worker process keeps its own environment between tasks (made once by the initializer).
_worker_env: gym.Env | None = None


# Ctrl-C, `kill` and `timeout` may signal the whole process group. Only the parent acts on
# them: it checkpoints at the end of the iteration and then closes the pool. A worker that
# died of one mid-task would leave `pool.map` waiting forever.
_STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}


def _init_worker(env_id: str) -> None:
    global _worker_env
    # The worker started with the stop signals blocked (a signal mask survives exec; see
    # RolloutRunner). It leaves the parent's process group, drops what arrived meanwhile,
    # and keeps SIGTERM's default action, with which Pool.terminate stops it.
    os.setsid()
    for signum in _STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _worker_env = make_env(env_id)


def _rollout_task(task: tuple) -> tuple:
    return rollout(_worker_env, *task)


def rollout(
    env: gym.Env,
    weights: np.ndarray,
    obs_mean: np.ndarray,
    obs_std: np.ndarray,
    seed: int,
    survival_bonus: float,
    collect_states: bool,
) -> tuple:
    """One episode of the linear policy from ``reset(seed=seed)``.

    Returns (return minus survival bonus per step, steps, true return, state statistics) where
    the statistics are (count, mean, squared deviations) of the states acted upon, or None.
    """
    low, high = env.action_space.low, env.action_space.high
    observation, _ = env.reset(seed=seed)
    states, true_return, steps, done = [], 0.0, 0, False
    while not done:
        if collect_states:
            states.append(observation)
        action = np.clip(weights @ ((observation - obs_mean) / obs_std), low, high)  # (dim A,)
        observation, reward, terminated, truncated, _ = env.step(action)
        true_return += float(reward)
        steps += 1
        done = terminated or truncated
    statistics = None
    if collect_states:
        visited = np.asarray(states, dtype=np.float64)  # (T, dim S)
        mean = visited.mean(axis=0)  # (dim S,)
        statistics = (len(visited), mean, ((visited - mean) ** 2).sum(axis=0))
    return true_return - survival_bonus * steps, steps, true_return, statistics


class RolloutRunner:
    """Runs rollout tasks in ``workers`` processes (or in this process when workers == 1)."""

    def __init__(self, env_id: str, workers: int):
        self.pool = None
        self.mid_task = False  # a stop inside run() must not wait for the workers
        if workers > 1:
            # spawn: a clean interpreter per worker, safe whatever threads the parent holds.
            # The stop signals are blocked while the pool starts, so the workers inherit the
            # block and are never cut off in their start-up (seconds of imports) before
            # _init_worker takes them out of the process group; the parent gets its signals
            # when the block ends. The pool's threads keep the block: signals go to this one.
            signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
            try:
                context = multiprocessing.get_context("spawn")
                self.pool = context.Pool(workers, initializer=_init_worker, initargs=(env_id,))
            finally:
                signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)
        else:
            self.env = make_env(env_id)

    def run(self, tasks: list[tuple]) -> list[tuple]:
        if self.pool is not None:
            self.mid_task = True
            results = self.pool.map(_rollout_task, tasks, chunksize=1)
            self.mid_task = False
            return results
        return [rollout(self.env, *task) for task in tasks]

    def close(self) -> None:
        if self.pool is not None:
            self.pool.close()
            self.pool.join()
        else:
            self.env.close()

    def __enter__(self) -> RolloutRunner:
        return self

    def __exit__(self, error_type, error, traceback) -> None:
        # A stop at a checkpoint finds the workers idle (or one still starting, on a loaded
        # machine): close and join let them exit cleanly, where terminating a worker in the
        # middle of its imports leaves a child of it writing to a dead pipe. Only a stop
        # in the middle of the rollouts (a second signal) terminates them.
        if self.pool is not None and error_type is not None and self.mid_task:
            self.pool.terminate()
        self.close()


# ---------------------------------------------------------------------------------------------
# The run: its state, one iteration of Algorithm 2, evaluation and the training loop
# ---------------------------------------------------------------------------------------------


@dataclass
class ARSState:
    """Everything needed to continue a run exactly: the checkpoint's contents."""

    env_id: str
    seed: int
    config: ARSConfig
    weights: np.ndarray  # M, (dim A, dim S)
    statistics: ObservationStatistics
    rng: np.random.Generator
    iteration: int = 0
    env_steps: int = 0
    wall_seconds: float = 0.0
    best_return: float = -np.inf
    best_return_std: float = 0.0
    best_weights: np.ndarray | None = None
    best_obs_mean: np.ndarray | None = None
    best_obs_std: np.ndarray | None = None
    best_env_steps: int = 0
    commands: tuple[str, ...] = ()

    @property
    def interactions(self) -> int:
        """The environment steps, by the name harness.Clock reads."""
        return self.env_steps

    def save(self, path: Path) -> None:
        best = self.best_weights is not None
        harness.save_arrays(
            path,
            dict(
                env_id=np.array(self.env_id),
                seed=np.array(self.seed),
                config=np.array(json.dumps(dataclasses.asdict(self.config))),
                weights=self.weights,
                stat_count=np.array(self.statistics.count),
                stat_mean=self.statistics.mean,
                stat_squared_deviations=self.statistics.squared_deviations,
                rng_state=np.array(json.dumps(self.rng.bit_generator.state)),
                iteration=np.array(self.iteration),
                env_steps=np.array(self.env_steps),
                wall_seconds=np.array(self.wall_seconds),
                best_return=np.array(self.best_return),
                best_return_std=np.array(self.best_return_std),
                best_weights=self.best_weights if best else np.zeros(0),
                best_obs_mean=self.best_obs_mean if best else np.zeros(0),
                best_obs_std=self.best_obs_std if best else np.zeros(0),
                best_env_steps=np.array(self.best_env_steps),
                commands=np.array(json.dumps(list(self.commands))),
            ),
        )

    @classmethod
    def load(cls, path: Path) -> ARSState:
        file = harness.load_arrays(path)  # a missing or damaged file: one line naming it
        try:
            statistics = ObservationStatistics(file["stat_mean"].shape[0])
            statistics.count = int(file["stat_count"])
            statistics.mean = file["stat_mean"]
            statistics.squared_deviations = file["stat_squared_deviations"]
            rng = np.random.default_rng()
            rng.bit_generator.state = json.loads(str(file["rng_state"]))
            best = file["best_weights"].size > 0
            return cls(
                env_id=str(file["env_id"]),
                seed=int(file["seed"]),
                config=ARSConfig(**json.loads(str(file["config"]))),
                weights=file["weights"],
                statistics=statistics,
                rng=rng,
                iteration=int(file["iteration"]),
                env_steps=int(file["env_steps"]),
                wall_seconds=float(file["wall_seconds"]),
                best_return=float(file["best_return"]),
                best_return_std=float(file["best_return_std"]),
                best_weights=file["best_weights"] if best else None,
                best_obs_mean=file["best_obs_mean"] if best else None,
                best_obs_std=file["best_obs_std"] if best else None,
                best_env_steps=int(file["best_env_steps"]),
                commands=tuple(json.loads(str(file["commands"]))),
            )
        except (ValueError, KeyError, TypeError) as error:
            raise UserError(f"{path}: not a valid ARS checkpoint ({error})") from None


def ars_iteration(state: ARSState, runner: RolloutRunner) -> None:
    """One iteration of Algorithm 2 (V2-t), updating M and (mu, Sigma) in place."""
    config, rng = state.config, state.rng
    # mu and Sigma are frozen for the whole iteration (line 5 uses those of iteration j).
    obs_mean, obs_std = state.statistics.mean.copy(), state.statistics.std()
    # Line 4: delta_1..delta_N with i.i.d. standard normal entries, each (dim A, dim S).
    deltas = rng.standard_normal((config.directions, *state.weights.shape))  # (N, dim A, dim S)
    # Every rollout gets its own reset seed from the one Generator, so that results do not
    # depend on which worker runs which rollout, and a resumed run continues exactly.
    reset_seeds = rng.integers(0, 2**31 - 1, size=(config.directions, 2))
    tasks = []
    for k in range(config.directions):
        for sign_index, sign in enumerate((+1.0, -1.0)):
            # Line 5: pi_{j,k,+/-}(s) = (M_j +/- nu delta_k) diag(Sigma_j)^(-1/2) (s - mu_j).
            perturbed = state.weights + sign * config.noise * deltas[k]
            tasks.append(
                (
                    perturbed,
                    obs_mean,
                    obs_std,
                    int(reset_seeds[k, sign_index]),
                    config.survival_bonus,
                    True,
                )
            )
    results = runner.run(tasks)
    rewards = np.array([result[0] for result in results]).reshape(config.directions, 2)  # (N, 2)
    state.env_steps += sum(result[1] for result in results)
    # Line 8 (V2): update mu and Sigma with every state visited in this iteration, in task order.
    for result in results:
        state.statistics.merge(*result[3])
    # Line 6 (V2-t): keep the b directions with the largest max(r+, r-).
    top = np.argsort(-rewards.max(axis=1), kind="stable")[: config.top]
    # Line 7: M += alpha / (b sigma_R) sum_k (r+ - r-) delta_k, sigma_R over the 2b rewards.
    reward_std = rewards[top].std()
    if reward_std < 1e-8:
        reward_std = 1.0  # all b directions scored alike: no signal, and no division by zero
    differences = rewards[top, 0] - rewards[top, 1]  # (b,)
    step = np.tensordot(differences, deltas[top], axes=1)  # (dim A, dim S)
    state.weights = state.weights + config.step_size / (config.top * reward_std) * step
    state.iteration += 1


def evaluate_linear(state: ARSState, runner: RolloutRunner) -> np.ndarray:
    """True returns of the unperturbed policy M over ``eval_episodes`` fresh seeds.

    The seeds come from their own Generator, derived from (seed, iteration), so that how
    often one evaluates does not change the training run, and the shipped policy is not
    chosen on the fixed seeds that lab/table.py reports.
    """
    obs_mean, obs_std = state.statistics.mean.copy(), state.statistics.std()
    eval_rng = np.random.default_rng([state.seed, state.iteration])
    seeds = eval_rng.integers(2**20, 2**31 - 1, size=state.config.eval_episodes)
    tasks = [(state.weights, obs_mean, obs_std, int(seed), 0.0, False) for seed in seeds]
    return np.array([result[2] for result in runner.run(tasks)])


def train(
    env_id: str,
    seed: int,
    config: ARSConfig,
    workers: int,
    checkpoint_path: Path,
    expert_path: Path,
    resume: bool = False,
    command: str = "",
    checkpoint_seconds: float = 10.0,
    log: Callable[[str], None] = shipping.say,
) -> ARSState:
    """Run ARS V2-t until ``config.steps`` environment steps; keep the best evaluated policy.

    A fresh run refuses a checkpoint path that holds a run; ``resume`` continues that run
    exactly, with its own settings and the budget of ``config.steps``.
    """
    check_config(config)
    harness.will_checkpoint(checkpoint_path)  # a signal's last line: is there a run to resume
    env = make_env(env_id)
    dim_s, dim_a = env_dimensions(env)
    action_low = env.action_space.low.astype(np.float64)
    action_high = env.action_space.high.astype(np.float64)
    env.close()
    if resume:
        if not checkpoint_path.exists():
            raise UserError(f"--resume: no checkpoint at {checkpoint_path}")
        state = ARSState.load(checkpoint_path)
        if state.env_id != env_id:
            raise UserError(f"{checkpoint_path}: checkpoint is for {state.env_id}, not {env_id}")
        # Only the budget may change on resume; anything else would not be the same run.
        state.config = dataclasses.replace(state.config, steps=config.steps)
        log(f"resumed {env_id} at iteration {state.iteration}, {state.env_steps} env steps")
    else:
        if checkpoint_path.exists():
            raise UserError(
                f"{checkpoint_path} already holds a run; continue it with --resume"
                " or choose another --checkpoint"
            )
        state = ARSState(
            env_id=env_id,
            seed=seed,
            config=config,
            weights=np.zeros((dim_a, dim_s)),  # M_0 = 0 (Algorithm 2, line 2)
            statistics=ObservationStatistics(dim_s),
            rng=np.random.default_rng(seed),
        )
    state.commands = (*state.commands, command)
    log(
        f"ARS V2-t on {env_id}: seed {state.seed}, {workers} workers, "
        f"{json.dumps(dataclasses.asdict(state.config))}"
    )

    if not resume:  # a resumed run carries its own best
        state.best_return = shipping.bar_to_beat(env_id, expert_path, log)
    clock = harness.Clock(state, checkpoint_seconds, log_every=math.inf)  # wall time, pacing
    with RolloutRunner(env_id, workers) as runner:
        while state.env_steps < state.config.steps:
            ars_iteration(state, runner)
            finished = state.env_steps >= state.config.steps
            if state.iteration % state.config.eval_every == 0 or finished:
                returns = evaluate_linear(state, runner)
                clock.tick()
                improved = returns.mean() > state.best_return
                if improved:
                    state.best_return, state.best_return_std = returns.mean(), returns.std()
                    state.best_weights = state.weights.copy()
                    state.best_obs_mean = state.statistics.mean.copy()
                    state.best_obs_std = state.statistics.std()
                    state.best_env_steps = state.env_steps
                    best = (state.best_weights, state.best_obs_mean, state.best_obs_std)
                    policy = ExpertPolicy(env_id, action_low, action_high, *best)
                    shipping.ship(
                        policy, expert_path, returns, TRAINER, state, state.seed, state.config
                    )
                log(
                    f"iteration {state.iteration:5d}  env steps {state.env_steps:10d}  "
                    f"wall {state.wall_seconds:8.1f} s  eval return {returns.mean():9.1f} "
                    f"± {returns.std():6.1f}" + ("  (best, saved)" if improved else "")
                )
            clock.tick()
            if clock.checkpoint_due():
                state.save(checkpoint_path)
                clock.checkpointed()
                harness.stop_if_requested()  # Ctrl-C or kill, with the checkpoint written
        state.save(checkpoint_path)
    if state.best_weights is None:
        log(
            f"done: no evaluation beat the existing {expert_path} (eval return "
            f"{state.best_return:.1f}); left it unchanged"
        )
    else:
        log(
            f"done: best eval return {state.best_return:.1f} ± {state.best_return_std:.1f} at "
            f"{state.best_env_steps} env steps; expert in {expert_path}"
        )
    return state


# ---------------------------------------------------------------------------------------------
# Command line: python -m lab.ars --env ENV [flags]
# ---------------------------------------------------------------------------------------------


def add_config_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per ARSConfig field, its help the field's docstring. Every default is None,
    "not given": the task's defaults (ARS_DEFAULTS) apply, then the flags given. A count
    may be written as 7e6."""
    docs = harness.field_docstrings(ARSConfig)
    for field in dataclasses.fields(ARSConfig):
        parser.add_argument(
            harness.flag(field.name),
            type=float if field.type in ("float", float) else positive_int,
            default=None,
            help=f"{docs[field.name]} (default: per task, else {field.default})",
        )


def build_parser() -> argparse.ArgumentParser:
    parser = harness.CommandLineParser(
        prog="python -m lab.ars",
        description=__doc__.splitlines()[0],
        epilog="Per-task defaults (rl-zoo ars.yml): "
        + "; ".join(
            f"{env}: " + ", ".join(f"{harness.flag(k)} {v:g}" for k, v in values.items())
            for env, values in ARS_DEFAULTS.items()
        ),
    )
    parser.add_argument("--env", required=True, help="gymnasium id, e.g. Hopper-v4")
    parser.add_argument("--seed", type=harness.seed_number, default=0)
    parser.add_argument(
        "--workers",
        type=positive_int,
        default=os.cpu_count() or 1,
        help="rollout processes (default: CPU count)",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue exactly from --checkpoint, with its settings (only --steps may change)",
    )
    parser.add_argument("--checkpoint", help="default: experts/checkpoints/<env>.ckpt.npz")
    parser.add_argument("--out", help="expert file (default: experts/<env>.npz)")
    add_config_flags(parser)
    return parser


def run_from_args(args: argparse.Namespace, argv: list[str]) -> ARSState:
    fields = dataclasses.fields(ARSConfig)
    given = {f.name: getattr(args, f.name) for f in fields if getattr(args, f.name) is not None}
    checkpoint = Path(args.checkpoint or CHECKPOINTS_DIR / f"{args.env}.ckpt.npz")
    if args.resume and checkpoint.exists():  # the run's own settings; only the budget may change
        saved = dataclasses.asdict(ARSState.load(checkpoint).config)
        config = ARSConfig(**harness.resumed_settings(saved, given, ("steps",)))
    else:
        config = ars_config_for(args.env, **given)
    return train(
        args.env,
        args.seed,
        config,
        args.workers,
        checkpoint,
        Path(args.out or default_expert_path(args.env)),
        resume=args.resume,
        command=shipping.command_line("lab.ars", argv),
    )


def main(argv: list[str] | None = None) -> int:
    return harness.cli_main(argv, lambda argv: build_parser().parse_args(argv), run_from_args)


if __name__ == "__main__":
    sys.exit(main())
