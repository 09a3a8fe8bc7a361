"""Off-policy actor-critic imitation learning, in NumPy.

Sasaki, Yohira & Kawaguchi, "Sample Efficient Imitation Learning for Continuous
Control", ICLR 2019 (https://openreview.net/forum?id=BkN5UoAqF7). Equation numbers
below are the paper's.

Algorithm 1 in four lines:
  1. roll out one episode with a = pi_theta(s, z) = tanh(PN(s, z)), z ~ N(0, I) (Sec. 3.2),
     storing each (s, a, s') in a FIFO replay buffer B_beta;          -> run_episode
  2. then, as many times as the episode had steps:                     -> update
  3.   move the critic q_nu (Q = log q, Eq. 10) by objective (18): match q(s, a) to
       E_z q_nu'(s', pi(s', z))^gamma on expert triplets, and to half of it on replay
       triplets, in Jensen-Shannon divergence; soft-update nu'.        -> critic_step
  4.   move the policy by gradient (6): the gradient of log q(s, pi(s, z)) through the
       critic's action Jacobian, over 128 noise samples per state.    -> policy_step
No reward is ever learned: q itself encodes "expert-like now and later" (Sec. 3.1.3).

Run `python offpac_il.py --env Hopper-v4`; `--help` lists every setting. The paper's
ablations (Figure 4) live in lab/ablations.py and hook in at the `Variant` below.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

import expert
import harness
import nets


@dataclass
class RunConfig:
    """What every imitation run sets (the learner's and lab/baselines.py's): the task, the
    demonstrations, the evaluation and the run directory. Each field is a --flag."""

    env: str = "Hopper-v4"
    """Gymnasium environment id (Box observations, bounded Box actions)."""
    seed: int = 0
    """Seed of the run's single numpy Generator and of the environment."""
    demos: str = ""
    """Demonstrations: a .npz file, or minari:<dataset id> (in the local cache); empty: the
    shipped expert's default ones. --trajectories, --sampling, --demo-seed apply to both."""
    trajectories: int = 4
    """Expert trajectories in the default demonstrations (Sec. 5.1)."""
    sampling: str = "sparse"
    """Default demonstrations: sparse (100 random triplets per trajectory) or dense."""
    demo_seed: int = 0
    """Seed of the default demonstrations."""
    standardize: bool = True
    """Standardise states by the demonstrations' mean and std (+1e-3), as DAC/ValueDICE."""
    eval_episodes: int = 5
    """Episodes per evaluation (stochastic policy, true reward)."""
    run_dir: str = ""
    """Run directory; empty: a new one under runs/ named by the task and seed."""
    checkpoint_every: float = 120.0
    """Seconds between checkpoints (taken at episode ends); 0: after every episode."""
    log_every: float = 10.0
    """Seconds between training progress lines (evaluations always print)."""

    def __post_init__(self):
        # Stored absolute: a resume from another working directory reads the same file.
        if self.demos and not self.demos.startswith(expert.MINARI):
            self.demos = os.path.abspath(self.demos)


@dataclass
class Config(RunConfig):
    """The learner's hyperparameters: Appendix B unless said otherwise."""

    program: ClassVar[str] = "python offpac_il.py"  # the command that resumes its runs
    # Settings measured not to help, which left the code: name -> (the value that meant
    # "off", the last commit that had it). A run made with one on cannot be resumed here.
    removed_settings: ClassVar[dict[str, tuple[float | str, str]]] = {
        "critic_reg": (0.0, ""),
        "critic_grad_penalty": (0.0, ""),
        "critic_input_noise": (0.0, ""),
        "expert_state_negatives": (0.0, "f379e83"),
        "state_clip": (0.0, "44dc556"),
        "policy_entropy": (0.0, "519758d"),
        "expert_action_anchor": (0.0, "08a20b2"),
        "critic_interpolate_penalty": (0.0, "157447b"),
        "critic_action_contrast": (0.0, "d59b57f"),
        "critic_loss": ("js", "f454a88"),
        "critic_spectral_bound": (0.0, "4542e27"),
    }

    total_steps: int = 300_000
    """Interaction budget; the learning rates decrease linearly to 0 over it."""
    eval_every: int = 5_000
    """Interactions between evaluations."""
    policy_hidden: tuple[int, ...] = (100, 100)
    """PN's hidden layer sizes."""
    critic_hidden: tuple[int, ...] = (500, 500)
    """QN's hidden layer sizes."""
    # Deviation: 0.23 x and 0.3 x Appendix B's rates (README, Deviations); at the paper's
    # rates Hopper-v4 reaches the expert and falls away again.
    policy_lr: float = 2.3e-5
    """PN's initial RMSProp learning rate (paper: 1e-4)."""
    critic_lr: float = 3e-4
    """QN's initial RMSProp learning rate (paper: 1e-3)."""
    rmsprop_decay: float = 0.995
    """RMSProp decay of the mean square."""
    rmsprop_eps: float = 1e-8
    """RMSProp epsilon."""
    tau: float = 1e-3
    """Target critic tracking rate: nu' <- tau nu + (1 - tau) nu'."""
    batch_size: int = 64
    """Triplets per minibatch, from each of the expert and replay buffers."""
    replay_size: int = 15_000
    """Capacity of the FIFO replay buffer B_beta."""
    gamma: float = 0.85
    """Discount factor."""
    noise_samples: int = 128
    """Noise vectors z per state in the policy gradient (6)."""
    # The paper is silent; 8 cost about a tenth of an update (lab/benchmarks/update.py).
    target_samples: int = 8
    """Noise vectors z per next state in the critic's target E_z q'(s', pi(s', z))^gamma."""
    # The paper is silent (README, Deviations, has the measurements): zero continuation
    # is the only treatment that makes a fall worse than staying up. Standardisation
    # (RunConfig): without it Hopper reached 0.91 at 41 k and fell to 0.03 by 75 k.
    termination: str = "zero"
    """At a terminal s': bootstrap (literal Alg. 1), absorbing (DAC), or zero (q'^gamma=0)."""
    policy_expert_states: float = 0.5
    """Fraction of the policy step's states drawn from the demonstrations (paper: 0)."""
    exploration_noise: float = 0.0
    """Std of Gaussian noise on executed training actions (paper: 0; HalfCheetah, Walker2d: 0.3)."""
    policy_average: float = 1e-4
    """Rate of the Polyak average of PN's weights, the policy handed over (0: none)."""


# Appendix B's values of the settings whose defaults deviate from it (--paper).
PAPER_SETTINGS = dict(policy_lr=1e-4, critic_lr=1e-3, policy_expert_states=0.0, policy_average=0.0)


# === The critic step: objective (18) ===


def critic_targets(
    learner: Learner, batch: Triplets, n_expert: int, config: Config, rng: np.random.Generator
) -> tuple[np.ndarray, dict]:
    """t, the Bernoulli parameter that q_nu(s, a) is matched to, per row (Eq. 17-18):

        t = E_z[q_nu'(s', pi(s', z))^gamma],  halved on replay rows,

    the "/2" being objective (8)'s optimal reward written in as constants: 1 on expert
    pairs, 1/2 on the learner's. The expectation is a mean over `target_samples` noise
    vectors per next state, through the target critic q_nu' (Appendix B). At a terminal
    s' under termination="zero" the continuation q'^gamma is 0; "bootstrap" treats it
    like any other s'; under "absorbing" s' is the absorbing state, learned like any
    other. No gradient flows through t. Returns (t (rows,), stats: none for Ours).
    """
    k = learner.policy.samples_per_state(config.target_samples)
    noise = rng.standard_normal((len(batch.next_states) * k, learner.policy.noise_dim), np.float32)

    def chunk_targets(rows: slice) -> np.ndarray:
        next_states = batch.next_states[rows]  # (C, dim s), each shared by k noise rows
        z = noise[rows.start * k : rows.stop * k]  # (C*k, dim z)
        next_actions = learner.policy.act(next_states, z)  # (C*k, dim A)
        _, cache = learner.target_critic.forward((next_states, next_actions))
        log_q = nets.log_sigmoid(cache.logits).reshape(-1, k)  # (C, k): log q'(s', a'_k)
        return np.exp(config.gamma * log_q).mean(axis=1)  # (C,): mean_k q'^gamma

    t = np.concatenate(harness.map_row_chunks(chunk_targets, len(noise) // k, k))
    if config.termination == "zero":
        t[batch.terminal] = 0.0
    t[n_expert:] *= 0.5  # the "/2" of Eq. (17)-(18): replay pairs earn r = 1/2
    return t, {}


def critic_loss_and_grads(critic: nets.MLP, batch: Triplets, t: np.ndarray, n_expert: int):
    """Objective (18) and its gradient w.r.t. every critic parameter, for fixed t.

    D_JS(P_nu(.|s, a) || Bern(t)) with P_nu(pi_E|s, a) = q_nu(s, a) (Eq. 12), averaged
    over the expert rows and over the replay rows, the two averages added. With t frozen,
    dD_JS/dx = 1/2 p(1-p)(logit p - logit m), m = (p + t)/2, in the critic's logit x
    (nets.js_divergence_grad), is backpropagated through QN. batch: n_expert expert rows,
    then as many replay rows; t: (rows, 1). Returns (loss, grads, critic cache).
    """
    _, cache = critic.forward((batch.states, batch.actions))
    x = cache.logits  # (2n, 1): p = q_nu(s, a) = sigmoid(x), Eq. (10)
    # Eq. (18): both halves hold n rows, so one sum / n is the two means added.
    loss = nets.js_divergence(x, t).sum() / n_expert
    d_x = nets.js_divergence_grad(x, t) / n_expert  # Eq. (18): 1/2 p(1-p)(logit p - logit m)
    _, grads = critic.backward(d_x, cache, through_head=False, input_grads=False)
    return float(loss), grads, cache


def concatenated(expert_batch: Triplets, replay_batch: Triplets) -> Triplets:
    fields = (f.name for f in dataclasses.fields(Triplets))
    return Triplets(
        *(np.concatenate([getattr(expert_batch, f), getattr(replay_batch, f)]) for f in fields)
    )


def critic_step(
    learner: Learner,
    expert_batch: Triplets,
    replay_batch: Triplets,
    config: Config,
    lr: float,
    rng: np.random.Generator,
    targets: Callable = critic_targets,
) -> dict[str, float]:
    """Alg. 1, lines 11-12: one RMSProp step on objective (18), then the target update
    nu' <- tau nu + (1 - tau) nu' (Appendix B). Ours+IRL passes its own `targets`."""
    n = len(expert_batch.states)
    batch = concatenated(expert_batch, replay_batch)  # (2n, ...)
    t, stats = targets(learner, batch, n, config, rng)
    loss, grads, cache = critic_loss_and_grads(learner.critic, batch, t[:, None], n)
    learner.critic_optimizer.step(learner.critic.params, grads, lr)
    nets.soft_update(learner.target_critic, learner.critic, config.tau)
    q = cache.output[:, 0]  # q_nu(s, a): the expert rows, then the replay rows
    q_expert, q_replay = float(q[:n].mean()), float(q[n:].mean())
    return {"critic_loss": loss, "q_expert": q_expert, "q_replay": q_replay} | stats


# === The policy step: gradient (6) ===


def policy_gradient(learner: Learner, states: np.ndarray, noise: np.ndarray, total_rows: int):
    """Gradient (6) of -mean log q(s, pi(s, z)) w.r.t. PN's parameters, on one chunk.

    states: (B, dim s); noise: (B*Z, dim z), Z noise vectors per state; total_rows: the
    rows of the whole step, over which (6) averages. Returns sums over the chunk's rows,
    so chunks add up: (grads, loss, sum of q, (saturated components, all components)).
    """
    actions, policy_cache = learner.policy.forward(states, noise)  # (B*Z, dim A)
    _, critic_cache = learner.critic.forward((states, actions))  # logits x (B*Z, 1)
    # Q = log q (Eq. 10): d(-log q)/dx = -(1 - q), averaged over all rows.
    d_x = -nets.log_sigmoid_grad(critic_cache.logits) / total_rows
    # Back through the fixed critic to its action input (its Jacobian, no weight grads).
    (_, d_actions), _ = learner.critic.backward(
        d_x, critic_cache, through_head=False, param_grads=False, input_grads=(False, True)
    )
    grads = learner.policy.backward(d_actions, policy_cache)  # Eq. (6): through tanh and PN
    log_q = nets.log_sigmoid(critic_cache.logits)
    saturated = (np.count_nonzero(np.abs(actions) > 0.99), actions.size)
    return grads, -float(log_q.sum()) / total_rows, float(critic_cache.output.sum()), saturated


def policy_loss_and_grads(learner: Learner, states: np.ndarray, noise: np.ndarray):
    """-E_{s, z}[log q(s, pi(s, z))] and gradient (6), over row chunks on both cores.
    states: (B, dim s); noise: (B*Z, dim z). Returns (loss, grads, stats)."""
    z_per_state = len(noise) // len(states)

    def chunk(rows: slice):
        z = noise[rows.start * z_per_state : rows.stop * z_per_state]
        return policy_gradient(learner, states[rows], z, len(noise))

    parts = harness.map_row_chunks(chunk, len(states), z_per_state)
    grads = {
        name: sum(p[0][name] for p in parts[1:]) + parts[0][0][name] for name in parts[0][0]
    }  # the chunks' partial sums, in a fixed order
    saturation = sum(p[3][0] for p in parts) / sum(p[3][1] for p in parts)
    stats = {"q_policy": sum(p[2] for p in parts) / len(noise), "saturation": saturation}
    return sum(p[1] for p in parts), grads, stats


def policy_states(
    expert_buffer: Triplets, replay: ReplayBuffer, config: Config, rng: np.random.Generator
) -> np.ndarray:
    """The states of one policy step (batch_size, dim s): a fresh replay batch (line 13),
    the first `policy_expert_states` of it replaced by demonstration states (a
    deviation: without them Hopper-v4 reaches the expert and falls away)."""
    states = replay.sample(rng, config.batch_size).states
    n_expert = round(config.policy_expert_states * config.batch_size)
    if n_expert:
        states[:n_expert] = expert_buffer.sample(rng, n_expert).states
    return states


def policy_step(
    learner: Learner, states: np.ndarray, config: Config, lr: float, rng: np.random.Generator
) -> dict[str, float]:
    """Alg. 1, line 14: one RMSProp step on PN by gradient (6), `noise_samples` z per state."""
    rows = len(states) * learner.policy.samples_per_state(config.noise_samples)
    noise = rng.standard_normal((rows, learner.policy.noise_dim), np.float32)
    _, grads, stats = policy_loss_and_grads(learner, states, noise)
    learner.policy_optimizer.step(learner.policy.net.params, grads, lr)
    stats["policy_grad_norm"] = math.sqrt(sum(float((g * g).sum()) for g in grads.values()))
    return stats


# === Buffers of (s, a, s') triplets in the networks' units ===


@dataclass
class Triplets:
    states: np.ndarray  # (N, dim s)
    actions: np.ndarray  # (N, dim A), in [-1, 1]
    next_states: np.ndarray  # (N, dim s)
    terminal: np.ndarray  # (N,) bool: s' is terminal (a time limit is not: it bootstraps)

    def take(self, index: np.ndarray) -> Triplets:
        return Triplets(*(getattr(self, f.name)[index] for f in dataclasses.fields(self)))

    def sample(self, rng: np.random.Generator, n: int) -> Triplets:
        return self.take(rng.integers(0, len(self.states), n))


class ReplayBuffer:
    """B_beta: a FIFO of the most recent `capacity` triplets (Sec. 3.3)."""

    def __init__(self, capacity: int, state_dim: int, action_dim: int):
        self.capacity, self.size, self.next_index = capacity, 0, 0
        self.data = Triplets(
            np.zeros((capacity, state_dim), np.float32),
            np.zeros((capacity, action_dim), np.float32),
            np.zeros((capacity, state_dim), np.float32),
            np.zeros(capacity, bool),
        )

    def add(self, state, action, next_state, terminal: bool) -> None:
        i = self.next_index
        self.data.states[i], self.data.actions[i] = state, action
        self.data.next_states[i], self.data.terminal[i] = next_state, terminal
        self.next_index = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, rng: np.random.Generator, n: int) -> Triplets:
        return self.data.take(rng.integers(0, self.size, n))

    def state(self) -> dict[str, np.ndarray]:
        fields = dataclasses.fields(Triplets)
        arrays = {f"replay/{f.name}": getattr(self.data, f.name) for f in fields}
        return arrays | {"replay/size_next": np.array([self.size, self.next_index])}

    def load_state(self, arrays) -> None:
        for f in dataclasses.fields(Triplets):
            getattr(self.data, f.name)[...] = arrays[f"replay/{f.name}"]
        self.size, self.next_index = (int(v) for v in arrays["replay/size_next"])


# === The networks: pi = tanh(PN([s, z])), q_nu = sigmoid(QN([s, a])), target q_nu' ===


@dataclass
class BoundedPolicy:
    """pi_theta(s, z) = tanh(PN([s, z])), z ~ N(0, I) with dim z = dim s (Sec. 3.2).

    `states` (G, dim s) may be shared by the N/G consecutive rows of `noise` (N, dim z)
    (nets.MLP's shared blocks): the policy step's 128 samples per state reuse the state's
    part of PN's first layer. The ablations' policies (Variant) have these same methods.
    """

    net: nets.MLP
    noise_dim: int

    @classmethod
    def create(cls, state_dim, noise_dim, action_dim, config: Config, rng, dtype=np.float32):
        sizes = [state_dim + noise_dim, *config.policy_hidden, action_dim]
        return cls(nets.MLP.create(sizes, "tanh", rng, dtype), noise_dim)

    def samples_per_state(self, samples: int) -> int:
        return samples

    def forward(self, states: np.ndarray, noise: np.ndarray):
        return self.net.forward((states, noise))  # (N, dim A) actions, cache

    def backward(self, d_actions: np.ndarray, cache) -> dict[str, np.ndarray]:
        """PN's parameter gradients from dL/da, through tanh; PN's input needs none."""
        return self.net.backward(d_actions, cache, input_grads=False)[1]

    def act(self, states: np.ndarray, noise: np.ndarray) -> np.ndarray:
        return self.forward(states, noise)[0]

    def state(self, prefix: str = "policy") -> dict[str, np.ndarray]:
        return self.net.state(prefix)

    def load_state(self, arrays, prefix: str = "policy") -> None:
        self.net.load_state(arrays, prefix)

    def copy(self) -> BoundedPolicy:
        return dataclasses.replace(self, net=self.net.copy())


@dataclass
class Learner:
    """The policy, the critic q_nu, its target q_nu' and their RMSProp optimisers.

    average_policy (a deviation, --policy-average): a Polyak average of PN's weights.
    It never acts in training nor enters a gradient; it is evaluated beside PN and is the
    policy a run hands over (policy_average.npz).
    """

    policy: BoundedPolicy
    critic: nets.MLP
    target_critic: nets.MLP
    policy_optimizer: nets.RMSProp
    critic_optimizer: nets.RMSProp
    average_policy: BoundedPolicy | None = None
    extra_state: dict = field(default_factory=dict)  # an ablation's networks, checkpointed

    @classmethod
    def create(cls, policy, state_dim, action_dim, config: Config, rng, dtype=np.float32):
        """QN is drawn from `rng` after PN (made by the caller), so every variant that
        keeps PN's shape starts from Ours' networks at one seed."""
        sizes = [state_dim + action_dim, *config.critic_hidden, 1]
        critic = nets.MLP.create(sizes, "sigmoid", rng, dtype)
        optimizers = [nets.RMSProp(config.rmsprop_decay, config.rmsprop_eps) for _ in range(2)]
        average_policy = policy.copy() if config.policy_average > 0 else None
        return cls(policy, critic, critic.copy(), *optimizers, average_policy)

    def averaged(self) -> Learner:
        """This learner acting with the averaged PN."""
        return dataclasses.replace(self, policy=self.average_policy)

    def parts(self) -> dict:
        """Everything a checkpoint holds, by name (each part has state/load_state)."""
        parts = {"policy": self.policy, "critic": self.critic, "target_critic": self.target_critic}
        parts |= {"policy_rmsprop": self.policy_optimizer, "critic_rmsprop": self.critic_optimizer}
        parts |= self.extra_state
        return parts | ({"average_policy": self.average_policy} if self.average_policy else {})

    def state(self) -> dict[str, np.ndarray]:
        return {k: v for name, part in self.parts().items() for k, v in part.state(name).items()}

    def load_state(self, arrays) -> None:
        for name, part in self.parts().items():
            part.load_state(arrays, name)


# === Where the paper's ablations hook in (lab/ablations.py) ===


@dataclass(frozen=True)
class Variant:
    """Where an ablation changes Algorithm 1 (lab/ablations.py); the defaults are Ours.

    make_policy: the policy object (BoundedPolicy's methods: Ours+GP, Ours+DP);
    make_extras(learner, ...): what is added to the learner after QN (Ours+IRL's reward
    network, Ours+DP's z_0); critic_step: Ours+IRL's reward step and objective (15);
    after_updates(replay): after an episode's updates (Ours+OnP empties the buffer);
    diagnostics(learner, states) and progress_fields: the variant's own columns.
    """

    make_policy: Callable = BoundedPolicy.create
    make_extras: Callable = lambda learner, state_dim, action_dim, config, rng: None
    critic_step: Callable = critic_step
    after_updates: Callable = lambda replay: None
    diagnostics: Callable = lambda learner, states: {}
    progress_fields: tuple[str, ...] = ()


OURS = Variant()


# === One update (Alg. 1, lines 10-15) ===


def update(
    learner: Learner,
    expert_buffer: Triplets,
    replay: ReplayBuffer,
    config: Config,
    interactions: int,
    rng: np.random.Generator,
    variant: Variant = OURS,
) -> dict[str, float]:
    """Alg. 1, lines 11-14: a critic step, the target update and a policy step, with the
    learning rates decreased linearly to 0 over the budget (Appendix B)."""
    critic_lr = nets.linear_decay(config.critic_lr, interactions, config.total_steps)
    policy_lr = nets.linear_decay(config.policy_lr, interactions, config.total_steps)
    expert_batch = expert_buffer.sample(rng, config.batch_size)
    replay_batch = replay.sample(rng, config.batch_size)
    stats = variant.critic_step(learner, expert_batch, replay_batch, config, critic_lr, rng)
    states = policy_states(expert_buffer, replay, config, rng)
    stats.update(policy_step(learner, states, config, policy_lr, rng))
    if learner.average_policy is not None:
        # theta_avg <- rate theta + (1 - rate) theta_avg: rides out PN's short relapses.
        nets.soft_update(learner.average_policy.net, learner.policy.net, config.policy_average)
    return stats


# === Acting: the spaces, one episode (Alg. 1, lines 4-9) and evaluation ===


@dataclass
class Spaces:
    """Maps between the environment's units and the networks' units: actions in
    [-1, 1]^dim A, standardised states, and DAC's absorbing-state indicator."""

    low: np.ndarray
    high: np.ndarray
    state_mean: np.ndarray
    state_std: np.ndarray
    absorbing: bool

    def to_env_action(self, action: np.ndarray) -> np.ndarray:
        return expert.tanh_to_bounds(action, self.low, self.high)

    def from_env_action(self, env_action: np.ndarray) -> np.ndarray:
        """[low, high] -> [-1, 1], clipped at the bounds."""
        scaled = 2.0 * (env_action - self.low) / (self.high - self.low) - 1.0
        return np.clip(scaled, -1.0, 1.0).astype(np.float32)

    def state(self, observation: np.ndarray) -> np.ndarray:
        """Network state: standardised observation, plus a 0 indicator when absorbing."""
        s = ((observation - self.state_mean) / self.state_std).astype(np.float32)
        if self.absorbing:
            s = np.concatenate([s, np.zeros((*s.shape[:-1], 1), np.float32)], axis=-1)
        return s

    def absorbing_state(self) -> np.ndarray:
        """DAC's absorbing state: zeros with the indicator set."""
        s = np.zeros(len(self.state_mean) + 1, np.float32)
        s[-1] = 1.0
        return s


def make_spaces(env, demos: expert.Demos, config: Config) -> Spaces:
    obs_dim = env.observation_space.shape[0]
    if config.standardize:
        mean, std = demos.observations.mean(axis=0), demos.observations.std(axis=0) + 1e-3
        if not (np.isfinite(mean).all() and np.isfinite(std).all()):  # every state would be 0
            raise harness.UserError(f"{demos.path}: the states' mean or std is not finite")
    else:
        mean, std = np.zeros(obs_dim, np.float32), np.ones(obs_dim, np.float32)
    return Spaces(
        env.action_space.low.astype(np.float32),
        env.action_space.high.astype(np.float32),
        mean.astype(np.float32),
        std.astype(np.float32),
        absorbing=config.termination == "absorbing",
    )


def expert_buffer_from(demos: expert.Demos, spaces: Spaces) -> Triplets:
    """B_pi_E: every demonstration triplet, in the networks' units."""
    return Triplets(
        spaces.state(demos.observations),
        spaces.from_env_action(demos.actions),
        spaces.state(demos.next_observations),
        demos.terminals.astype(bool),
    )


def run_episode(
    env,
    learner: Learner,
    spaces: Spaces,
    rng: np.random.Generator,
    seed: int,
    replay: ReplayBuffer | None = None,
    exploration_noise: float = 0.0,
) -> tuple[float, int]:
    """One episode with a_t = pi_theta(s_t, z), z ~ N(0, I); stores triplets if `replay`.
    Returns (true return, length). exploration_noise > 0 (a deviation; HalfCheetah, Walker2d):
    a_t + N(0, sigma^2 I), clipped to [-1, 1], is executed and stored. An unbounded action
    (Ours+GP) is clipped only on its way to the environment; the replay stores it as sampled.
    """
    observation, _ = env.reset(seed=seed)
    state = spaces.state(observation)
    episode_return, length, done = 0.0, 0, False
    while not done:
        noise = rng.standard_normal((1, learner.policy.noise_dim), np.float32)
        action = learner.policy.act(state[None], noise)[0]
        if exploration_noise > 0:
            action = action + exploration_noise * rng.standard_normal(action.shape, np.float32)
            action = np.clip(action, -1.0, 1.0)
        executed = spaces.to_env_action(np.clip(action, -1.0, 1.0))
        observation, reward, terminated, truncated, _ = env.step(executed)
        next_state = spaces.state(observation)
        episode_return, length, done = episode_return + reward, length + 1, terminated or truncated
        if replay is not None:
            if terminated and spaces.absorbing:  # DAC: s_T -> absorbing -> absorbing
                absorbing = spaces.absorbing_state()
                replay.add(state, action, absorbing, False)
                replay.add(absorbing, np.zeros_like(action), absorbing, False)
            else:
                replay.add(state, action, next_state, terminated)
        state = next_state
    return float(episode_return), length


def evaluate(env, learner: Learner, spaces: Spaces, config: Config, round_index: int):
    """True returns of the stochastic policy over `eval_episodes` seeded episodes, and how
    many fell (ended by termination before the time limit). Evaluation has its own
    Generator, so a run evaluated more often learns the same way."""
    rng = np.random.default_rng([config.seed, 1, round_index])
    episodes = []
    for i in range(config.eval_episodes):
        harness.stop_if_requested()  # a long evaluation must not hold a signal for minutes
        episodes.append(run_episode(env, learner, spaces, rng, seed=10**6 + config.seed * 1000 + i))
    time_limit = env.spec.max_episode_steps if env.spec is not None else None
    falls = sum(time_limit is not None and length < time_limit for _, length in episodes)
    return np.array([episode_return for episode_return, _ in episodes]), falls


def imitation_diagnostics(learner: Learner, expert_buffer: Triplets, rng) -> dict[str, float]:
    """How the policy and the critic see the expert's own states: the policy's squared
    action error, q at the expert's and at the policy's actions, the critic's sharpness
    there (1/2 mean ||dx/d[s, a]||^2), and the std of pi(s_E, z) over 8 noise vectors."""
    states, noise_dim = expert_buffer.states, learner.policy.noise_dim
    noise = rng.standard_normal((len(states), noise_dim), np.float32)
    actions = learner.policy.act(states, noise)
    q_expert, _ = learner.critic.forward((states, expert_buffer.actions))
    q_policy, policy_cache = learner.critic.forward((states, actions))
    z_per_state = 8  # each state is shared by 8 consecutive noise rows
    spread_noise = rng.standard_normal((len(states) * z_per_state, noise_dim), np.float32)
    spread = learner.policy.act(states, spread_noise).reshape(len(states), z_per_state, -1)
    return {
        "expert_action_error": float(((actions - expert_buffer.actions) ** 2).mean()),
        "q_at_expert_action": float(q_expert.mean()),
        "q_at_policy_action": float(q_policy.mean()),
        "critic_input_grad": learner.critic.input_gradient_sq_norm(policy_cache),
        "policy_noise_spread": float(spread.std(axis=1).mean()),
    }


# === The run: Algorithm 1's loop, with evaluation, progress.csv and checkpoints ===

PROGRESS_FIELDS = (
    *("interactions", "wall_seconds", "updates", "episodes", "eval_return_mean"),
    *("eval_return_std", "normalized_score", "train_return"),
    # the latest update's measurements, then the evaluation's (imitation_diagnostics)
    *("q_expert", "q_replay", "q_policy", "saturation", "critic_loss", "policy_grad_norm"),
    *("expert_action_error", "q_at_expert_action", "q_at_policy_action", "critic_input_grad"),
    *("policy_noise_spread", "eval_falls"),  # falls: episodes ended before the time limit
)
# The averaged PN's evaluation, on the same episode seeds as PN's (--policy-average).
AVERAGE_FIELDS = ("average_return_mean", "average_score", "average_falls")
# The policy the run hands over (policy_average.npz, else policy_final.npz) and its score.
HANDOVER_FIELDS = ("handover", "handover_score")
SNAPSHOTS = "policies"  # the policy of each evaluation, named by its interactions


def snapshot_path(run_dir: Path, interactions: int) -> Path:
    return Path(run_dir) / SNAPSHOTS / f"{interactions:07d}.npz"


def check_config(config: Config) -> None:
    """Refuse settings that cannot work, with one clear line, before anything is written."""
    harness.check_choices(config, {"termination": TERMINATIONS, "sampling": expert.SAMPLING_MODES})
    at_least_one = ("total_steps", "trajectories", "batch_size", "replay_size", "noise_samples")
    at_least_one += ("target_samples", "eval_every")
    non_negative = ("checkpoint_every", "log_every", "exploration_noise")
    harness.check_numbers(
        config,
        {name: (1, math.inf, "[)") for name in at_least_one}
        | {name: (0, harness.MAX_SEED, "[]") for name in ("seed", "demo_seed")}
        | {"eval_episodes": (1, MAX_EVAL_EPISODES, "[]")}
        | {name: (0, math.inf, "[)") for name in non_negative}
        | {name: (0, math.inf, "()") for name in ("policy_lr", "critic_lr", "rmsprop_eps")}
        | {name: (0, 1, "[]") for name in ("policy_expert_states", "policy_average")}
        | {"rmsprop_decay": (0, 1, "[)"), "tau": (0, 1, "(]"), "gamma": (0, 1, "[)")},
    )
    for name in ("policy_hidden", "critic_hidden"):
        if not getattr(config, name) or min(getattr(config, name)) < 1:
            raise harness.UserError(f"{harness.flag(name)} needs layer sizes of at least 1")


TERMINATIONS = ("bootstrap", "absorbing", "zero")
# 100 000 Hopper episodes are up to 10^8 steps, days of one evaluation; more is a typo.
MAX_EVAL_EPISODES = 100_000


def check_memory(config: Config, env) -> None:
    """Refuse sizes whose arrays cannot fit in memory, before any is made or anything
    written: an estimate of the largest ones from the flags (float32, 4 bytes a number)."""
    dim_s, dim_a = expert.env_dimensions(env)

    def weights(sizes) -> int:
        return sum(n_in * n_out for n_in, n_out in zip(sizes, sizes[1:], strict=False))

    hidden = (*config.policy_hidden, *config.critic_hidden)
    networks = weights([dim_s + dim_a + 1, *config.critic_hidden, 1])
    networks += weights([2 * dim_s, *config.policy_hidden, 2 * dim_a])
    # A row chunk holds at least one state's noise rows; each core runs one chunk.
    chunk_rows = max(harness.CHUNK_ROWS, config.noise_samples, config.target_samples)
    chunk_rows *= os.cpu_count() or 1
    harness.check_fits_in_memory(
        {
            "--replay-size": 4 * config.replay_size * (2 * dim_s + dim_a + 2),
            # the networks, the target critic, the averaged PN and their RMSProp states
            "--critic-hidden and --policy-hidden": 4 * 4 * networks,
            "--batch-size x --noise-samples": 4
            * config.batch_size
            * config.noise_samples
            * (dim_s + dim_a)
            * 2,
            "--batch-size x --target-samples": 4
            * 2
            * config.batch_size
            * config.target_samples
            * (dim_s + dim_a)
            * 2,
            "--noise-samples or --target-samples rows of the hidden layers": 4
            * 3
            * chunk_rows
            * sum(hidden),
        }
    )


def prepare(
    config: Config, env, rng: np.random.Generator, variant: Variant = OURS, resume: bool = False
):
    """The demonstrations (B_pi_E; on a resume, the run's own: expert.run_demos), the
    spaces, a fresh learner and an empty B_beta. The networks are drawn from `rng` in a
    fixed order: PN, QN, then a variant's extras."""
    demos = expert.run_demos(config, resume)
    spaces = make_spaces(env, demos, config)
    expert_buffer = expert_buffer_from(demos, spaces)
    state_dim, action_dim = expert_buffer.states.shape[1], expert_buffer.actions.shape[1]
    env.action_space.seed(config.seed)
    noise_dim = env.observation_space.shape[0]  # dim z = dim s (Appendix B)
    policy = variant.make_policy(state_dim, noise_dim, action_dim, config, rng)
    learner = Learner.create(policy, state_dim, action_dim, config, rng)
    variant.make_extras(learner, state_dim, action_dim, config, rng)
    replay = ReplayBuffer(config.replay_size, state_dim, action_dim)
    return spaces, expert_buffer, learner, replay, demos


def load_checkpoint(run_dir, learner: Learner, replay: ReplayBuffer, rng) -> harness.Progress:
    return harness.load_checkpoint(
        run_dir, rng, lambda a: (learner.load_state(a), replay.load_state(a))
    )


def train(config: Config, resume: bool = False, variant: Variant = OURS) -> harness.Progress:
    """Algorithm 1, with evaluation, logging and checkpoints around it."""
    check_config(config)
    env, eval_env = expert.make_env(config.env), expert.make_env(config.env)
    check_memory(config, env)
    rng = np.random.default_rng(config.seed)  # the run's one Generator, passed explicitly
    spaces, expert_buffer, learner, replay, demos = prepare(config, env, rng, variant, resume)
    print(demos.describe(), flush=True)
    references = expert.references_or_nan(config.env, demos)
    run_dir = harness.open_run_dir(config.run_dir or f"runs/{config.env}-seed{config.seed}", resume)
    progress = load_checkpoint(run_dir, learner, replay, rng) if resume else harness.Progress()
    record = {harness.PROGRAM: config.program, expert.DEMOS_SHA256: demos.sha256}
    harness.write_config(
        run_dir, record | dataclasses.asdict(config)
    )  # a resume may change the budget
    started = f"resumed {run_dir} at {progress.interactions} interactions" if resume else run_dir
    print(f"run directory: {started}", flush=True)
    fields = PROGRESS_FIELDS + variant.progress_fields
    fields += (AVERAGE_FIELDS if learner.average_policy is not None else ()) + HANDOVER_FIELDS
    handover = "policy_average.npz" if learner.average_policy is not None else "policy_final.npz"
    print(f"hands over: {run_dir / handover}", flush=True)
    clock = harness.Clock(progress, config.checkpoint_every, config.log_every)

    def check_finite() -> None:  # before acting, and before a checkpoint overwrites the last
        arrays = learner.state() | {"observations": replay.data.states[: replay.size]}
        harness.check_finite(arrays, f"by {progress.interactions} interactions")

    def checkpoint() -> None:
        check_finite()
        harness.save_checkpoint(run_dir, learner.state() | replay.state(), rng, progress, fields)
        clock.checkpointed()

    def evaluated(policy: Learner):
        """evaluate(policy); a first signal stops it between episodes: the state before
        it is checkpointed, and the resumed run evaluates it again, exactly (its own seeds)."""
        try:
            return evaluate(eval_env, policy, spaces, config, progress.eval_rounds)
        except harness.StopRequested:
            checkpoint()
            raise

    while True:
        stats = progress.last_stats
        if progress.evaluation_due(config.eval_every, config.total_steps):
            check_finite()
            returns, falls = evaluated(learner)
            diagnostics_rng = np.random.default_rng([config.seed, 2, progress.eval_rounds])
            measured = {**stats, **imitation_diagnostics(learner, expert_buffer, diagnostics_rng)}
            measured |= {"eval_falls": falls, **variant.diagnostics(learner, expert_buffer.states)}
            if learner.average_policy is not None:
                average_returns, average_falls = evaluated(learner.averaged())
                average_return = float(average_returns.mean())
                measured |= {
                    "average_return_mean": round(average_return, 2),
                    "average_score": expert.normalized_score(average_return, references),
                    "average_falls": average_falls,
                }
                average_policy = learner.average_policy.state("policy")
                harness.save_arrays(run_dir / "policy_average.npz", average_policy)
            score = expert.normalized_score(float(returns.mean()), references)
            measured |= {
                "handover": handover,
                "handover_score": measured.get("average_score", score),
            }
            clock.tick()
            row = progress.record(returns, score, measured, fields)
            policy = learner.policy.state("policy")
            harness.save_arrays(snapshot_path(run_dir, progress.interactions), policy)
            if returns.mean() > progress.best_eval_return:
                progress.best_eval_return = float(returns.mean())
                harness.save_arrays(run_dir / "policy_best.npz", policy)
            print(
                f"eval  {progress.interactions:>8d} steps  return {returns.mean():8.1f}"
                f" ± {returns.std():6.1f}  score {row['normalized_score']:6.3f}"
                f"  q_E {harness.shown(stats.get('q_expert'), '.3f')}"
                f"  q_B {harness.shown(stats.get('q_replay'), '.3f')}"
                f"  sat {harness.shown(stats.get('saturation'), '.2f')}"
                f"  |pi(s_E)-a_E|^2 {measured['expert_action_error']:.3f}"
                + (f"  averaged PN {row['average_score']:6.3f}" if "average_score" in row else ""),
                flush=True,
            )
            checkpoint()
        if progress.interactions >= config.total_steps:
            break

        # Alg. 1, lines 4-9: one episode with the current policy.
        seed = int(rng.integers(2**31))
        episode_return, length = run_episode(
            env, learner, spaces, rng, seed, replay, config.exploration_noise
        )
        progress.recent_returns.append(episode_return)
        progress.episodes += 1
        # Lines 10-15: as many updates as the episode had steps.
        update_start = time.perf_counter()
        for _ in range(length):
            stats = progress.last_stats = update(
                learner, expert_buffer, replay, config, progress.interactions, rng, variant
            )
            progress.updates += 1
        variant.after_updates(replay)
        update_seconds = time.perf_counter() - update_start
        progress.interactions += length

        clock.tick()
        if clock.log_due():
            score = expert.normalized_score(episode_return, references)
            print(
                f"train {progress.interactions:>8d} steps  return {episode_return:8.1f}"
                f" ({length:4d} steps)  score {score:6.3f}"
                f"  {length / max(update_seconds, 1e-9):5.1f} updates/s"
                f"  ETA {clock.eta_minutes(config.total_steps):6.1f} min",
                flush=True,
            )
        if clock.checkpoint_due():
            checkpoint()
            harness.stop_if_requested()

    harness.save_arrays(run_dir / "policy_final.npz", learner.policy.state("policy"))
    return progress


# === The command line, generated from Config ===

# Settings a resumed run may change: the budget (the learning rates' schedule follows it)
# and what only logging and checkpointing read.
RESUMABLE_CHANGES = ("total_steps", "eval_every", "checkpoint_every", "log_every")


def main(argv: list[str] | None = None, config_class=Config, variant_of=lambda config: OURS) -> int:
    argv = sys.argv[1:] if argv is None else argv

    def body() -> None:
        description = "Off-policy actor-critic imitation learning (Sasaki et al., ICLR 2019)."
        config, resume = harness.config_from_command_line(
            argv, config_class, description, PAPER_SETTINGS, RESUMABLE_CHANGES
        )
        train(config, resume, variant_of(config))

    return harness.run_cli(body)


if __name__ == "__main__":
    sys.exit(main())
