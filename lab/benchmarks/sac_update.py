"""Time one SAC update (sac.update) at Walker2d-v4 sizes, against its GEMM floor.

    python -m lab.benchmarks.sac_update [--repeats 300] [--threads 1]

dim S = 17, dim A = 6, 256-256 networks, batch 256, float32: the settings of the
Walker2d-v4 expert run. Reports wall and CPU time per update (CPU time is what the
update costs; wall time also counts other processes sharing the cores), and the GEMM
floor: every matrix product one update performs, at its shapes, timed alone.
floor_fraction = floor / update (1.0: element-wise work and Python overhead free).
The last line is machine-readable.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from threadpoolctl import threadpool_limits

from lab import sac
from lab.benchmarks.update import time_gemm_floor

STATE_DIM, ACTION_DIM = 17, 6


def gemm_shapes(batch: int, hidden: int) -> list[tuple[int, int, int]]:
    """(rows, inner, cols) of every matrix product of `sac.update`, two hidden layers.

    Forward: the policy twice (s, s'), each critic three times ((s', a') as a target,
    (s, a), (s, a_pi)), the critic's input in two blocks. Backward: both critics with
    weight gradients (the TD loss), both without, to the action block only (the
    policy loss), and the policy with weight gradients but no input gradient. A
    critic's single output column is a broadcast, not a product (nets.MLP.backward).
    """
    b, h, s, a = batch, hidden, STATE_DIM, ACTION_DIM
    policy_forward = [(b, s, h), (b, h, h), (b, h, 2 * a)]
    critic_forward = [(b, s, h), (b, a, h), (b, h, h), (b, h, 1)]
    critic_weights = [(h, b, 1), (h, b, h), (b, h, h), (s, b, h), (a, b, h)]
    critic_actions = [(b, h, h), (b, h, a)]
    policy_weights = [(h, b, 2 * a), (b, 2 * a, h), (h, b, h), (b, h, h), (s, b, h)]
    return (
        2 * policy_forward
        + 6 * critic_forward
        + 2 * critic_weights
        + 2 * critic_actions
        + policy_weights
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=300)
    parser.add_argument("--threads", type=int, default=1, help="BLAS threads (training uses 1)")
    args = parser.parse_args()
    config = sac.SACConfig()
    rng = np.random.default_rng(0)
    agent = sac.Agent.create(STATE_DIM, ACTION_DIM, config, rng)
    replay = sac.ReplayBuffer(50_000, STATE_DIM, ACTION_DIM)
    for _ in range(50_000):
        replay.add(
            rng.standard_normal(STATE_DIM),
            rng.uniform(-1, 1, ACTION_DIM),
            rng.standard_normal(),
            rng.standard_normal(STATE_DIM),
            False,
        )
    with threadpool_limits(limits=args.threads, user_api="blas"):
        for _ in range(30):  # warm up: Adam's moments, malloc's reusable memory
            sac.update(agent, replay.sample(rng, config.batch_size), config, rng)
        wall, cpu = time.perf_counter(), time.process_time()
        for _ in range(args.repeats):
            sac.update(agent, replay.sample(rng, config.batch_size), config, rng)
        wall = (time.perf_counter() - wall) / args.repeats
        cpu = (time.process_time() - cpu) / args.repeats
        shapes = gemm_shapes(config.batch_size, config.hidden[0])
        floor = time_gemm_floor(shapes, np.random.default_rng(0), 20, (args.threads,))
    flops = 2 * sum(r * i * c for r, i, c in gemm_shapes(config.batch_size, config.hidden[0]))
    print(f"one update: {1e3 * wall:.2f} ms wall, {1e3 * cpu:.2f} ms CPU ({args.threads} thread)")
    print(f"GEMM floor: {1e3 * floor:.2f} ms for {flops / 1e6:.0f} MFLOP")
    print(f"floor_fraction: {floor / cpu:.2f}; at this CPU time, 10^6 updates take "
          f"{1e6 * cpu / 3600:.1f} h")  # fmt: skip
    result = dict(update_ms_wall=1e3 * wall, update_ms_cpu=1e3 * cpu, floor_ms=1e3 * floor)
    print(json.dumps({k: round(v, 3) for k, v in result.items()}))


if __name__ == "__main__":
    main()
