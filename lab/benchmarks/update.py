"""Time one full update (critic step, target update, policy step) at the paper's sizes.

    python -m lab.benchmarks.update [--task Hopper-v4] [--noise-samples 128] [--repeats 20]
    python -m lab.benchmarks.update --table   # every paper task at 8 and 128 noise samples

A task's dimensions (Hopper-v4: dim S = 11, dim A = 3), PN 100-100, QN 500-500,
minibatch 64, 128 noise samples per state: 8 192 rows through the critic and back per
policy step. --table prints one Markdown row per task and noise setting.
In the same run it times the GEMM floor: every matrix product of one update, at the
update's shapes, each in NumPy with the faster of one BLAS thread or all cores, and no
element-wise work at all. floor_fraction = floor / update is the share of the GEMM floor's speed
that the real update reaches (1.0 would mean element-wise work and overhead are free).
The last line is machine-readable.
"""

from __future__ import annotations

import argparse
import os
import resource
import time
import tracemalloc

import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits

import harness
import offpac_il

# (dim S, dim A) of the paper's tasks, as gymnasium's -v4 environments have them.
TASK_DIMS = {
    "Hopper-v4": (11, 3),
    "HalfCheetah-v4": (17, 6),
    "Walker2d-v4": (17, 6),
    "Ant-v4": (27, 8),
    "Humanoid-v4": (376, 17),
}
STATE_DIM, ACTION_DIM = TASK_DIMS["Hopper-v4"]  # set by main for --task


def make_problem(config: offpac_il.Config, rng: np.random.Generator):
    policy = offpac_il.BoundedPolicy.create(STATE_DIM, STATE_DIM, ACTION_DIM, config, rng)
    learner = offpac_il.Learner.create(policy, STATE_DIM, ACTION_DIM, config, rng)
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
    """(rows, inner, cols) of every matrix product one update needs.

    The products `offpac_il.update` performs, no more: a state shared by the noise
    samples of its rows enters the first layer once (shape (states, dim s, hidden));
    the policy step needs the critic's gradient for the actions only and no input
    gradient of the policy; the critic step needs no input gradient at all.
    """
    b, z, k = config.batch_size, config.noise_samples, config.target_samples
    ph, ch = config.policy_hidden, config.critic_hidden
    s, a = STATE_DIM, ACTION_DIM

    def forward(rows, states, inputs, hidden, out):
        sizes = [*hidden, out]
        first = [(states, s, hidden[0]), (rows, inputs, hidden[0])]
        return first + [(rows, i, o) for i, o in zip(sizes[:-1], sizes[1:], strict=True)]

    def weight_grads(rows, states, inputs, hidden, out):
        sizes = [*hidden, out]
        first = [(s, states, hidden[0]), (inputs, rows, hidden[0])]
        return first + [(i, rows, o) for i, o in zip(sizes[:-1], sizes[1:], strict=True)]

    def hidden_grads(rows, hidden):
        """d_h @ W.T between hidden layers. (The critic's 1-wide output layer backward is
        a broadcast, not a product; the policy's is listed where it is used.)"""
        return [(rows, o, i) for i, o in zip(hidden[:-1], hidden[1:], strict=True)]

    shapes = []
    # Critic step: targets (policy and target critic forward, 2b next states x k noise),
    # then the critic's forward and parameter gradients on 2b triplets.
    shapes += forward(2 * b * k, 2 * b, s, ph, a) + forward(2 * b * k, 2 * b, a, ch, 1)
    shapes += forward(2 * b, 2 * b, a, ch, 1) + weight_grads(2 * b, 2 * b, a, ch, 1)
    shapes += hidden_grads(2 * b, ch)
    # Policy step on b*z rows: policy forward, critic forward, critic backward to the
    # actions, policy backward with parameter gradients.
    shapes += forward(b * z, b, s, ph, a) + forward(b * z, b, a, ch, 1)
    shapes += hidden_grads(b * z, ch) + [(b * z, ch[0], a)]
    shapes += [(b * z, a, ph[-1])] + hidden_grads(b * z, ph) + weight_grads(b * z, b, s, ph, a)
    return shapes


def time_gemm_floor(shapes, rng, repeats: int, thread_counts=None) -> float:
    """Sum over the shapes of each product's median time, with the BLAS thread count
    of `thread_counts` (default: one, or all cores) that is faster for that shape: the
    best NumPy can do."""
    total = 0.0
    for m, k, n in shapes:
        a = rng.standard_normal((m, k), dtype=np.float32)  # (m, k) @ (k, n)
        b = rng.standard_normal((k, n), dtype=np.float32)
        candidates = []
        for threads in sorted(set(thread_counts or {1, os.cpu_count() or 1})):
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


def measure(config: offpac_il.Config, repeats: int) -> dict:
    """One update's median time, its page faults and peak memory, and its GEMM floor."""
    rng = np.random.default_rng(0)
    learner, replay, expert_buffer = make_problem(config, rng)

    def one_update():
        offpac_il.update(learner, expert_buffer, replay, config, 0, rng)

    # As in training: BLAS on one thread, parallelism from harness.map_row_chunks.
    with threadpool_limits(limits=1, user_api="blas"):
        update_s = median_seconds(one_update, repeats)
        faults_before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        one_update()
        page_faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults_before
        tracemalloc.start()
        one_update()
        peak_bytes = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    floor_s = time_gemm_floor(gemm_shapes(config), rng, repeats)
    return {"update_s": update_s, "floor_s": floor_s, "faults": page_faults, "peak": peak_bytes}


def main() -> None:
    global STATE_DIM, ACTION_DIM
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", choices=sorted(TASK_DIMS), default="Hopper-v4")
    parser.add_argument("--table", action="store_true", help="every task, 8 and 128 samples")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--noise-samples", type=int, default=128)
    parser.add_argument("--target-samples", type=int, default=offpac_il.Config.target_samples)
    args = parser.parse_args()
    harness.reuse_freed_memory()  # as a training run does
    blas = [
        f"{i['internal_api']} {i.get('version')} ({i['num_threads']} threads)"
        for i in threadpool_info()
        if i["user_api"] == "blas"
    ]
    print(f"cores: {os.cpu_count()}  numpy {np.__version__}  BLAS: {', '.join(blas)}")
    if args.table:
        print("| task | dim S | dim A | noise samples | update (ms) | GEMM floor (ms) | fraction |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for task, (STATE_DIM, ACTION_DIM) in TASK_DIMS.items():
            for samples in (8, 128):
                config = offpac_il.Config(noise_samples=samples, target_samples=args.target_samples)
                m = measure(config, args.repeats)
                print(
                    f"| {task} | {STATE_DIM} | {ACTION_DIM} | {samples} | {m['update_s'] * 1e3:.1f}"
                    f" | {m['floor_s'] * 1e3:.1f} | {m['floor_s'] / m['update_s']:.2f} |",
                    flush=True,
                )
        return
    STATE_DIM, ACTION_DIM = TASK_DIMS[args.task]
    config = offpac_il.Config(noise_samples=args.noise_samples, target_samples=args.target_samples)
    m = measure(config, args.repeats)
    update_s, floor_s = m["update_s"], m["floor_s"]
    print(
        f"{args.task} (dim S {STATE_DIM}, dim A {ACTION_DIM}): noise samples "
        f"{config.noise_samples}, target samples {config.target_samples}, "
        f"batch {config.batch_size}, critic {config.critic_hidden}"
    )
    print(f"update:      {update_s * 1e3:7.1f} ms (median of {args.repeats})")
    print(f"GEMM floor:  {floor_s * 1e3:7.1f} ms (the update's matrix products alone)")
    print(f"peak memory: {m['peak'] / 2**20:7.1f} MiB allocated by one update")
    print(f"page faults: {m['faults']:7d} in one update (see harness.reuse_freed_memory)")
    print(
        f"update_ms={update_s * 1e3:.1f} gemm_floor_ms={floor_s * 1e3:.1f} "
        f"floor_fraction={floor_s / update_s:.3f}"
    )


if __name__ == "__main__":
    main()
