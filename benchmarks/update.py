"""Time one full update (critic step, target update, policy step) at the paper's sizes.

    python -m benchmarks.update [--repeats 20] [--noise-samples 128] [--target-samples 8]

Hopper-v4 dimensions (dim S = 11, dim A = 3), PN 100-100, QN 500-500, minibatch 64,
128 noise samples per state: 8 192 rows through the critic and back per policy step.
In the same run it times the GEMM floor: every matrix product of one update, at the
update's shapes, each in NumPy with the faster of one BLAS thread or all cores, and no
element-wise work at all. floor_fraction = floor / update is the share of the GEMM floor's speed
that the real update reaches (1.0 would mean element-wise work and overhead are free).
The last line is machine-readable.
"""

from __future__ import annotations

import argparse
import os
import time
import tracemalloc

import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits

import offpac_il

STATE_DIM, ACTION_DIM = 11, 3


def make_problem(config: offpac_il.Config, rng: np.random.Generator):
    learner = offpac_il.Learner.create(STATE_DIM, STATE_DIM, ACTION_DIM, config, rng)
    replay = offpac_il.ReplayBuffer(config.replay_size, STATE_DIM, ACTION_DIM)
    for _ in range(config.replay_size):
        replay.add(
            rng.standard_normal(STATE_DIM),
            rng.uniform(-1, 1, ACTION_DIM),
            rng.standard_normal(STATE_DIM),
            False,
        )
    n_expert = 400
    expert_buffer = offpac_il.Triplets(
        rng.standard_normal((n_expert, STATE_DIM), dtype=np.float32),
        rng.uniform(-1, 1, (n_expert, ACTION_DIM)).astype(np.float32),
        rng.standard_normal((n_expert, STATE_DIM), dtype=np.float32),
        np.zeros(n_expert, bool),
    )
    return learner, replay, expert_buffer


def gemm_shapes(config: offpac_il.Config) -> list[tuple[int, int, int]]:
    """(rows, inner, cols) of every matrix product in one update, forward and backward."""
    b, z, k = config.batch_size, config.noise_samples, config.target_samples
    policy = [STATE_DIM + STATE_DIM, *config.policy_hidden, ACTION_DIM]
    critic = [STATE_DIM + ACTION_DIM, *config.critic_hidden, 1]
    layers = lambda sizes: list(zip(sizes[:-1], sizes[1:], strict=True))  # noqa: E731
    shapes = []
    # Critic step: targets (policy + target critic forward on 2b*k rows), then the critic
    # forward and backward (input and weight gradients) on 2b rows.
    for rows, sizes in ((2 * b * k, policy), (2 * b * k, critic)):
        shapes += [(rows, i, o) for i, o in layers(sizes)]
    for i, o in layers(critic):
        shapes += [(2 * b, i, o), (2 * b, o, i), (i, 2 * b, o)]
    # Policy step on b*z rows: policy forward and full backward; critic forward and
    # backward to its input only.
    for i, o in layers(policy):
        shapes += [(b * z, i, o), (b * z, o, i), (i, b * z, o)]
    for i, o in layers(critic):
        shapes += [(b * z, i, o), (b * z, o, i)]
    return shapes


def time_gemm_floor(shapes, rng, repeats: int) -> float:
    """Sum over the shapes of each product's median time, with the BLAS thread count
    (one, or all cores) that is faster for that shape: the best NumPy can do."""
    total = 0.0
    for m, k, n in shapes:
        a = rng.standard_normal((m, k), dtype=np.float32)
        b = rng.standard_normal((k, n), dtype=np.float32)
        candidates = []
        for threads in sorted({1, os.cpu_count() or 1}):
            with threadpool_limits(limits=threads, user_api="blas"):
                candidates.append(median_seconds(lambda a=a, b=b: np.matmul(a, b), repeats))
        total += min(candidates)
    return total


def median_seconds(fn, repeats: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--noise-samples", type=int, default=128)
    parser.add_argument("--target-samples", type=int, default=offpac_il.Config.target_samples)
    args = parser.parse_args()
    config = offpac_il.Config(noise_samples=args.noise_samples, target_samples=args.target_samples)
    rng = np.random.default_rng(0)
    learner, replay, expert_buffer = make_problem(config, rng)

    def one_update():
        offpac_il.update(learner, expert_buffer, replay, config, 0, rng)

    # As in training: BLAS on one thread, parallelism from map_chunks over row chunks.
    with threadpool_limits(limits=1, user_api="blas"):
        update_s = median_seconds(one_update, args.repeats)
        tracemalloc.start()
        one_update()
        peak_bytes = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    floor_s = time_gemm_floor(gemm_shapes(config), rng, args.repeats)

    blas = [
        f"{i['internal_api']} {i.get('version')} ({i['num_threads']} threads)"
        for i in threadpool_info()
        if i["user_api"] == "blas"
    ]
    print(f"cores: {os.cpu_count()}  numpy {np.__version__}  BLAS: {', '.join(blas)}")
    print(
        f"noise samples {config.noise_samples}, target samples {config.target_samples}, "
        f"batch {config.batch_size}, critic {config.critic_hidden}"
    )
    print(f"update:      {update_s * 1e3:7.1f} ms (median of {args.repeats})")
    print(f"GEMM floor:  {floor_s * 1e3:7.1f} ms (the update's matrix products alone)")
    print(f"peak memory: {peak_bytes / 2**20:7.1f} MiB allocated by one update")
    print(
        f"update_ms={update_s * 1e3:.1f} gemm_floor_ms={floor_s * 1e3:.1f} "
        f"floor_fraction={floor_s / update_s:.3f}"
    )


if __name__ == "__main__":
    main()
