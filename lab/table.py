"""Table 1 of the paper, measured: per task dim S, dim A, and the returns of a uniformly
random policy and of the shipped expert, the two ends of the normalised score.

`python -m lab.table` measures the paper's five -v4 tasks and the three -v5 tasks that a
-v4 expert serves over 10 seeded episodes (reset seeds 0..9), writes experts/table.json
(which expert.reference_returns reads) and prints the table in Markdown; `--episodes`,
`--seed` and `--out` change that. `--tasks` measures only some rows: the rows of the other
tasks already in `--out` are kept as they are.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterable
from pathlib import Path

import gymnasium as gym
import numpy as np

import expert
import harness

# The paper's five tasks, on the MuJoCo versions gymnasium still ships (-v1 is long gone).
PAPER_TASKS = ("Hopper-v4", "HalfCheetah-v4", "Walker2d-v4", "Ant-v4", "Humanoid-v4")
# gymnasium's -v5 versions of them that a -v4 expert serves (expert.SERVED_BY).
TABLE_TASKS = PAPER_TASKS + tuple(expert.SERVED_BY)


def run_episode(env: gym.Env, policy_fn: Callable, seed: int) -> tuple[float, int]:
    """One episode from ``env.reset(seed=seed)``; returns (true return, steps)."""
    observation, _ = env.reset(seed=seed)
    episode_return, steps, done = 0.0, 0, False
    while not done:
        observation, reward, terminated, truncated, _ = env.step(policy_fn(observation))
        episode_return += float(reward)
        steps += 1
        done = terminated or truncated
    return episode_return, steps


def returns(env: gym.Env, policy_fn: Callable, seeds: Iterable[int]) -> np.ndarray:
    """True returns of one episode per reset seed (lab/sac.py evaluates with these too)."""
    return np.array([run_episode(env, policy_fn, int(seed))[0] for seed in seeds])


def evaluate(env_id: str, policy_fn: Callable, episodes: int, seed: int) -> np.ndarray:
    """Returns of ``episodes`` seeded episodes (``env.reset(seed=seed + i)``), true reward."""
    with expert.make_env(env_id) as env:
        return returns(env, policy_fn, range(seed, seed + episodes))


def random_policy_returns(env_id: str, episodes: int, seed: int) -> np.ndarray:
    """Returns of uniform random actions; the action space is seeded like the resets."""
    with expert.make_env(env_id) as env:
        results = []
        for i in range(episodes):
            env.action_space.seed(seed + i)
            results.append(run_episode(env, lambda _: env.action_space.sample(), seed + i)[0])
        return np.array(results)


def numeric_platform() -> dict:
    """What decides the last bits of a return: library versions and the BLAS kernel in use.

    The returns of the SAC experts (float32 networks) on Ant-v4 change with the kernel that
    OpenBLAS picks for the CPU (for example 4932 with SkylakeX, 4454 with Haswell over
    the same 10 seeded episodes) because an episode ends when rounding tips the robot out of
    its healthy range; OPENBLAS_CORETYPE chooses the kernel.
    """
    import mujoco
    from threadpoolctl import threadpool_info

    blas = [pool for pool in threadpool_info() if pool["user_api"] == "blas"]
    return dict(
        numpy=np.__version__,
        mujoco=mujoco.__version__,
        gymnasium=gym.__version__,
        blas_kernel=blas[0].get("architecture", "unknown") if blas else "none",
    )


def measure_table(
    episodes: int = 10, seed: int = 0, tasks=PAPER_TASKS, log: Callable[[str], None] = print
) -> dict:
    """dim S, dim A, random and expert returns (mean, std over seeded episodes) per task."""
    table = {}
    for env_id in tasks:
        with expert.make_env(env_id) as env:
            dim_s, dim_a = expert.env_dimensions(env)
        random_returns = random_policy_returns(env_id, episodes, seed)
        row = dict(
            dim_s=dim_s,
            dim_a=dim_a,
            episodes=episodes,
            seed=seed,
            random_mean=float(random_returns.mean()),
            random_std=float(random_returns.std()),
            expert_mean=None,
            expert_std=None,
            measured_with=numeric_platform(),
        )
        if expert.serving_expert_path(env_id).exists():
            policy = expert.load_expert(env_id)
            expert_returns = evaluate(env_id, policy.act, episodes, seed)
            row.update(expert_mean=float(expert_returns.mean()))
            row.update(expert_std=float(expert_returns.std()))
            if policy.env_id != env_id:
                row.update(expert_trained_on=policy.env_id)
        log(f"{env_id}: random {row['random_mean']:.2f}, expert {row['expert_mean']}")
        table[env_id] = row
    return table


def table_markdown(table: dict) -> str:
    lines = ["| Task | dim S | dim A | Random policy | Expert |", "|---|---:|---:|---:|---:|"]
    for env_id, row in table.items():
        expert_cell = (
            f"{row['expert_mean']:.2f} ± {row['expert_std']:.2f}"
            if row["expert_mean"] is not None
            else "missing (not trained yet)"
        )
        lines.append(
            f"| {env_id} | {row['dim_s']} | {row['dim_a']} | "
            f"{row['random_mean']:.2f} ± {row['random_std']:.2f} | {expert_cell} |"
        )
    return "\n".join(lines)


def parse(argv: list[str]):
    parser = harness.CommandLineParser(
        prog="python -m lab.table", description="Measure Table 1 for the paper's tasks."
    )
    parser.add_argument("--episodes", type=harness.positive_int, default=10)
    parser.add_argument(
        "--tasks",
        nargs="+",
        default=list(TABLE_TASKS),
        help="only these rows; the other rows of --out are kept (default: every row)",
    )
    parser.add_argument(
        "--seed", type=harness.seed_number, default=0, help="episode i is reset with seed + i"
    )
    parser.add_argument("--out", default=str(expert.TABLE_PATH))
    return parser.parse_args(argv)


def run(args, argv) -> None:
    out = Path(args.out)
    if out.is_dir():  # refused now, not after hours of measuring
        raise harness.UserError(f"--out {out} is a directory; give a file name")
    if any(parent.exists() and not parent.is_dir() for parent in out.parents):
        raise harness.UserError(f"--out {out} lies under a file")
    for env_id in args.tasks:  # a wrong task stops here, before hours of measuring
        expert.make_env(env_id).close()
    kept = {}
    if out.is_file():
        try:
            kept = json.loads(out.read_text())
        except (OSError, ValueError) as error:
            raise harness.UserError(f"{out}: not a valid table ({error})") from None
        if not isinstance(kept, dict):
            raise harness.UserError(f"{out}: not a valid table (a JSON object of rows)")
    measured = measure_table(
        args.episodes, args.seed, args.tasks, log=lambda line: print(line, flush=True)
    )
    table = kept | measured
    harness.write_text(out, json.dumps(table, indent=2) + "\n")
    print(f"wrote {args.out}\n\n{table_markdown(table)}")


def main(argv: list[str] | None = None) -> int:
    return harness.cli_main(argv, parse, run, checkpoints=False)


if __name__ == "__main__":
    sys.exit(main())
