"""Soft Actor-Critic in NumPy: the expert trainer for the tasks ARS cannot reach.

Haarnoja, Zhou, Hartikainen, Tucker, Ha, Tan, Kumar, Zhu, Gupta, Abbeel & Levine, "Soft
Actor-Critic Algorithms and Applications", 2018 (https://arxiv.org/abs/1812.05905): the
version of SAC with twin Q-functions and a learned entropy temperature. Equation numbers
below are that paper's. ARS (lab/ars.py) trains the Hopper, HalfCheetah and Humanoid
experts; it falls short of the targets on Walker2d and Ant within a practical budget on 2
cores, so those are trained here: ``python -m lab.sac --env Walker2d-v4`` from the
repository root (``--help`` lists every setting; ``--resume RUN_DIR`` continues a run).

The paper's symbols and where they live:

    s, a, r, s'    state, action in [-1, 1]^dim A, reward, next state  -> ``Batch``
    D              replay buffer                                        -> ``ReplayBuffer``
    pi_phi         tanh-squashed Gaussian policy: an MLP s -> (mu, log sigma),
                   u = mu + sigma * eps, a = tanh(u)   (Eq. 8, App. C) -> ``sample_actions``
    Q_theta1,2     twin soft Q-functions, MLPs [s, a] -> 1              -> ``Agent.q1``, ``q2``
    Q_theta_bar    their targets, theta_bar <- tau theta + (1 - tau) theta_bar
                                                                        -> ``target_q1``, ``q2``
    alpha          entropy temperature, learned as log alpha            -> ``Agent.log_alpha``
    H_bar          target entropy, -dim A                               -> ``Agent.target_entropy``

One update (``update``), as in Stable-Baselines3's SAC:
  1. sample a ~ pi(.|s) for the batch's states (Eq. 8), keeping the forward pass;
  2. one step on the temperature loss J(alpha), Eq. (18);
  3. targets y = r + gamma (1 - terminated) (min_i Q_bar_i(s', a') - alpha log pi(a'|s')),
     a' ~ pi(.|s'): Eq. (2)-(3) with the twin minimum; a time-limit truncation is not a
     termination, so it bootstraps;
  4. one step on each critic's loss J_Q, Eq. (5), whose gradient is Eq. (6);
  5. one step on the policy loss J_pi = E[alpha log pi(a|s) - min_i Q_i(s, a)], Eq. (9),
     through the reparameterised sample, Eq. (10), with the critics just updated;
  6. soft updates of both target critics.
Every gradient is written out by hand below and checked against finite differences in
tests/test_sac.py.

Settings are the common SAC settings for MuJoCo (Stable-Baselines3 / rl-baselines3-zoo and
CleanRL): two hidden layers of 256 units, Adam with learning rate 3e-4 for everything,
batch 256, replay 10^6, gamma 0.99, tau 0.005, 10 000 uniformly random steps before the
first update, then one gradient step per environment step; log sigma clipped to [-20, 2]
(SB3); initial alpha 1. Two differences from those libraries, both from ``nets.MLP``:
hidden units are leaky ReLU (slope 0.01) instead of ReLU, and weights start from Xavier
(Glorot) uniform instead of PyTorch's default. Observations are not normalised (neither
library does for SAC).

Files in the run directory (by default under the git-ignored ``runs/``), written through
harness.py: ``config.json``, ``progress.csv`` (one row per evaluation), ``checkpoint.npz``
(everything needed to continue: networks, targets, optimisers, alpha, the Generator's
state, counters and progress rows; written atomically at the end of an episode every
``checkpoint_every`` seconds) and, SAC's own, ``replay/`` (the replay buffer in float32,
one file per checkpoint holding the transitions added since the previous one). The best
evaluated policy goes to the expert file (default ``experts/<env>.npz``), in the format
``expert.load_expert`` reads; evaluation is the deterministic policy a = tanh(mu(s)).
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

import expert
import harness
import nets
from harness import UserError
from lab import optim, shipping, table

TRAINER = "SAC (Haarnoja et al. 2018, arXiv:1812.05905), lab/sac.py"  # in the expert file

# ----------------------------------------------------------------------------------------
# Hyperparameters. The command line has one --flag per field, its help the docstring.
# ----------------------------------------------------------------------------------------


@dataclass
class SACConfig:
    """SAC settings; the defaults are the SB3 / rl-zoo / CleanRL settings for MuJoCo."""

    program: ClassVar[str] = "python -m lab.sac"  # the command that resumes its runs

    env: str = ""
    """Gymnasium environment id, e.g. Walker2d-v4 (required)."""
    seed: int = 0
    """Seed of the run's one Generator (the environment's resets are drawn from it)."""
    out: str = ""
    """Expert file for the best evaluated policy; empty: experts/<env>.npz."""
    run_dir: str = ""
    """Run directory; empty: runs/sac-<env>-seed<seed>."""
    steps: int = 1_000_000
    """Training budget in environment steps (evaluation episodes not counted)."""
    hidden: tuple[int, ...] = (256, 256)
    """Hidden layer sizes of the policy and of each critic."""
    lr: float = 3e-4
    """Adam learning rate of the policy, the critics and log alpha."""
    batch_size: int = 256
    """Transitions per gradient step."""
    replay_size: int = 1_000_000
    """Capacity of the replay buffer (FIFO)."""
    gamma: float = 0.99
    """Discount factor."""
    tau: float = 0.005
    """Target critic tracking rate: theta_bar <- tau theta + (1 - tau) theta_bar."""
    learning_starts: int = 10_000
    """Uniformly random actions for this many steps; updates start after them."""
    initial_alpha: float = 1.0
    """Entropy temperature alpha before its first step."""
    eval_every: int = 10_000
    """Environment steps between evaluations of the deterministic policy tanh(mu(s))."""
    eval_episodes: int = 10
    """Episodes per evaluation; the best evaluated policy is the one shipped."""
    checkpoint_every: float = 300.0
    """Seconds between checkpoints (taken at episode ends); 0: after every episode."""
    log_every: float = 60.0
    """Seconds between training progress lines (evaluations always print)."""

    # What `update` reads besides lr, gamma and tau; SAC proper learns everything at one
    # rate and always learns alpha. The imitation peers (lab/peers.py) set them apart.
    @property
    def policy_lr(self) -> float:
        return self.lr

    @property
    def learn_alpha(self) -> bool:
        return True

    @property
    def twin_critics(self) -> bool:
        return True


def check_config(config: SACConfig) -> None:
    """Refuse settings that cannot work (NaN anywhere, a count below 1, ...), in one line."""
    count, positive, seconds = (1, math.inf, "[)"), (0.0, math.inf, "()"), (0.0, math.inf, "[)")
    harness.check_numbers(
        config,
        {
            **dict.fromkeys(
                ("steps", "hidden", "batch_size", "replay_size", "eval_every", "eval_episodes"),
                count,
            ),
            "learning_starts": count,  # the buffer must not be empty at the first update
            "gamma": (0.0, 1.0, "[)"),
            "tau": (0.0, 1.0, "(]"),
            "lr": positive,
            "initial_alpha": positive,
            "checkpoint_every": seconds,
            "log_every": seconds,
        },
    )
    if not config.hidden:
        raise UserError("--hidden needs at least one layer")
    if not config.env:
        raise UserError("--env is required, e.g. --env Walker2d-v4")


# ----------------------------------------------------------------------------------------
# The policy: a tanh-squashed Gaussian, sampled by reparameterisation (Eq. 8, App. C).
# ----------------------------------------------------------------------------------------

# log sigma is clipped to [-20, 2] (SB3): sigma from 2e-9 (a deterministic action) to 7.4
# (far wider than tanh's useful range). Outside, the clip has zero gradient.
LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0
HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)
LOG_2 = math.log(2.0)


def squash_correction(u: np.ndarray) -> np.ndarray:
    """-sum_i log(1 - tanh(u_i)^2), the change of variables a = tanh(u) (App. C), per row.

    1 - tanh(u)^2 underflows to 0 in float32 already at |u| = 9, and log 0 = -inf; the
    identity 1 - tanh(u)^2 = 4 / (e^u + e^-u)^2 gives the stable form
        log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)),
    finite for every u. Its derivative is `squash_correction_grad`.
    """
    return -2.0 * (LOG_2 - u - nets.softplus(-2.0 * u)).sum(axis=1)


def squash_correction_grad(u: np.ndarray) -> np.ndarray:
    """d/du_i of `squash_correction`: -d/du log(1 - tanh(u)^2) = 2 tanh(u), element-wise."""
    return 2.0 * np.tanh(u)


@dataclass
class PolicySample:
    """What `sample_actions_backward` needs from `sample_actions`, all (B, dim A) but cache."""

    cache: nets.Cache  # the policy MLP's forward pass
    noise: np.ndarray  # eps ~ N(0, I)
    std: np.ndarray  # sigma = exp(log sigma)
    log_std_free: np.ndarray  # 1 where log sigma was inside its clip range, else 0
    u: np.ndarray  # pre-squash sample mu + sigma eps
    actions: np.ndarray  # a = tanh(u)


def sample_actions(policy: nets.MLP, states: np.ndarray, noise: np.ndarray):
    """a = tanh(mu(s) + sigma(s) eps) and log pi(a|s), for one noise row per state.

    states: (B, dim S); noise: eps, (B, dim A). Returns (actions (B, dim A), log_prob (B,),
    PolicySample). With u = mu + sigma eps (Eq. 8), the Gaussian's log density at u is
    sum_i -eps_i^2/2 - log sigma_i - log(2 pi)/2, and App. C adds the squashing term:
        log pi(a|s) = log N(u; mu, sigma) - sum_i log(1 - tanh(u_i)^2).
    """
    dim_a = noise.shape[1]
    out, cache = policy.forward(states)  # (B, 2 dim A)
    mean, raw_log_std = out[:, :dim_a], out[:, dim_a:]
    log_std = np.clip(raw_log_std, LOG_STD_MIN, LOG_STD_MAX)
    std = np.exp(log_std)
    u = mean + std * noise  # Eq. (8): a = f_phi(eps; s) = tanh(u)
    actions = np.tanh(u)
    log_gaussian = -(0.5 * noise * noise + log_std + HALF_LOG_2PI).sum(axis=1)
    log_prob = log_gaussian + squash_correction(u)  # App. C
    log_std_free = ((raw_log_std > LOG_STD_MIN) & (raw_log_std < LOG_STD_MAX)).astype(out.dtype)
    return actions, log_prob, PolicySample(cache, noise, std, log_std_free, u, actions)


def sample_actions_backward(
    policy: nets.MLP, d_actions: np.ndarray, d_log_prob: np.ndarray, sample: PolicySample
) -> dict[str, np.ndarray]:
    """The policy's parameter gradients of a loss L(a, log pi), the noise eps held fixed.

    d_actions: dL/da, (B, dim A); d_log_prob: dL/d log pi, (B,). Eq. (10) is this chain
    rule. With eps fixed, the Gaussian term -eps^2/2 is constant, so log pi depends on mu
    only through the squashing term, and on log sigma through -log sigma and through u:
        dL/du       = dL/da (1 - a^2) + dL/dlog pi * 2 tanh(u)
        dL/dmu      = dL/du                                  (du/dmu = 1)
        dL/dlog sig = dL/du sigma eps - dL/dlog pi            (du/dlog sigma = sigma eps)
    and the clip passes the log sigma gradient only inside [-20, 2].
    """
    d_log_prob = d_log_prob[:, None]  # (B, 1), broadcast over the action dimensions
    d_u = d_actions * (1.0 - sample.actions * sample.actions)  # d tanh(u)/du = 1 - tanh^2
    d_u += d_log_prob * squash_correction_grad(sample.u)
    d_log_std = (d_u * sample.std * sample.noise - d_log_prob) * sample.log_std_free
    d_out = np.concatenate([d_u, d_log_std], axis=1)  # (B, 2 dim A): d(mu), d(log sigma)
    _, grads = policy.backward(d_out, sample.cache, input_grads=False)
    return grads


def deterministic_actions(policy: nets.MLP, states: np.ndarray) -> np.ndarray:
    """tanh(mu(s)), the evaluation action, (B, dim A)."""
    out, _ = policy.forward(states)
    return np.tanh(out[:, : out.shape[1] // 2])


# ----------------------------------------------------------------------------------------
# The three losses and their gradients: critics (Eq. 5-6), policy (Eq. 9-10), alpha (Eq. 18).
# ----------------------------------------------------------------------------------------


@dataclass
class Batch:
    """Transitions, one per row; actions in [-1, 1], terminated as 0.0 / 1.0."""

    observations: np.ndarray  # s, (B, dim S)
    actions: np.ndarray  # a, (B, dim A)
    rewards: np.ndarray  # r, (B,)
    next_observations: np.ndarray  # s', (B, dim S)
    terminated: np.ndarray  # 1 if s' is terminal (not a time limit), (B,)


def critic_targets(
    target_q1: nets.MLP,
    target_q2: nets.MLP,
    policy: nets.MLP,
    batch: Batch,
    alpha: float,
    gamma: float,
    noise: np.ndarray,
) -> np.ndarray:
    """y = r + gamma (1 - terminated) V_bar(s'), (B,). No gradient flows through y.

    V_bar(s') = min_i Q_bar_i(s', a') - alpha log pi(a'|s'), a' ~ pi(.|s') with noise
    (B, dim A): the soft state value of Eq. (3), one sample, with the twin minimum.
    """
    next_actions, next_log_prob, _ = sample_actions(policy, batch.next_observations, noise)
    q1 = target_q1.forward((batch.next_observations, next_actions))[0][:, 0]  # (B,)
    q2 = target_q2.forward((batch.next_observations, next_actions))[0][:, 0]  # (B,)
    soft_value = np.minimum(q1, q2) - alpha * next_log_prob  # Eq. (3)
    return batch.rewards + gamma * (1.0 - batch.terminated) * soft_value  # Eq. (2)


def critic_loss_and_grads(critic: nets.MLP, batch: Batch, targets: np.ndarray):
    """J_Q = mean_b 1/2 (Q(s, a) - y)^2 (Eq. 5) and its gradient (Eq. 6) for one critic.

    dJ_Q/dQ_b = (Q_b - y_b) / B, then backward through the critic. Returns (loss, grads, Q).
    """
    q, cache = critic.forward((batch.observations, batch.actions))  # (B, 1)
    td_error = q[:, 0] - targets  # (B,)
    loss = 0.5 * float(np.mean(td_error * td_error))  # Eq. (5)
    d_q = (td_error / len(td_error))[:, None]  # (B, 1), Eq. (6)
    _, grads = critic.backward(d_q, cache, input_grads=False)
    return loss, grads, q[:, 0]


def policy_loss_and_grads(
    policy: nets.MLP,
    q1: nets.MLP,
    q2: nets.MLP,
    states: np.ndarray,
    actions: np.ndarray,
    log_prob: np.ndarray,
    sample: PolicySample,
    alpha: float,
):
    """J_pi = mean_b [alpha log pi(a_b|s_b) - min_i Q_i(s_b, a_b)] (Eq. 9) and Eq. (10).

    actions, log_prob, sample: from `sample_actions(policy, states, noise)`. The critics
    are held fixed: only their action Jacobians are needed. The minimum routes each row's
    gradient to the critic that attains it. Returns (loss, policy grads).
    """
    batch = len(states)
    q1_values, q1_cache = q1.forward((states, actions))  # (B, 1)
    q2_values, q2_cache = q2.forward((states, actions))  # (B, 1)
    first_is_min = q1_values <= q2_values  # (B, 1)
    min_q = np.where(first_is_min, q1_values, q2_values)[:, 0]  # (B,)
    loss = float(np.mean(alpha * log_prob - min_q))  # Eq. (9)
    # dJ/dmin Q = -1/B, sent to whichever critic is the minimum on that row.
    d_q1 = np.where(first_is_min, -1.0 / batch, 0.0).astype(q1_values.dtype)  # (B, 1)
    d_q2 = np.where(first_is_min, 0.0, -1.0 / batch).astype(q2_values.dtype)  # (B, 1)
    backward = dict(param_grads=False, input_grads=(False, True))
    (_, d_actions), _ = q1.backward(d_q1, q1_cache, **backward)  # (B, dim A)
    (_, d_actions_2), _ = q2.backward(d_q2, q2_cache, **backward)
    d_actions += d_actions_2
    d_log_prob = np.full(batch, alpha / batch, dtype=log_prob.dtype)  # dJ/dlog pi
    return loss, sample_actions_backward(policy, d_actions, d_log_prob, sample)  # Eq. (10)


def temperature_loss_and_grad(log_alpha: float, log_prob: np.ndarray, target_entropy: float):
    """J(alpha) = mean_b [-alpha log pi(a_b|s_b) - alpha H_bar] (Eq. 18), alpha = e^log alpha.

    log pi is held fixed. Gradient with respect to log alpha (the variable optimised, so
    that alpha stays positive): dJ/dlog alpha = alpha dJ/dalpha = -alpha mean(log pi + H_bar).
    It raises alpha while the policy's entropy -E log pi is below H_bar, and lowers it above.
    Returns (loss, gradient).
    """
    alpha = math.exp(log_alpha)
    mean_excess = float(np.mean(log_prob)) + target_entropy  # E[log pi] + H_bar
    return -alpha * mean_excess, -alpha * mean_excess  # J = alpha * (-excess); same slope


# ----------------------------------------------------------------------------------------
# The agent: networks, targets, temperature and optimisers, and one update.
# ----------------------------------------------------------------------------------------


@dataclass
class Agent:
    """pi_phi, Q_theta1, Q_theta2, their targets, log alpha, and one Adam per learner."""

    policy: nets.MLP
    q1: nets.MLP
    q2: nets.MLP
    target_q1: nets.MLP
    target_q2: nets.MLP
    log_alpha: dict[str, np.ndarray]  # {"log_alpha": (1,) float64}: a dict for Adam
    target_entropy: float
    policy_optimizer: optim.Adam = field(default_factory=optim.Adam)
    q1_optimizer: optim.Adam = field(default_factory=optim.Adam)
    q2_optimizer: optim.Adam = field(default_factory=optim.Adam)
    alpha_optimizer: optim.Adam = field(default_factory=optim.Adam)

    @classmethod
    def create(cls, dim_s: int, dim_a: int, config: SACConfig, rng, dtype=np.float32) -> Agent:
        hidden = list(config.hidden)
        policy = nets.MLP.create([dim_s, *hidden, 2 * dim_a], "identity", rng, dtype)
        q1 = nets.MLP.create([dim_s + dim_a, *hidden, 1], "identity", rng, dtype)
        q2 = nets.MLP.create([dim_s + dim_a, *hidden, 1], "identity", rng, dtype)
        log_alpha = {"log_alpha": np.array([math.log(config.initial_alpha)])}
        # H_bar = -dim A (Sec. 5 leaves it a hyperparameter; -dim A is its App. D value).
        return cls(policy, q1, q2, q1.copy(), q2.copy(), log_alpha, -float(dim_a))

    @property
    def alpha(self) -> float:
        return math.exp(float(self.log_alpha["log_alpha"][0]))

    def state(self) -> dict[str, np.ndarray]:
        arrays = {"log_alpha": self.log_alpha["log_alpha"]}
        for name in ("policy", "q1", "q2", "target_q1", "target_q2"):
            arrays.update(getattr(self, name).state(name))
        for name in ("policy", "q1", "q2", "alpha"):
            arrays.update(getattr(self, f"{name}_optimizer").state(f"{name}_adam"))
        return arrays

    def load_state(self, arrays) -> None:
        self.log_alpha["log_alpha"][...] = arrays["log_alpha"]
        for name in ("policy", "q1", "q2", "target_q1", "target_q2"):
            getattr(self, name).load_state(arrays, name)
        for name in ("policy", "q1", "q2", "alpha"):
            getattr(self, f"{name}_optimizer").load_state(arrays, f"{name}_adam")


def bellman_critic_step(
    agent: Agent,
    batch: Batch,
    actions: np.ndarray,
    log_prob: np.ndarray,
    alpha: float,
    config,
    rng: np.random.Generator,
) -> tuple[dict, dict, dict]:
    """SAC's critic step (update's steps 3-4): the soft Bellman targets y, Eq. (2)-(3),
    from the target critics and a fresh a' ~ pi(.|s'), then each critic's J_Q, Eq. (5)-(6).

    actions, log_prob: a ~ pi(.|s) at the batch's states (unused here; another critic
    objective, such as IQ-Learn's in lab/peers.py, takes V(s) from them). Returns (q1's
    gradients, q2's gradients, statistics)."""
    next_noise = rng.standard_normal(actions.shape, dtype=actions.dtype)
    targets = critic_targets(
        agent.target_q1, agent.target_q2, agent.policy, batch, alpha, config.gamma, next_noise
    )
    q1_loss, q1_grads, q1_values = critic_loss_and_grads(agent.q1, batch, targets)
    q2_loss, q2_grads, _ = critic_loss_and_grads(agent.q2, batch, targets)
    return q1_grads, q2_grads, {"critic_loss": q1_loss + q2_loss, "q_mean": float(q1_values.mean())}


def update(
    agent: Agent, batch: Batch, config, rng: np.random.Generator, critic_step=bellman_critic_step
) -> dict:
    """One gradient step of every learner, in SB3's order (module docstring, steps 1-6).

    config: lr (critics and log alpha), policy_lr, learn_alpha, gamma and tau (SACConfig,
    or a peer's settings). critic_step: steps 3-4, `bellman_critic_step` for SAC."""
    dim_a = batch.actions.shape[1]
    dtype = agent.policy.dtype
    alpha = agent.alpha  # the same alpha in the targets and the policy loss (as SB3)
    # 1. a ~ pi(.|s), Eq. (8); the forward pass is kept for the policy step (5).
    noise = rng.standard_normal((len(batch.rewards), dim_a), dtype=dtype)
    actions, log_prob, sample = sample_actions(agent.policy, batch.observations, noise)
    # 2. Temperature, Eq. (18), unless it is held at its initial value.
    if config.learn_alpha:
        log_alpha = float(agent.log_alpha["log_alpha"][0])
        _, d_log_alpha = temperature_loss_and_grad(log_alpha, log_prob, agent.target_entropy)
        d_log_alpha = {"log_alpha": np.array([d_log_alpha])}
        agent.alpha_optimizer.step(agent.log_alpha, d_log_alpha, config.lr)
    # 3-4. Critics: SAC's Eq. (2)-(6), or the peer's objective. Without twin critics
    # (config.twin_critics false, a peer's choice) Q_2 is never stepped nor read: the
    # critic step returns None for it, and the policy's minimum is over Q_1 alone.
    q1_grads, q2_grads, stats = critic_step(agent, batch, actions, log_prob, alpha, config, rng)
    agent.q1_optimizer.step(agent.q1.params, q1_grads, config.lr)
    second = agent.q2 if config.twin_critics else agent.q1
    if config.twin_critics:
        agent.q2_optimizer.step(agent.q2.params, q2_grads, config.lr)
    # 5. Policy, Eq. (9)-(10), against the critics just updated.
    policy_loss, policy_grads = policy_loss_and_grads(
        agent.policy, agent.q1, second, batch.observations, actions, log_prob, sample, alpha
    )
    agent.policy_optimizer.step(agent.policy.params, policy_grads, config.policy_lr)
    # 6. Targets track the critics.
    nets.soft_update(agent.target_q1, agent.q1, config.tau)
    if config.twin_critics:
        nets.soft_update(agent.target_q2, agent.q2, config.tau)
    return {
        **stats,
        "policy_loss": policy_loss,
        "alpha": alpha,
        "entropy": -float(np.mean(log_prob)),  # a one-sample estimate of H(pi(.|s))
    }


# ----------------------------------------------------------------------------------------
# The replay buffer D.
# ----------------------------------------------------------------------------------------


class ReplayBuffer:
    """A FIFO of the latest `capacity` transitions, float32, allocated once.

    np.zeros maps untouched pages lazily, so a 10^6 buffer costs memory only as it fills.
    Transition number t (counting from 0 over the whole run) lives in row t % capacity;
    `added` counts them all.

    Saved as segments (`save_new_rows`): each checkpoint writes only the transitions added
    since the previous one to a file of its own, `SEGMENTS/<first>-<end>.npz`, and never
    rewrites it. A checkpoint then costs what was added since the last one, not the whole
    buffer (Humanoid's 10^6 rows would be 3 GB each time), and a run directory kept in
    version control grows by the new rows only.
    """

    FIELDS = ("observations", "actions", "rewards", "next_observations", "terminated")

    def __init__(self, capacity: int, dim_s: int, dim_a: int):
        self.capacity, self.added = capacity, 0
        self.observations = np.zeros((capacity, dim_s), np.float32)
        self.actions = np.zeros((capacity, dim_a), np.float32)
        self.rewards = np.zeros(capacity, np.float32)
        self.next_observations = np.zeros((capacity, dim_s), np.float32)
        self.terminated = np.zeros(capacity, np.float32)

    @property
    def size(self) -> int:
        return min(self.added, self.capacity)

    def add(self, observation, action, reward: float, next_observation, terminated: bool):
        i = self.added % self.capacity
        self.observations[i], self.actions[i], self.rewards[i] = observation, action, reward
        self.next_observations[i], self.terminated[i] = next_observation, terminated
        self.added += 1

    def sample(self, rng: np.random.Generator, n: int) -> Batch:
        rows = rng.integers(0, self.size, n)  # uniform, with replacement
        return Batch(*(getattr(self, name)[rows] for name in self.FIELDS))

    @staticmethod
    def segments(folder: Path) -> list[tuple[int, int, Path]]:
        """(first, end, path) of the segment files in folder, by first transition."""
        found = []
        for path in Path(folder).glob("*-*.npz"):
            first, _, end = path.stem.partition("-")
            if first.isdigit() and end.isdigit():
                found.append((int(first), int(end), path))
        return sorted(found)

    def save_new_rows(self, folder: Path) -> None:
        """Write the transitions not yet in a segment of folder (before the checkpoint
        that counts them, so that a checkpoint never names rows that are not on disk)."""
        oldest = self.added - self.size
        saved = max([end for _, end, _ in self.segments(folder) if end <= self.added] or [0])
        first = max(saved, oldest)
        if first == self.added:
            return
        rows = np.arange(first, self.added) % self.capacity
        Path(folder).mkdir(parents=True, exist_ok=True)
        harness.save_arrays(
            Path(folder) / f"{first:010d}-{self.added:010d}.npz",
            {name: getattr(self, name)[rows] for name in self.FIELDS},
        )

    def prune(self, folder: Path) -> None:
        """Delete the segments wholly older than the buffer's oldest transition (after
        the checkpoint that no longer needs them)."""
        for _, end, path in self.segments(folder):
            if end <= self.added - self.size:
                path.unlink()

    def load_rows(self, folder: Path, added: int) -> None:
        """Refill the buffer as it was after `added` transitions from folder's segments.

        Every segment ends where some checkpoint's count was, so one that ends beyond
        `added` was written by a run killed before its next checkpoint: it is deleted, and
        the resumed run writes those transitions again."""
        self.added = added
        filled = added - self.size  # the oldest transition the buffer holds
        for first, end, path in self.segments(folder):
            if end > added:
                path.unlink()
                continue
            if end <= filled:
                continue
            if first > filled:
                break  # a gap: reported below
            arrays = harness.load_arrays(path)
            rows = np.arange(filled, end) % self.capacity
            for name in self.FIELDS:
                getattr(self, name)[rows] = arrays[name][filled - first : end - first]
            filled = end
        if filled < added:
            raise UserError(
                f"{folder}: the replay buffer's transitions {filled}..{added - 1} are missing"
            )


# ----------------------------------------------------------------------------------------
# The run: progress, checkpoints, evaluation and the training loop.
# ----------------------------------------------------------------------------------------

UPDATE_STATS = ("alpha", "entropy", "critic_loss", "policy_loss", "q_mean")
# harness.Progress.record's columns, then the means of the updates since the last row.
PROGRESS_FIELDS = (
    *("interactions", "wall_seconds", "updates", "episodes", "eval_return_mean"),
    *("eval_return_std", "normalized_score", "train_return", *UPDATE_STATS, "steps_per_second"),
)


@dataclass
class Progress(harness.Progress):
    """harness.Progress (interactions are env steps), and what SAC adds: the best
    evaluation's std and env steps, the command of each session, and the sums of the update
    statistics since the last evaluation."""

    best_return_std: float = 0.0
    best_env_steps: int = 0
    commands: list[str] = field(default_factory=list)
    stat_sums: dict[str, float] = field(default_factory=dict)
    stat_count: int = 0


# The names of runs saved before SAC shared harness.Progress (results/sac-ant-seed0).
OLD_NAMES = {"env_steps": "interactions", "best_return": "best_eval_return"}


def progress_of(rows: list[dict], **counters) -> Progress:
    """A checkpoint's Progress, its counters and rows under today's names."""
    renamed = [{OLD_NAMES.get(k, k): v for k, v in d.items()} for d in (counters, *rows)]
    return Progress(**renamed[0], rows=renamed[1:])


REPLAY_SEGMENTS = "replay"  # the folder of the replay buffer's segments in a run directory


def save_checkpoint(
    run_dir: Path,
    agent: Agent,
    replay: ReplayBuffer,
    progress: Progress,
    rng,
    fields=PROGRESS_FIELDS,
) -> None:
    """Everything needed to continue exactly: the replay buffer's new rows in a segment
    of their own, then one atomic checkpoint file (networks, Generator, counters, the
    number of transitions), then progress.csv; last, the segments no longer needed go."""
    segments = Path(run_dir) / REPLAY_SEGMENTS
    replay.save_new_rows(segments)
    state = {**agent.state(), "replay/added": np.array(replay.added)}
    harness.save_checkpoint(run_dir, state, rng, progress, fields)
    replay.prune(segments)


def load_checkpoint(run_dir: Path, agent: Agent, replay: ReplayBuffer, rng) -> Progress:
    def load(arrays: dict) -> None:
        agent.load_state(arrays)
        replay.load_rows(Path(run_dir) / REPLAY_SEGMENTS, int(arrays["replay/added"]))

    return harness.load_checkpoint(run_dir, rng, load, progress_of)


def expert_policy(env_id: str, agent: Agent, low, high) -> expert.ExpertPolicy:
    """The deterministic policy tanh(mu(s)) as an expert (a copy of the network)."""
    return expert.ExpertPolicy(env_id, low, high, network=agent.policy.copy())


def evaluate(env, policy: expert.ExpertPolicy, seed: int, round_index: int, episodes: int):
    """True returns of the deterministic policy over `episodes` fresh seeded episodes.

    The reset seeds come from their own Generator, (seed, round), so evaluating never
    shifts the training Generator, and they lie far from the seeds 0..9 of Table 1, so
    the shipped policy is not chosen on the episodes that lab/table.py reports.
    """
    seeds = np.random.default_rng([seed, round_index]).integers(2**20, 2**31 - 1, episodes)
    return table.returns(env, policy.act, seeds)


def train(config: SACConfig, resume: bool = False, command: str = "", log=shipping.say) -> Progress:
    """Train SAC until `config.steps` environment steps; keep the best evaluated policy.

    A fresh run refuses a run directory that holds a checkpoint. `resume` continues the
    run from its last checkpoint exactly (same Generator state, same buffer); `config`
    must then be the run's own (config.json), but for RESUMABLE_CHANGES (the budget).
    A run stopped by its budget in the middle of an episode, then extended, starts the
    extension with a fresh episode; a killed run continues exactly where its checkpoint is.
    """
    check_config(config)
    env, eval_env = expert.make_env(config.env), expert.make_env(config.env)  # before any file
    run_dir = harness.open_run_dir(
        config.run_dir or expert.REPO_DIR / "runs" / f"sac-{config.env}-seed{config.seed}", resume
    )
    expert_path = Path(config.out or expert.default_expert_path(config.env))
    dim_s, dim_a = expert.env_dimensions(env)
    low = env.action_space.low.astype(np.float64)
    high = env.action_space.high.astype(np.float64)
    references = expert.references_or_nan(config.env)
    rng = np.random.default_rng(config.seed)  # the run's one Generator, passed explicitly
    agent = Agent.create(dim_s, dim_a, config, rng)
    replay = ReplayBuffer(config.replay_size, dim_s, dim_a)
    if resume:
        progress = load_checkpoint(run_dir, agent, replay, rng)
        log(f"resumed {run_dir} at {progress.interactions} env steps")
    else:
        progress = Progress(best_eval_return=shipping.bar_to_beat(config.env, expert_path, log))
        harness.write_config(
            run_dir, {harness.PROGRAM: config.program, **dataclasses.asdict(config)}
        )
        # A resume needs progress.csv: a kill right after the first checkpoint finds one.
        harness.write_text(run_dir / harness.PROGRESS, harness.progress_csv([], PROGRESS_FIELDS))
    progress.commands.append(command)
    settings = json.dumps(dataclasses.asdict(config))
    log(f"SAC: run dir {run_dir}, expert file {expert_path}, settings {settings}")

    def evaluate_now() -> None:
        policy = expert_policy(config.env, agent, low, high)
        returns = evaluate(
            eval_env, policy, config.seed, progress.eval_rounds, config.eval_episodes
        )
        clock.tick()
        previous = progress.rows[-1] if progress.rows else {"interactions": 0, "wall_seconds": 0}
        count = max(progress.stat_count, 1)
        measured = {name: total / count for name, total in progress.stat_sums.items()}
        measured["steps_per_second"] = (progress.interactions - previous["interactions"]) / max(
            progress.wall_seconds - previous["wall_seconds"], 1e-9
        )
        score = expert.normalized_score(float(returns.mean()), references)
        progress.record(returns, score, measured, PROGRESS_FIELDS)
        progress.stat_sums, progress.stat_count = {}, 0
        improved = returns.mean() > progress.best_eval_return
        if improved:
            progress.best_eval_return, progress.best_return_std = returns.mean(), returns.std()
            progress.best_env_steps = progress.interactions
            shipping.ship(policy, expert_path, returns, TRAINER, progress, config.seed, config)
        csv = harness.progress_csv(progress.rows, PROGRESS_FIELDS)
        harness.write_text(run_dir / harness.PROGRESS, csv)
        log(
            f"eval   env steps {progress.interactions:9d}  wall {progress.wall_seconds:9.1f} s  "
            f"return {returns.mean():8.1f} ± {returns.std():6.1f}"
            + ("  (best, saved)" if improved else "")
        )

    clock = harness.Clock(progress, config.checkpoint_every, config.log_every)
    last_log, steps_at_log, updates_at_log = clock.start, progress.interactions, progress.updates
    observation, episode_return = None, 0.0
    with env, eval_env:
        while progress.interactions < config.steps:
            if observation is None:  # a new episode; checkpoints are taken only here
                observation, _ = env.reset(seed=int(rng.integers(2**31)))
                episode_return = 0.0
            if progress.interactions < config.learning_starts:
                action = rng.uniform(-1.0, 1.0, dim_a).astype(np.float32)
            else:
                state = observation[None].astype(np.float32)  # (1, dim S)
                noise = rng.standard_normal((1, dim_a), dtype=np.float32)
                action = sample_actions(agent.policy, state, noise)[0][0]  # (dim A,)
            next_observation, reward, terminated, truncated, _ = env.step(
                expert.tanh_to_bounds(action, low, high)
            )
            # Only a true termination stops the bootstrap; a time limit does not.
            replay.add(observation, action, reward, next_observation, terminated)
            progress.interactions += 1
            episode_return += float(reward)
            observation = next_observation

            if progress.interactions >= config.learning_starts:
                stats = update(agent, replay.sample(rng, config.batch_size), config, rng)
                progress.updates += 1
                for name in UPDATE_STATS:
                    progress.stat_sums[name] = progress.stat_sums.get(name, 0.0) + stats[name]
                progress.stat_count += 1

            done = progress.interactions == config.steps
            if progress.interactions % config.eval_every == 0 or done:
                evaluate_now()

            clock.tick()
            if clock.log_due():
                now = time.perf_counter()
                seconds = max(now - last_log, 1e-9)
                log(
                    f"train  env steps {progress.interactions:9d}"
                    f"  wall {progress.wall_seconds:9.1f} s"
                    f"  {(progress.interactions - steps_at_log) / seconds:6.1f} steps/s"
                    f"  {(progress.updates - updates_at_log) / seconds:6.1f} updates/s"
                    f"  alpha {agent.alpha:.4f}  episodes {progress.episodes}"
                    + (
                        f"  recent return {np.mean(progress.recent_returns):.1f}"
                        if progress.recent_returns
                        else ""
                    )
                )
                last_log, steps_at_log = now, progress.interactions
                updates_at_log = progress.updates

            if terminated or truncated:
                progress.recent_returns.append(episode_return)
                progress.episodes += 1
                observation = None
                if clock.checkpoint_due():
                    save_checkpoint(run_dir, agent, replay, progress, rng)
                    clock.checkpointed()
                    harness.stop_if_requested()
        save_checkpoint(run_dir, agent, replay, progress, rng)  # at the budget's end
    log(
        f"done: {progress.interactions} env steps; best eval return "
        f"{progress.best_eval_return:.1f} ± {progress.best_return_std:.1f} at "
        f"{progress.best_env_steps} env steps; expert in {expert_path}"
    )
    return progress


# ----------------------------------------------------------------------------------------
# Command line: python -m lab.sac --env ENV [flags], one flag per SACConfig field.
# ----------------------------------------------------------------------------------------

# What a resumed run may change: its budget, its expert file, and what only logging and
# checkpoints read.
RESUMABLE_CHANGES = ("steps", "out", "checkpoint_every", "log_every")


def parse(argv: list[str]) -> tuple[SACConfig, bool]:
    description = __doc__.splitlines()[0]
    return harness.config_from_command_line(
        argv, SACConfig, description, {}, RESUMABLE_CHANGES, prog="python -m lab.sac"
    )


def main(argv: list[str] | None = None) -> int:
    def run(parsed, argv) -> Progress:
        return train(*parsed, command=shipping.command_line("lab.sac", argv))

    return harness.cli_main(argv, parse, run)


if __name__ == "__main__":
    sys.exit(main())
