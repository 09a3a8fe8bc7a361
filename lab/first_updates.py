"""The first updates of a run, measured after each episode: where Ant's failure sets in.

Runs Algorithm 1 (offpac_il.update, one update per interaction) for a few thousand
interactions and prints, after each episode once `--every` interactions have passed:

- err: the policy's squared action error at the demonstrated states (per component);
- sat B / sat E: the share of pi(s, z)'s components at the tanh bound (|a| > 0.99) at
  replay states and at the demonstrated states;
- q E / q B: the critic on the last update's expert and replay rows;
- prefers a_E: the share of demonstrated states where q(s_E, a_E) > q(s_E, pi(s_E, z)).

Nothing is written to disk. `--start` changes how the run begins, to test what sets the
failure off (none of these is a setting of offpac_il.py):

- defaults: offpac_il.py's defaults;
- bias-corrected: both RMSProp optimisers divide the mean square by 1 - decay^t, as Adam
  does, so the first steps are lr-sized instead of up to 14 lr;
- bc-start: PN is first fitted to the demonstrations by squared error (`--bc-steps`
  RMSProp steps, rate 1e-3, 64 triplets each), then the run starts from it;
- std-floor: the state standardisation's std is raised to at least 0.3 x its median.

    python -m lab.first_updates --env Ant-v4 --interactions 3000 [--start bc-start]
        [--sampling dense] [--batch-size 256]
"""

from __future__ import annotations

import dataclasses
import sys

import numpy as np

import expert
import harness
import nets
import offpac_il

STARTS = ("defaults", "bias-corrected", "bc-start", "std-floor")


@dataclasses.dataclass
class BiasCorrectedRMSProp(nets.RMSProp):
    """RMSProp whose mean square is divided by c = 1 - decay^t (t: steps taken).

    lr g / (sqrt(ms / c) + eps) = (lr sqrt c) g / (sqrt(ms) + eps sqrt c): nets.RMSProp's
    own step with the rate and epsilon scaled by sqrt c, on the same mean square.
    """

    steps: int = 0

    def step(self, params, grads, lr):
        self.steps += 1
        root_c = np.sqrt(1.0 - self.decay**self.steps)
        plain = nets.RMSProp(self.decay, self.eps * root_c, self.mean_square)
        plain.step(params, grads, lr * root_c)


def cloning_loss_and_grads(policy, states, noise, actions):
    """Behavioural cloning's loss mean ||tanh(PN([s_E, z])) - a_E||^2 over components, and
    its gradient w.r.t. PN's parameters. states, noise: (B, dim s), (B, dim z); actions:
    (B, dim A). Returns (loss, grads)."""
    predicted, cache = policy.forward(states, noise)  # (B, dim A)
    error = predicted - actions
    d_predicted = 2.0 * error / error.size  # d mean(error^2) / d predicted
    return float((error**2).mean()), policy.backward(d_predicted, cache)


def fit_to_demonstrations(policy, expert_buffer, steps: int, rng) -> None:
    """Behavioural cloning of PN on the demonstrations: RMSProp at rate 1e-3 on
    `cloning_loss_and_grads`, 64 triplets and one z ~ N(0, I) each per step."""
    optimizer = nets.RMSProp()
    for _ in range(steps):
        rows = rng.integers(len(expert_buffer.states), size=64)
        noise = rng.standard_normal((64, policy.noise_dim), np.float32)
        states, actions = expert_buffer.states[rows], expert_buffer.actions[rows]
        _, grads = cloning_loss_and_grads(policy, states, noise, actions)
        optimizer.step(policy.net.params, grads, 1e-3)


def measure(learner, expert_buffer, replay, stats, rng) -> dict[str, float]:
    """The printed columns. Beside offpac_il.imitation_diagnostics, which averages q over
    the demonstrated states, this compares q(s_E, a_E) and q(s_E, pi) state by state."""

    def sampled_actions(states):
        return learner.policy.act(
            states, rng.standard_normal((len(states), learner.policy.noise_dim), np.float32)
        )

    expert_states = expert_buffer.states
    actions = sampled_actions(expert_states)
    q_at_expert, _ = learner.critic.forward((expert_states, expert_buffer.actions))
    q_at_policy, _ = learner.critic.forward((expert_states, actions))
    replay_actions = sampled_actions(replay.sample(rng, 256).states)
    return {
        "err": float(((actions - expert_buffer.actions) ** 2).mean()),
        "sat B": float((np.abs(replay_actions) > 0.99).mean()),
        "sat E": float((np.abs(actions) > 0.99).mean()),
        "q E": stats["q_expert"],
        "q B": stats["q_replay"],
        "prefers a_E": float((q_at_expert > q_at_policy).mean()),
    }


def first_updates(
    config: offpac_il.Config, interactions: int, start: str, every: int = 1000, bc_steps: int = 3000
) -> list[dict[str, float]]:
    """Runs the first `interactions` of Algorithm 1 with the given start; returns the rows."""
    env = expert.make_env(config.env)
    rng = np.random.default_rng(config.seed)
    spaces, expert_buffer, learner, replay, demos = offpac_il.prepare(config, env, rng)
    if start == "std-floor":
        floor = 0.3 * np.median(spaces.state_std)
        spaces = dataclasses.replace(spaces, state_std=np.maximum(spaces.state_std, floor))
        expert_buffer = offpac_il.expert_buffer_from(demos, spaces)
    if start == "bias-corrected":
        decay, eps = config.rmsprop_decay, config.rmsprop_eps
        learner.policy_optimizer = BiasCorrectedRMSProp(decay, eps)
        learner.critic_optimizer = BiasCorrectedRMSProp(decay, eps)
    if start == "bc-start":
        fit_to_demonstrations(learner.policy, expert_buffer, bc_steps, np.random.default_rng(7))
        if learner.average_policy is not None:
            learner.average_policy = learner.policy.copy()
    measure_rng = np.random.default_rng([config.seed, 3])
    rows, done, next_row = [], 0, 0
    while done < interactions:
        episode_return, length = offpac_il.run_episode(
            env, learner, spaces, rng, int(rng.integers(2**31)), replay, config.exploration_noise
        )
        for _ in range(length):
            stats = offpac_il.update(learner, expert_buffer, replay, config, done, rng)
        done += length
        if done >= next_row or done >= interactions:  # and always the last
            row = {"interactions": done, "return": episode_return}
            rows.append(row | measure(learner, expert_buffer, replay, stats, measure_rng))
            print(
                "  ".join(
                    f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}"
                    for k, v in rows[-1].items()
                ),
                flush=True,
            )
            next_row += every
    return rows


def main(argv=None) -> int:
    """A bad flag or setting ends in one line on stderr and exit status 2."""
    parser = harness.CommandLineParser(
        prog="python -m lab.first_updates", description=__doc__.splitlines()[0]
    )
    count = harness.positive_int
    parser.add_argument("--env", default="Ant-v4")
    parser.add_argument("--seed", type=harness.seed_number, default=0)
    parser.add_argument("--trajectories", type=count, default=4)
    parser.add_argument("--interactions", type=count, default=3000)
    parser.add_argument("--every", type=count, default=1000)
    parser.add_argument("--start", choices=STARTS, default="defaults")
    parser.add_argument("--bc-steps", type=count, default=3000)
    parser.add_argument("--noise-samples", type=count, default=8)
    parser.add_argument("--policy-lr", type=float, default=offpac_il.Config.policy_lr)
    parser.add_argument("--policy-expert-states", type=float, default=0.5)
    parser.add_argument("--exploration-noise", type=float, default=0.0)
    parser.add_argument("--gamma", type=float, default=offpac_il.Config.gamma)
    parser.add_argument("--sampling", default=offpac_il.Config.sampling)
    parser.add_argument("--batch-size", type=count, default=offpac_il.Config.batch_size)
    args = parser.parse_args(argv)
    config = offpac_il.Config(
        env=args.env,
        seed=args.seed,
        trajectories=args.trajectories,
        noise_samples=args.noise_samples,
        policy_lr=args.policy_lr,
        policy_expert_states=args.policy_expert_states,
        exploration_noise=args.exploration_noise,
        gamma=args.gamma,
        sampling=args.sampling,
        batch_size=args.batch_size,
    )

    def body() -> None:
        offpac_il.check_config(config)
        first_updates(config, args.interactions, args.start, args.every, args.bc_steps)

    return harness.run_cli(body, at_once=True)


if __name__ == "__main__":
    sys.exit(main())
