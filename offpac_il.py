"""Off-policy actor-critic imitation learning, in NumPy.

Sasaki, Yohira & Kawaguchi, "Sample Efficient Imitation Learning for Continuous
Control", ICLR 2019 (https://openreview.net/forum?id=BkN5UoAqF7). Equation numbers
below are the paper's.

The method in four lines (Algorithm 1):
  1. roll out one episode with a = pi_theta(s, z) = tanh(PN(s, z)), z ~ N(0, I) (Sec. 3.2),
     and store each (s, a, s') in a FIFO replay buffer B_beta;
  2. then, as many times as the episode had steps:
  3.   move the critic q_nu (Q = log q, Eq. 10) by objective (18): match q(s, a) to
       E_z q_nu'(s', pi(s', z))^gamma on expert triplets, and to half of it on replay
       triplets, in Jensen-Shannon divergence; then soft-update the target critic nu';
  4.   move the policy by gradient (6): the gradient of log q(s, pi(s, z)) through the
       critic's action Jacobian, averaged over 128 noise samples per replay state.
No reward is ever learned: q itself encodes "expert-like now and later" (Sec. 3.1.3).

The paper's ablations (Sec. 5.3, Figure 4) are switches of the same code, off by default:
--on-policy (Ours+OnP), --reward-learning discriminator|entropy (Ours+IRL(D), Ours+IRL(E)),
--policy-type gaussian|deterministic (Ours+GP, Ours+DP); see "The learner" below.

Run `python offpac_il.py --env Hopper-v4`; `--help` lists every setting.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

import expert
import nets
from expert import UserError

# ----------------------------------------------------------------------------------------
# Hyperparameters (Appendix B unless said otherwise). The command line is made from
# this dataclass: each field becomes --field-name, its docstring the help text.
# ----------------------------------------------------------------------------------------


@dataclass
class Config:
    env: str = "Hopper-v4"
    """Gymnasium environment id (Box observations, bounded Box actions)."""
    seed: int = 0
    """Seed of the run's single numpy Generator and of the environment."""
    total_steps: int = 300_000
    """Interaction budget; the learning rates decrease linearly to 0 over it."""
    demos: str = ""
    """Demonstration file (.npz); empty: the shipped expert's default demonstrations."""
    trajectories: int = 4
    """Expert trajectories in the default demonstrations (Sec. 5.1)."""
    sampling: str = "sparse"
    """Default demonstrations: sparse (100 random triplets per trajectory) or dense."""
    demo_seed: int = 0
    """Seed of the default demonstrations."""

    policy_hidden: tuple[int, ...] = (100, 100)
    """PN's hidden layer sizes."""
    critic_hidden: tuple[int, ...] = (500, 500)
    """QN's hidden layer sizes."""
    # The learning rates are 0.23 x (PN) and 0.3 x (QN) Appendix B's (1e-4, 1e-3), and the
    # policy step also sees expert states (policy_expert_states below): measured
    # deviations without which Hopper-v4 reaches the expert and falls away again (README,
    # Results). PN's 2.3e-5 (not 3e-5) is for the 128 noise samples: at 3e-5 they
    # relapsed or got stuck where 8 samples held. --paper restores Appendix B's values.
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
    """Noise vectors z per replay state in the policy gradient (6)."""
    # 8 target samples cost 1 024 rows through the policy and the target critic, about a
    # tenth of an update (benchmarks/update.py); its effect on learning against 1 and 128
    # is not measured yet.
    target_samples: int = 8
    """Noise vectors z per next state in the critic's target E_z q'(s', pi(s', z))^gamma."""

    # Defaults from the measurements in the README: under objective (18) the absorbing
    # state taught Hopper to fall at once; zero continuation is the only treatment that
    # makes a fall worse than staying up (bootstrapping through falls did as well over
    # one 55 k run). Standardisation is DAC's and ValueDICE's default; without it Hopper
    # reached 0.91 at 41 k and fell to 0.03 by 75 k.
    termination: str = "zero"
    """At a terminal s': bootstrap (literal Alg. 1), absorbing (DAC), or zero (q'^gamma=0)."""
    standardize: bool = True
    """Standardise states by the demonstrations' mean and std (+1e-3)."""
    critic_reg: float = 0.0
    """Weight of D_JS(q_nu(s,a) || q_nu'(s,a)), the submitted version's critic regulariser."""
    critic_grad_penalty: float = 0.0
    """Weight of 1/2 mean ||dx/d[s,a]||^2 on the critic's logit (DAC's stabiliser; paper: 0)."""
    policy_expert_states: float = 0.5
    """Fraction of the policy step's states drawn from the demonstrations (paper: 0)."""
    exploration_noise: float = 0.0
    """Std of Gaussian noise added to the action in training episodes (paper: 0)."""
    critic_input_noise: float = 0.0
    """Std of Gaussian noise added to the critic step's (s, a) inputs (paper: 0)."""
    # Measured on Hopper (README): the averaged PN held the expert's return through the
    # spells in which PN itself relapsed. It changes nothing in training.
    policy_average: float = 1e-4
    """Rate of a Polyak average of PN's weights, also evaluated (0: none; paper: none)."""

    # The paper's ablations (Sec. 5.3, Figure 4), switches of this one learner; the
    # defaults are Ours. What each switch changes, and why: the comment above `Learner`.
    on_policy: bool = False
    """Ours+OnP: empty the replay buffer after each episode's updates (only fresh samples)."""
    reward_learning: str = "none"
    """Ours+IRL(D)/(E): learn r_omega by objective (2) (discriminator) or (8) (entropy)."""
    policy_type: str = "bounded"
    """bounded: tanh(PN(s, z)) (Ours); gaussian (Ours+GP); deterministic, fixed z (Ours+DP)."""

    eval_every: int = 5_000
    """Interactions between evaluations."""
    eval_episodes: int = 5
    """Episodes per evaluation (stochastic policy, true reward)."""
    run_dir: str = ""
    """Run directory; empty: runs/<env>-seed<seed>."""
    checkpoint_every: float = 120.0
    """Seconds between checkpoints (taken at episode ends); 0: after every episode."""
    log_every: float = 10.0
    """Seconds between progress lines for training episodes (evaluations always print)."""


# Appendix B's values of the settings whose defaults deviate from it (--paper).
PAPER_SETTINGS = {
    "policy_lr": 1e-4,
    "critic_lr": 1e-3,
    "policy_expert_states": 0.0,
    "policy_average": 0.0,
}


def saved_config(saved: dict) -> Config:
    """The Config of a run's config.json. A setting the file lacks did not exist when the
    run was made, so the run had that setting's behaviour from before it existed: the
    paper's (PAPER_SETTINGS), not today's default."""
    known = {f.name for f in dataclasses.fields(Config)}
    values = {**PAPER_SETTINGS, **saved}
    return Config(
        **{k: tuple(v) if isinstance(v, list) else v for k, v in values.items() if k in known}
    )


TERMINATIONS = ("bootstrap", "absorbing", "zero")
SAMPLINGS = ("sparse", "dense")
REWARD_LEARNINGS = ("none", "discriminator", "entropy")
POLICY_TYPES = ("bounded", "gaussian", "deterministic")


def check_config(config: Config) -> None:
    """Refuse settings that cannot work, with one clear message."""
    for name, choices in (
        ("termination", TERMINATIONS),
        ("sampling", SAMPLINGS),
        ("reward_learning", REWARD_LEARNINGS),
        ("policy_type", POLICY_TYPES),
    ):
        if getattr(config, name) not in choices:
            raise UserError(f"--{name.replace('_', '-')} must be one of {', '.join(choices)}")
    for name in (
        "total_steps",
        "trajectories",
        "batch_size",
        "replay_size",
        "noise_samples",
        "target_samples",
        "eval_every",
        "eval_episodes",
    ):
        if getattr(config, name) < 1:
            raise UserError(f"--{name.replace('_', '-')} must be at least 1")
    if not 0.0 <= config.gamma < 1.0:
        raise UserError("--gamma must lie in [0, 1)")
    if config.critic_reg < 0 or config.critic_grad_penalty < 0:
        raise UserError("--critic-reg and --critic-grad-penalty must be at least 0")
    if not 0.0 <= config.policy_expert_states <= 1.0:
        raise UserError("--policy-expert-states must lie in [0, 1]")
    if not 0.0 <= config.policy_average <= 1.0:
        raise UserError("--policy-average must lie in [0, 1]")
    for name in ("exploration_noise", "critic_input_noise"):
        if not 0.0 <= getattr(config, name) < math.inf:
            raise UserError(f"--{name.replace('_', '-')} must be a finite number, at least 0")


# ----------------------------------------------------------------------------------------
# Spaces: the learner acts in [-1, 1]^dim A and sees
# standardised states, with one extra indicator input for the absorbing state.
# ----------------------------------------------------------------------------------------


@dataclass
class Spaces:
    """Maps between the environment's units and the networks' units."""

    low: np.ndarray
    high: np.ndarray
    state_mean: np.ndarray
    state_std: np.ndarray
    absorbing: bool

    def to_env_action(self, action: np.ndarray) -> np.ndarray:
        """[-1, 1] -> [low, high]: low + (a + 1)(high - low)/2."""
        return self.low + (action + 1.0) * (self.high - self.low) / 2.0

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
    if config.standardize:  # as DAC and ValueDICE do
        mean = demos.observations.mean(axis=0)
        std = demos.observations.std(axis=0) + 1e-3
    else:
        mean, std = np.zeros(obs_dim, np.float32), np.ones(obs_dim, np.float32)
    return Spaces(
        env.action_space.low.astype(np.float32),
        env.action_space.high.astype(np.float32),
        mean.astype(np.float32),
        std.astype(np.float32),
        absorbing=config.termination == "absorbing",
    )


# ----------------------------------------------------------------------------------------
# Buffers of (s, a, s') triplets. `terminal` marks a terminal s' (not a time limit).
# ----------------------------------------------------------------------------------------


@dataclass
class Triplets:
    states: np.ndarray  # (N, dim s)
    actions: np.ndarray  # (N, dim A), in [-1, 1]
    next_states: np.ndarray  # (N, dim s)
    terminal: np.ndarray  # (N,) bool


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
        return take(self.data, rng.integers(0, self.size, n))

    def clear(self) -> None:
        """Forget every triplet (the on-policy ablation, after each episode's updates)."""
        self.size, self.next_index = 0, 0

    def state(self) -> dict[str, np.ndarray]:
        return {
            "replay/states": self.data.states,
            "replay/actions": self.data.actions,
            "replay/next_states": self.data.next_states,
            "replay/terminal": self.data.terminal,
            "replay/size_next": np.array([self.size, self.next_index]),
        }

    def load_state(self, arrays) -> None:
        for name in ("states", "actions", "next_states", "terminal"):
            getattr(self.data, name)[...] = arrays[f"replay/{name}"]
        self.size, self.next_index = (int(v) for v in arrays["replay/size_next"])


def take(triplets: Triplets, index: np.ndarray) -> Triplets:
    return Triplets(
        triplets.states[index],
        triplets.actions[index],
        triplets.next_states[index],
        triplets.terminal[index],
    )


def expert_buffer_from(demos: expert.Demos, spaces: Spaces) -> Triplets:
    """B_pi_E: every demonstration triplet, in the networks' units."""
    return Triplets(
        spaces.state(demos.observations),
        spaces.from_env_action(demos.actions),
        spaces.state(demos.next_observations),
        demos.terminals.astype(bool),
    )


# ----------------------------------------------------------------------------------------
# The learner: networks, the critic step (18) and the policy step (6).
#
# The paper's ablations (Sec. 5.3, Figure 4) are switches of this one code path; with
# every switch off (the defaults) the run is Ours, draw for draw:
# - on_policy (Ours+OnP): the replay buffer is emptied after each episode's updates, so
#   every update samples the latest episode's triplets only (see `train`);
# - reward_learning (Ours+IRL(D), Ours+IRL(E)): a reward network r_omega, learned by
#   objective (2) or (8) (`reward_loss_and_grads`), and the critic trained by objective
#   (15) with P_omega-nu-gamma of Eq. (13) in place of (18) (`critic_targets`);
# - policy_type (Ours+GP, Ours+DP): a Gaussian policy, or the bounded policy with its
#   noise input held at one fixed vector (`Learner.policy_forward`).
# ----------------------------------------------------------------------------------------

# Bounds of the Gaussian policy's log-std, as in SAC's reference implementation (Haarnoja
# et al., 2018): sigma in [2e-9, 7.4] in [-1, 1] action units. A log-std output outside
# them is clipped and gets no gradient.
LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


@dataclass
class PolicyCache:
    """What `Learner.policy_backward` needs from `Learner.policy_forward`.

    net: PN's cache. Gaussian policy only: noise (G, Z, dim A), the eps of each row
    grouped by state; std (G, dim A); inside (G, dim A), 1 where the log-std output lies
    strictly within its bounds, else 0.
    """

    net: nets.Cache
    noise: np.ndarray | None = None
    std: np.ndarray | None = None
    inside: np.ndarray | None = None


@dataclass
class Learner:
    """pi_theta = tanh(PN([s, z])) and q_nu = sigmoid(QN([s, a])), with target q_nu'.

    policy_type: "bounded" is the above (Sec. 3.2). "gaussian" (Ours+GP, Figure 1a):
    PN([s]) = [mu, log sigma] with an identity head, a = mu + sigma * eps, eps ~ N(0, I),
    unbounded; `noise_dim` is then dim A. "deterministic" (Ours+DP): tanh(PN([s, z_0]))
    with z_0 = `fixed_noise`, whatever noise the caller draws.
    reward, reward_optimizer: r_omega = sigmoid(RN([s, a])), QN's size, and its RMSProp,
    when a reward is learned (reward_learning != "none"); else None.
    average_policy: PN's Polyak-averaged weights (--policy-average), else None. It never
    acts in training episodes nor enters a gradient: it is only evaluated beside PN.
    """

    policy: nets.MLP
    critic: nets.MLP
    target_critic: nets.MLP
    noise_dim: int
    policy_optimizer: nets.RMSProp = field(default_factory=nets.RMSProp)
    critic_optimizer: nets.RMSProp = field(default_factory=nets.RMSProp)
    policy_type: str = "bounded"
    fixed_noise: np.ndarray | None = None  # (dim z,): Ours+DP's z_0
    reward: nets.MLP | None = None
    reward_optimizer: nets.RMSProp | None = None
    average_policy: nets.MLP | None = None

    @classmethod
    def create(cls, state_dim, noise_dim, action_dim, config: Config, rng, dtype=np.float32):
        """The networks, drawn from `rng` in a fixed order: PN, QN, then (if any) the reward
        network and z_0. So at one seed every ablation but Ours+GP starts from Ours' PN
        and QN."""
        if config.policy_type == "gaussian":
            noise_dim = action_dim  # eps enters after PN (Figure 1a), one per action component
            policy = nets.MLP.create(
                [state_dim, *config.policy_hidden, 2 * action_dim], "identity", rng, dtype
            )
            # The log-std head starts at 0 (sigma = 1 at every state), as the Gaussian
            # policies of the paper's GAIL code (openai/imitation) and of baselines.py
            # do; with Xavier weights sigma would start at exp of O(1) values that vary
            # by state (a mean of 1.6 on Hopper's first states).
            policy.params[f"W{policy.n_layers - 1}"][:, action_dim:] = 0.0
        else:
            policy = nets.MLP.create(
                [state_dim + noise_dim, *config.policy_hidden, action_dim], "tanh", rng, dtype
            )
        critic = nets.MLP.create(
            [state_dim + action_dim, *config.critic_hidden, 1], "sigmoid", rng, dtype
        )
        learner = cls(
            policy,
            critic,
            critic.copy(),
            noise_dim,
            nets.RMSProp(config.rmsprop_decay, config.rmsprop_eps),
            nets.RMSProp(config.rmsprop_decay, config.rmsprop_eps),
            config.policy_type,
        )
        if config.reward_learning != "none":
            learner.reward = nets.MLP.create(
                [state_dim + action_dim, *config.critic_hidden, 1], "sigmoid", rng, dtype
            )
            learner.reward_optimizer = nets.RMSProp(config.rmsprop_decay, config.rmsprop_eps)
        if config.policy_average > 0:
            learner.average_policy = policy.copy()
        if config.policy_type == "deterministic":
            # Ours+DP, "a deterministic policy with fixed input noises" (Sec. 5.3): we
            # read it as Ours' PN with P_z replaced by a point mass at one draw
            # z_0 ~ N(0, I), made once per run. Not z = 0: that would make PN's z inputs
            # dead weights, a different network; with z_0 the network, its inputs'
            # scale and its parameters are Ours', and only the noise is frozen.
            learner.fixed_noise = rng.standard_normal(noise_dim).astype(dtype)
        return learner

    def samples_per_state(self, samples: int) -> int:
        """Noise rows worth drawing per state: `samples`, or 1 for the deterministic
        policy, whose rows would all be equal (same mean, `samples` times the work)."""
        return 1 if self.policy_type == "deterministic" else samples

    def policy_forward(self, states: np.ndarray, noise: np.ndarray):
        """Actions (N, dim A) for noise rows (N, dim z), `states` (G, dim s) each shared
        by N/G consecutive rows (G = N: one each); and the cache for `policy_backward`."""
        if self.policy_type == "gaussian":
            out, net_cache = self.policy.forward(states)  # (G, 2 dim A): PN once per state
            a_dim, groups = self.noise_dim, len(out)
            mean, log_std = out[:, :a_dim], out[:, a_dim:]  # (G, dim A) each
            std = np.exp(np.clip(log_std, LOG_STD_MIN, LOG_STD_MAX))  # (G, dim A)
            eps = noise.reshape(groups, -1, a_dim)  # (G, Z, dim A)
            actions = (mean[:, None, :] + std[:, None, :] * eps).reshape(-1, a_dim)  # (N, dim A)
            inside = (log_std > LOG_STD_MIN) & (log_std < LOG_STD_MAX)
            return actions, PolicyCache(net_cache, eps, std, inside.astype(std.dtype))
        if self.policy_type == "deterministic":
            noise = np.broadcast_to(self.fixed_noise, noise.shape)  # z_0 for every z
        actions, net_cache = self.policy.forward((states, noise))  # tanh(PN([s, z]))
        return actions, PolicyCache(net_cache)

    def policy_backward(self, d_actions: np.ndarray, cache: PolicyCache) -> dict[str, np.ndarray]:
        """PN's parameter gradients from d_actions = dL/da (N, dim A).

        Gaussian (the reparameterisation of gradient 6): a = mu + sigma * eps with
        sigma = exp(clip(l)), so da/dmu = 1 and da/dl = sigma * eps inside the bounds
        (0 outside). A state's mu and l serve its Z rows, so their gradients sum over
        them: dL/dmu = sum_z dL/da, dL/dl = sum_z dL/da * eps * sigma * inside.
        """
        if self.policy_type == "gaussian":
            d_a = d_actions.reshape(cache.noise.shape)  # (G, Z, dim A)
            d_mean = d_a.sum(axis=1)  # (G, dim A)
            d_log_std = (d_a * cache.noise).sum(axis=1) * cache.std * cache.inside  # (G, dim A)
            d_out = np.concatenate([d_mean, d_log_std], axis=1)  # (G, 2 dim A)
            return self.policy.backward(d_out, cache.net, input_grads=False)[1]  # identity head
        # Through tanh and PN; PN's own input needs no gradient.
        return self.policy.backward(d_actions, cache.net, input_grads=False)[1]

    def act(self, states: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """a = pi_theta(s, z) (in [-1, 1] unless Gaussian). `states` may be shared over
        the noise rows."""
        return self.policy_forward(states, noise)[0]

    def policy_std(self, states: np.ndarray) -> np.ndarray:
        """The Gaussian policy's sigma(s) (G, dim A), as it acts (clipped log-std)."""
        out, _ = self.policy.forward(states)
        return np.exp(np.clip(out[:, self.noise_dim :], LOG_STD_MIN, LOG_STD_MAX))

    def policy_state(self) -> dict[str, np.ndarray]:
        """What acting needs: PN's parameters, and z_0 for the deterministic policy (the
        contents of policy_best.npz and policy_final.npz)."""
        arrays = self.policy.state("policy")
        if self.fixed_noise is not None:
            arrays["policy/fixed_noise"] = self.fixed_noise
        return arrays

    def state(self) -> dict[str, np.ndarray]:
        arrays = {
            **self.policy_state(),
            **self.critic.state("critic"),
            **self.target_critic.state("target_critic"),
            **self.policy_optimizer.state("policy_rmsprop"),
            **self.critic_optimizer.state("critic_rmsprop"),
        }
        if self.reward is not None:
            arrays.update(self.reward.state("reward"))
            arrays.update(self.reward_optimizer.state("reward_rmsprop"))
        if self.average_policy is not None:
            arrays.update(self.average_policy.state("average_policy"))
        return arrays

    def averaged(self) -> Learner:
        """This learner acting with the averaged PN (shares every other part)."""
        return dataclasses.replace(self, policy=self.average_policy)

    def load_policy_state(self, arrays) -> None:
        """The inverse of policy_state (a policy file, or a checkpoint's policy)."""
        self.policy.load_state(arrays, "policy")
        if self.fixed_noise is not None:
            self.fixed_noise[...] = arrays["policy/fixed_noise"]

    def load_state(self, arrays) -> None:
        self.load_policy_state(arrays)
        self.critic.load_state(arrays, "critic")
        self.target_critic.load_state(arrays, "target_critic")
        self.policy_optimizer.load_state(arrays, "policy_rmsprop")
        self.critic_optimizer.load_state(arrays, "critic_rmsprop")
        if self.reward is not None:
            self.reward.load_state(arrays, "reward")
            self.reward_optimizer.load_state(arrays, "reward_rmsprop")
        if self.average_policy is not None:
            self.average_policy.load_state(arrays, "average_policy")


# Rows per chunk of the big passes (policy step, critic targets). Measured for the
# policy step at paper sizes on 2 cores: see `chunks_of`.
CHUNK_ROWS = 1024


def chunks_of(n_states: int, rows_per_state: int) -> list[slice]:
    """Slices of states whose rows (states x noise samples) fill about CHUNK_ROWS each.

    The chunks run on a thread pool (nets.map_chunks) with BLAS on one thread. Chunks
    are a trade: small ones keep activations in cache, large ones pay less Python
    overhead (which holds the GIL) per row. For 8 192 rows on 2 cores, the policy step
    took 167, 140, 109 and 98 ms at 128, 256, 512 and 1024 rows per chunk, and 158 ms
    unchunked with BLAS on both cores. There is at least one chunk per core.
    """
    cores = os.cpu_count() or 1
    per_chunk = max(1, min(CHUNK_ROWS // rows_per_state, -(-n_states // cores)))
    return [slice(lo, min(n_states, lo + per_chunk)) for lo in range(0, n_states, per_chunk)]


def critic_targets(
    learner: Learner,
    batch: Triplets,
    from_replay: np.ndarray,
    config: Config,
    rng: np.random.Generator,
) -> np.ndarray:
    """t, the Bernoulli parameter the critic's q_nu(s, a) is matched to, per row.

    Ours, objective (18): t = E_z[q_nu'(s', pi(s', z))^gamma], halved for replay rows
    (the "/2" of Eq. 17-18: objective (8)'s optimal reward, 1 on expert pairs and 1/2 on
    the learner's, written in as constants).

    With a learned reward (Ours+IRL), objective (15): t = E_{s', a'}[P_omega-nu-gamma(
    pi_E | s, a, s', a')] with Eq. (13)'s P = r_omega(s, a) q_nu(s', a')^gamma. r_omega
    depends on (s, a) alone, so t = r_omega(s, a) E_z[q_nu'(s', pi(s', z))^gamma] on every
    row, expert or replay, and nothing is halved: r_omega takes the place of the constants.

    The expectation is a mean over `target_samples` noise vectors per next state (one
    for the deterministic policy). At a terminal s' under termination="zero" the
    continuation q'^gamma is 0 (so t = 0 with or without r_omega); under "bootstrap"
    the terminal s' is treated like any other; under "absorbing" the next state is the
    absorbing state, which the critic (and r_omega) learn like any other. q_nu in the
    target is the target critic q_nu' (App. B). No gradient flows through t, neither to
    nu nor to omega (r_omega learns from its own objective only).
    """
    k = learner.samples_per_state(config.target_samples)
    noise = rng.standard_normal((len(batch.next_states) * k, learner.noise_dim), np.float32)

    def chunk_targets(rows: slice) -> np.ndarray:
        next_states = batch.next_states[rows]  # (C, dim s), each shared by k noise rows
        z = noise[rows.start * k : rows.stop * k]  # (C*k, dim z)
        next_actions = learner.act(next_states, z)  # (C*k, dim A)
        _, cache = learner.target_critic.forward((next_states, next_actions))
        log_q = nets.log_sigmoid(cache.logits).reshape(-1, k)  # (C, k): log q'(s', a'_k)
        return np.exp(config.gamma * log_q).mean(axis=1)  # (C,): mean_k q'^gamma

    t = np.concatenate(nets.map_chunks(chunk_targets, chunks_of(len(noise) // k, k)))
    if config.termination == "zero":
        t[batch.terminal] = 0.0
    if learner.reward is None:
        t[from_replay] *= 0.5  # the "/2" of Eq. (17)-(18): replay pairs earn r = 1/2
    else:
        reward, _ = learner.reward.forward((batch.states, batch.actions))  # (rows, 1)
        t *= reward[:, 0]  # Eq. (13) in (15): r_omega(s, a) E q'(s', a')^gamma
    return t


def reward_loss_and_grads(
    reward: nets.MLP, states: np.ndarray, actions: np.ndarray, n_expert: int, objective: str
):
    """The reward network's loss and its gradient w.r.t. every reward parameter.

    r_omega(s, a) = sigmoid(x), x the network's logit: the probability that the expert
    would take a at s, R_omega = log r_omega (Sec. 3.1.1). Rows: n_expert expert pairs
    (from B_pi_E), then the learner's pairs (from B_beta: the paper's pi in (2) and (8)
    is sampled through the behaviour policy beta, as for the critic in Sec. 3.3). Each
    expectation is the mean over its rows; the loss is the objective's negative.

    "discriminator", objective (2) (Ours+IRL(D)): argmax_omega J(pi_E, R_omega) -
    J(pi, R_omega). Read literally, with J(pi, R) = E_{rho_pi, pi}[R], that is
    E_E[log r] - E_pi[log r], which has no maximum (-log r grows without bound as r -> 0
    on the learner's pairs; max-margin IRL bounds the norm of omega). The paper reads (2)
    as assigning r = 1 to expert pairs and r = 0 to the learner's (Sec. 3.1.1), which the
    AIL methods it names do with a discriminator: GAIL (Ho & Ermon 2016, Eq. 17; the same
    loss as baselines.py's) maximises E_E[log r] + E_pi[log(1 - r)], whose optimum
    r* = rho_E / (rho_E + rho_pi) is 1 on expert pairs and 0 on the learner's pairs away
    from them (log r = -inf there: the problem Sec. 3.1.1 points out, which this ablation
    is to show). From the logit, log r = -softplus(-x) and log(1 - r) = -softplus(x):
        L = mean_E softplus(-x) + mean_pi softplus(x)
        dL/dx = -(1 - r) / n_E on expert rows,  r / n_pi on the learner's rows.

    "entropy", objective (8) (Ours+IRL(E)): argmax_omega E_E[p_omega(pi_E|s, a)] +
    E_pi[H(p_omega(.|s, a))], with p_omega(pi_E|s, a) = r (Sec. 3.1.1) and H the
    Bernoulli entropy (9). The first term is r itself, not log r, as (8) is written: it
    is maximal at r = 1 on expert pairs; the entropy is maximal at r = 1/2 on the
    learner's. With dr/dx = r(1 - r) and dH/dx = -x r(1 - r) (nets.bernoulli_entropy_grad):
        L = -mean_E r - mean_pi H(r)
        dL/dx = -r(1 - r) / n_E on expert rows,  x r(1 - r) / n_pi on the learner's rows.

    Returns (loss, grads, cache).
    """
    _, cache = reward.forward((states, actions))
    x = cache.logits  # (n_E + n_pi, 1): r = sigmoid(x)
    x_expert, x_learner = x[:n_expert], x[n_expert:]
    n_learner = len(x_learner)
    if objective == "discriminator":  # objective (2), as a logistic discriminator
        loss = nets.softplus(-x_expert).mean() + nets.softplus(x_learner).mean()
        d_x = np.concatenate(
            [-nets.sigmoid(-x_expert) / n_expert, nets.sigmoid(x_learner) / n_learner]
        )
    elif objective == "entropy":  # objective (8), with H of Eq. (9)
        loss = -nets.sigmoid(x_expert).mean() - nets.bernoulli_entropy(x_learner).mean()
        d_x = np.concatenate(
            [
                -nets.sigmoid_grad(x_expert) / n_expert,
                -nets.bernoulli_entropy_grad(x_learner) / n_learner,
            ]
        )
    else:
        raise ValueError(f"unknown reward objective {objective!r}")
    _, grads = reward.backward(d_x, cache, through_head=False, input_grads=False)
    return float(loss), grads, cache


def reward_step(
    learner: Learner, batch: Triplets, n_expert: int, config: Config, lr: float
) -> dict[str, float]:
    """One RMSProp step of r_omega on objective (2) or (8) (Ours+IRL).

    It uses the critic step's triplets, and QN's optimiser settings and learning rate
    (the paper gives none for a reward network; ours is QN-sized, so it is trained like
    QN). It runs before the critic's targets are computed, so each update alternates the
    three processes of Sec. 1 (b) in order: reward, value, policy.
    """
    loss, grads, cache = reward_loss_and_grads(
        learner.reward, batch.states, batch.actions, n_expert, config.reward_learning
    )
    learner.reward_optimizer.step(learner.reward.params, grads, lr)
    r = cache.output[:, 0]
    return {
        "reward_loss": loss,
        "r_expert": float(r[:n_expert].mean()),
        "r_replay": float(r[n_expert:].mean()),
    }


def critic_loss_and_grads(
    learner: Learner,
    batch: Triplets,
    t: np.ndarray,
    n_expert: int,
    critic_reg: float,
    grad_penalty: float = 0.0,
):
    """Objective (18), or (15), and its gradient w.r.t. every critic parameter, for fixed t.

    Both objectives are D_JS(P_nu(.|s, a) || Bern(t)) with P_nu(pi_E|s, a) = q_nu(s, a)
    (Eq. 12), averaged over the expert rows and over the replay rows, the two averages
    added; they differ only in t (`critic_targets`): (18)'s E q'^gamma and its half, or
    (15)'s r_omega(s, a) E q'^gamma (Eq. 13). With t frozen, the gradient w.r.t. the
    critic's logit x is dD_JS/dx = 1/2 p(1-p)(logit p - logit m), m = (p + t)/2 (derived
    in nets.js_divergence_grad), backpropagated through QN.

    batch: n_expert expert triplets followed by as many replay triplets; t: (rows, 1).
    critic_reg, grad_penalty: weights of the two optional stabilisers (Config).
    Returns (loss, grads, critic cache).
    """
    _, cache = learner.critic.forward((batch.states, batch.actions))
    x = cache.logits  # (2n, 1): p = q_nu(s, a) = sigmoid(x), Eq. (10)
    # Eq. (18): mean over expert rows of D_JS(P_nu || t) + mean over replay rows of the same
    # (both halves hold n rows, so one sum / n is both means added).
    loss = nets.js_divergence(x, t).sum() / n_expert
    d_x = nets.js_divergence_grad(x, t) / n_expert  # dD_JS/dx = 1/2 p(1-p)(logit p - logit m)
    if critic_reg > 0:
        # The submitted version's regulariser: D_JS(q_nu(s,a) || q_nu'(s,a)), same rows.
        _, target_cache = learner.target_critic.forward((batch.states, batch.actions))
        q_target = nets.sigmoid(target_cache.logits)
        loss += critic_reg * nets.js_divergence(x, q_target).mean()
        d_x += critic_reg * nets.js_divergence_grad(x, q_target) / len(x)
    _, grads = learner.critic.backward(d_x, cache, through_head=False, input_grads=False)
    if grad_penalty > 0:
        # Not in the paper: keeps x smooth in (s, a) on the batch's rows, so that the
        # action gradient of gradient (6) cannot come from a sharp ridge the critic drew
        # between the few expert pairs and the learner's nearby ones.
        penalty, penalty_grads = learner.critic.input_gradient_penalty(cache)
        loss += grad_penalty * penalty
        for name, grad in penalty_grads.items():
            grads[name] += grad_penalty * grad
    return float(loss), grads, cache


def with_input_noise(batch: Triplets, std: float, rng: np.random.Generator) -> Triplets:
    """The batch with N(0, std^2) added to its states and actions (--critic-input-noise).

    Not in the paper: "instance noise" (Sonderby et al. 2017) for the critic step only.
    With 400 sparse expert triplets QN may ring each of them with a narrow bump (on
    Hopper its mean q is 0.6-0.9 on expert pairs and 0.02-0.06 on replay pairs even while
    the policy scores the expert's return), and gradient (6) then follows the bumps'
    tails at the learner's states. Noise on both classes' inputs makes QN fit the
    smoothed distributions instead. The targets t are computed from the clean triplets;
    the actions may leave [-1, 1] by the noise. Measured on Hopper: worse (README).
    """
    return Triplets(
        states=batch.states + std * rng.standard_normal(batch.states.shape, np.float32),
        actions=batch.actions + std * rng.standard_normal(batch.actions.shape, np.float32),
        next_states=batch.next_states,
        terminal=batch.terminal,
    )


def critic_step(
    learner: Learner,
    expert_batch: Triplets,
    replay_batch: Triplets,
    config: Config,
    lr: float,
    rng: np.random.Generator,
) -> dict[str, float]:
    """One RMSProp step on objective (18), then the target update (Appendix B).

    With a learned reward (Ours+IRL): first a reward step on the same triplets
    (`reward_step`), then the critic step on objective (15) with the updated r_omega.
    """
    n = len(expert_batch.states)
    batch = Triplets(  # expert rows first, then replay rows: (2n, ...)
        *(
            np.concatenate([getattr(expert_batch, f.name), getattr(replay_batch, f.name)])
            for f in dataclasses.fields(Triplets)
        )
    )
    reward_stats = {} if learner.reward is None else reward_step(learner, batch, n, config, lr)
    from_replay = np.arange(len(batch.states)) >= n
    t = critic_targets(learner, batch, from_replay, config, rng)[:, None]  # (2n, 1)
    if config.critic_input_noise > 0:
        batch = with_input_noise(batch, config.critic_input_noise, rng)
    loss, grads, cache = critic_loss_and_grads(
        learner, batch, t, n, config.critic_reg, config.critic_grad_penalty
    )
    learner.critic_optimizer.step(learner.critic.params, grads, lr)
    nets.soft_update(learner.target_critic, learner.critic, config.tau)
    q = cache.output[:, 0]
    return {
        "critic_loss": loss,
        "q_expert": float(q[:n].mean()),
        "q_replay": float(q[n:].mean()),
        **reward_stats,
    }


def neg_log_q_action_gradient(critic: nets.MLP, states, actions, total_rows: int):
    """d(-sum_n log q(s_n, a_n) / total_rows)/da_n (N, dim A), the critic's part of
    gradient (6), and the critic's cache (logits (N, 1)). The critic stays fixed."""
    _, cache = critic.forward((states, actions))  # logits (N, 1)
    # d(-log q)/dx = -(1 - q) for q = sigmoid(x), Eq. (10), averaged over the rows.
    d_x = -nets.log_sigmoid_grad(cache.logits) / total_rows
    # The critic's action Jacobian, without its weight gradients.
    (_, d_actions), _ = critic.backward(
        d_x, cache, through_head=False, param_grads=False, input_grads=(False, True)
    )
    return d_actions, cache


def policy_gradient(learner: Learner, states: np.ndarray, noise: np.ndarray, total_rows: int):
    """Gradient (6) of -mean log q(s, pi(s, z)) w.r.t. PN's parameters, on one chunk.

    states: (B, dim s); noise: (B*Z, dim z), Z noise vectors per state; total_rows: the
    rows of the whole step, over which gradient (6) averages. Returns sums over the
    chunk's rows, so that chunks add up: (grads, loss, sum of q, (saturated action
    components, all action components)).
    """
    actions, policy_cache = learner.policy_forward(states, noise)  # (B*Z, dim A)
    d_actions, critic_cache = neg_log_q_action_gradient(learner.critic, states, actions, total_rows)
    log_q = nets.log_sigmoid(critic_cache.logits)  # Q = log q, Eq. (10)
    # Through tanh (or the Gaussian's reparameterisation) and PN.
    grads = learner.policy_backward(d_actions, policy_cache)
    saturated = (np.count_nonzero(np.abs(actions) > 0.99), actions.size)
    return grads, -float(log_q.sum()) / total_rows, float(critic_cache.output.sum()), saturated


def policy_loss_and_grads(learner: Learner, states: np.ndarray, noise: np.ndarray):
    """-E_{s, z}[log q(s, pi(s, z))] and gradient (6), over row chunks on both cores.

    states: (B, dim s); noise: (B*Z, dim z). Returns (loss, grads, stats).
    """
    z_per_state = len(noise) // len(states)

    def chunk(rows: slice):
        return policy_gradient(
            learner,
            states[rows],
            noise[rows.start * z_per_state : rows.stop * z_per_state],
            len(noise),
        )

    parts = nets.map_chunks(chunk, chunks_of(len(states), z_per_state))
    grads = {
        name: sum(p[0][name] for p in parts[1:]) + parts[0][0][name] for name in parts[0][0]
    }  # the chunks' partial sums, in a fixed order
    stats = {
        "q_policy": sum(p[2] for p in parts) / len(noise),
        # Fraction of all action components at the bound.
        "saturation": sum(p[3][0] for p in parts) / sum(p[3][1] for p in parts),
    }
    return sum(p[1] for p in parts), grads, stats


def policy_noise(
    learner: Learner, n_states: int, samples: int, rng: np.random.Generator
) -> np.ndarray:
    """z ~ N(0, I) for gradient (6): (n_states * Z, dim z), Z = `samples` consecutive rows
    per state (one for the deterministic policy)."""
    rows = n_states * learner.samples_per_state(samples)
    return rng.standard_normal((rows, learner.noise_dim), np.float32)


def policy_step(
    learner: Learner, replay_states: np.ndarray, config: Config, lr: float, rng: np.random.Generator
) -> dict[str, float]:
    """One RMSProp step on PN by gradient (6), over `noise_samples` z per state (one for
    the deterministic policy)."""
    noise = policy_noise(learner, len(replay_states), config.noise_samples, rng)
    _, grads, stats = policy_loss_and_grads(learner, replay_states, noise)
    learner.policy_optimizer.step(learner.policy.params, grads, lr)
    stats["policy_grad_norm"] = math.sqrt(sum(float((g * g).sum()) for g in grads.values()))
    return stats


def update(
    learner: Learner,
    expert_buffer: Triplets,
    replay: ReplayBuffer,
    config: Config,
    interactions: int,
    rng: np.random.Generator,
) -> dict[str, float]:
    """Algorithm 1, lines 11-14: a critic step, the target update and a policy step."""
    critic_lr = nets.linear_decay(config.critic_lr, interactions, config.total_steps)
    policy_lr = nets.linear_decay(config.policy_lr, interactions, config.total_steps)
    expert_batch = take(
        expert_buffer, rng.integers(0, len(expert_buffer.states), config.batch_size)
    )
    stats = critic_step(
        learner, expert_batch, replay.sample(rng, config.batch_size), config, critic_lr, rng
    )
    states = policy_states(expert_buffer, replay, config, rng)
    stats.update(policy_step(learner, states, config, policy_lr, rng))
    if learner.average_policy is not None:
        # Not in the paper: theta_avg <- rate theta + (1 - rate) theta_avg, like the
        # target critic's update. The relapses of the README are spells of a worse PN a
        # few thousand updates long; an average over a longer horizon may ride them out.
        nets.soft_update(learner.average_policy, learner.policy, config.policy_average)
    return stats


def policy_states(
    expert_buffer: Triplets, replay: ReplayBuffer, config: Config, rng: np.random.Generator
) -> np.ndarray:
    """The states of one policy step (batch_size, dim s)."""
    states = replay.sample(rng, config.batch_size).states  # line 13: a fresh batch
    n_expert = round(config.policy_expert_states * config.batch_size)
    if n_expert:  # a deviation from Alg. 1 (on by default, README): some states from B_pi_E
        expert_rows = rng.integers(0, len(expert_buffer.states), n_expert)
        states[:n_expert] = expert_buffer.states[expert_rows]
    return states


# ----------------------------------------------------------------------------------------
# Acting in the environment: one episode (Alg. 1, lines 4-9) and evaluation.
# ----------------------------------------------------------------------------------------


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

    Returns (true return, length). Only `terminated` ends the value chain; a time-limit
    truncation bootstraps like any other step.

    exploration_noise > 0 (a deviation, --exploration-noise): a_t + N(0, sigma^2 I) is
    executed and stored instead. The learned policy comes to ignore its noise input z
    as it matches the noise-free expert, and then the critic sees one action per
    visited state and cannot tell the policy which other action would do better there.

    An unbounded (Gaussian) action is clipped to [-1, 1] only on its way to the
    environment; the replay stores the action as sampled, so the critic sees what the
    policy chose (out-of-bound actions included), as GAIL's discriminator did in the
    paper's Gaussian baselines. For tanh actions the clip changes nothing.
    """
    observation, _ = env.reset(seed=seed)
    state = spaces.state(observation)
    episode_return, length, done = 0.0, 0, False
    while not done:
        noise = rng.standard_normal((1, learner.noise_dim), np.float32)
        action = learner.act(state[None], noise)[0]
        if exploration_noise > 0:
            action = action + exploration_noise * rng.standard_normal(action.shape, np.float32)
            if learner.policy_type != "gaussian":  # stay inside tanh's range
                action = np.clip(action, -1.0, 1.0)
        executed = spaces.to_env_action(np.clip(action, -1.0, 1.0))
        observation, reward, terminated, truncated, _ = env.step(executed)
        next_state = spaces.state(observation)
        episode_return, length, done = episode_return + reward, length + 1, terminated or truncated
        if replay is not None:
            if terminated and spaces.absorbing:
                # DAC: s_T leads to the absorbing state, which leads to itself.
                absorbing = spaces.absorbing_state()
                replay.add(state, action, absorbing, False)
                replay.add(absorbing, np.zeros_like(action), absorbing, False)
            else:
                replay.add(state, action, next_state, terminated)
        state = next_state
    return float(episode_return), length


def evaluate(env, learner: Learner, spaces: Spaces, config: Config, round_index: int):
    """True returns of the stochastic policy over `eval_episodes` seeded episodes, and
    how many of them fell (ended by termination, before the time limit).

    Evaluation has its own Generator (seeded from the run's seed and the round), so it
    never shifts the training noise: a run evaluated more often learns the same way.
    The fall count separates "one episode of five fell" from "every episode is worse",
    which the mean return alone cannot.
    """
    rng = np.random.default_rng([config.seed, 1, round_index])
    episodes = [
        run_episode(env, learner, spaces, rng, seed=10**6 + config.seed * 1000 + i)
        for i in range(config.eval_episodes)
    ]
    falls = sum(fell(env, length) for _, length in episodes)
    return np.array([episode_return for episode_return, _ in episodes]), falls


def fell(env, length: int) -> bool:
    """Did an episode of `length` steps end by termination, before the time limit?
    (Without a time limit nothing counts as a fall.)"""
    time_limit = env.spec.max_episode_steps if env.spec is not None else None
    return time_limit is not None and length < time_limit


def imitation_diagnostics(learner: Learner, expert_buffer: Triplets, rng) -> dict[str, float]:
    """How the policy and the critic see the expert's own states, at evaluation time.

    expert_action_error: mean squared distance between pi(s_E, z) and a_E (in [-1, 1]
    units); q_at_expert_action / q_at_policy_action: mean q(s_E, a_E) and q(s_E, pi(s_E, z));
    critic_input_grad: 1/2 mean ||dx/d[s, a]||^2 of the critic's logit x at (s_E, pi(s_E, z)),
    how sharp the critic is where gradient (6) reads it (the quantity that
    --critic-grad-penalty penalises); policy_noise_spread: the std of pi(s_E, z) over 8
    noise vectors z, averaged over states and action components, how much the policy
    still explores through z; policy_std (Gaussian policy only): mean sigma(s_E).
    """
    states = expert_buffer.states
    noise = rng.standard_normal((len(states), learner.noise_dim), np.float32)
    actions = learner.act(states, noise)
    q_expert, _ = learner.critic.forward((states, expert_buffer.actions))
    q_policy, policy_cache = learner.critic.forward((states, actions))
    z_per_state = 8  # each state is shared by 8 consecutive noise rows (policy_forward)
    spread_noise = rng.standard_normal((len(states) * z_per_state, learner.noise_dim), np.float32)
    spread_actions = learner.act(states, spread_noise).reshape(len(states), z_per_state, -1)
    return {
        "expert_action_error": float(((actions - expert_buffer.actions) ** 2).mean()),
        "q_at_expert_action": float(q_expert.mean()),
        "q_at_policy_action": float(q_policy.mean()),
        "critic_input_grad": learner.critic.input_gradient_penalty(policy_cache)[0],
        "policy_noise_spread": float(spread_actions.std(axis=1).mean()),
        **(
            {"policy_std": float(learner.policy_std(states).mean())}
            if learner.policy_type == "gaussian"
            else {}
        ),
    }


# ----------------------------------------------------------------------------------------
# The run: directory, progress file, checkpoints, and the main loop.
# ----------------------------------------------------------------------------------------

PROGRESS_FIELDS = (
    "interactions",
    "wall_seconds",
    "updates",
    "episodes",
    "eval_return_mean",
    "eval_return_std",
    "normalized_score",
    "train_return",
    "q_expert",
    "q_replay",
    "q_policy",
    "saturation",
    "critic_loss",
    "policy_grad_norm",
    "expert_action_error",
    "q_at_expert_action",
    "q_at_policy_action",
    # Added later: blank in the rows of runs started before them.
    "critic_input_grad",
    "policy_noise_spread",
    "eval_falls",  # evaluation episodes that ended before the time limit
)
# Columns that only an ablation writes, after the others (a default run's file keeps
# the columns above and nothing else).
REWARD_FIELDS = ("reward_loss", "r_expert", "r_replay")  # reward learning (Ours+IRL)
GAUSSIAN_FIELDS = ("policy_std",)  # the Gaussian policy (Ours+GP)
# The averaged PN's evaluation, on the same episode seeds as PN's (--policy-average).
AVERAGE_FIELDS = ("average_return_mean", "average_score", "average_falls")


def progress_fields(config: Config) -> tuple[str, ...]:
    """The columns of this run's progress.csv."""
    return (
        PROGRESS_FIELDS
        + (REWARD_FIELDS if config.reward_learning != "none" else ())
        + (GAUSSIAN_FIELDS if config.policy_type == "gaussian" else ())
        + (AVERAGE_FIELDS if config.policy_average > 0 else ())
    )


@dataclass
class Progress:
    """Counters that a checkpoint must restore, besides networks, buffer and Generator."""

    interactions: int = 0
    updates: int = 0
    episodes: int = 0
    eval_rounds: int = 0
    wall_seconds: float = 0.0
    best_eval_return: float = -math.inf
    recent_returns: list[float] = field(default_factory=list)  # since the last evaluation
    last_stats: dict[str, float] = field(default_factory=dict)  # of the latest update
    rows: list[dict] = field(default_factory=list)


SNAPSHOTS = "policies"  # policy_state() at each evaluation, named by its interactions


def snapshot_path(run_dir: Path, interactions: int) -> Path:
    return Path(run_dir) / SNAPSHOTS / f"{interactions:07d}.npz"


def rounded(value):
    """Counts as they are, measurements to 5 significant digits."""
    return value if isinstance(value, int) else float(f"{value:.5g}")


def progress_csv(rows: list[dict]) -> str:
    """PROGRESS_FIELDS, then any other column the rows hold, in their order."""
    fields = list(PROGRESS_FIELDS)
    fields += [name for name in (rows[0] if rows else {}) if name not in PROGRESS_FIELDS]
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


def save_checkpoint(
    run_dir: Path,
    learner: Learner,
    replay: ReplayBuffer,
    progress: Progress,
    rng: np.random.Generator,
) -> None:
    """Everything needed to continue exactly, in one atomic file; then progress.csv."""
    state = {**learner.state(), **replay.state()}
    nets.save_checkpoint(run_dir, state, rng, progress, progress_csv(progress.rows))


def load_checkpoint(
    run_dir: Path, learner: Learner, replay: ReplayBuffer, rng: np.random.Generator
) -> Progress:
    arrays, counters, rows = nets.load_checkpoint(run_dir, rng)
    learner.load_state(arrays)
    replay.load_state(arrays)
    return Progress(**counters, rows=rows)


def prepare(config: Config, env, rng: np.random.Generator):
    """The demonstrations (B_piE), the spaces, a fresh learner and an empty B_beta."""
    demo_path = (
        Path(config.demos)
        if config.demos
        else expert.ensure_demos(config.env, config.trajectories, config.sampling, config.demo_seed)
    )
    demos = expert.load_demos(demo_path, config.env)
    spaces = make_spaces(env, demos, config)
    expert_buffer = expert_buffer_from(demos, spaces)
    state_dim, action_dim = expert_buffer.states.shape[1], expert_buffer.actions.shape[1]
    env.action_space.seed(config.seed)
    learner = Learner.create(state_dim, env.observation_space.shape[0], action_dim, config, rng)
    replay = ReplayBuffer(config.replay_size, state_dim, action_dim)
    return spaces, expert_buffer, learner, replay


def checkpointed_config(run_dir) -> Config:
    """The settings of the run in run_dir, which must hold a checkpoint."""
    run_dir = Path(run_dir)
    try:
        saved = json.loads((run_dir / "config.json").read_text())
    except (OSError, ValueError):
        raise UserError(f"{run_dir} holds no run (config.json missing or unreadable)") from None
    if not (run_dir / "checkpoint.npz").exists():
        raise UserError(f"{run_dir} holds no checkpoint")
    return saved_config({**saved, "run_dir": str(run_dir)})


def restore(run_dir) -> tuple[Config, Spaces, Triplets, Learner, ReplayBuffer, Progress]:
    """A run as its last checkpoint left it (for looking into it, not for training)."""
    run_dir = Path(run_dir)
    config = checkpointed_config(run_dir)
    rng = np.random.default_rng(config.seed)
    spaces, expert_buffer, learner, replay = prepare(config, expert.make_env(config.env), rng)
    progress = load_checkpoint(run_dir, learner, replay, rng)
    return config, spaces, expert_buffer, learner, replay, progress


class Pace:
    """Interactions per second since this process started or resumed the run: a resumed
    run's earlier sessions may have run on a faster or slower machine, so their pace is
    not used for the log's rate and ETA."""

    def __init__(self, interactions: int, now: float | None = None):
        self.start = time.perf_counter() if now is None else now
        self.interactions = interactions

    def rate(self, interactions: int, now: float) -> float:
        return (interactions - self.interactions) / max(now - self.start, 1e-9)

    def eta_seconds(self, remaining: int, interactions: int, now: float) -> float:
        """Seconds left for `remaining` interactions; never negative (the last episode may
        run past the budget), NaN before this process has done any."""
        done = interactions - self.interactions
        if done <= 0:
            return float("nan")
        return max(remaining, 0) * (now - self.start) / done


def train(config: Config, resume: bool = False) -> Progress:
    """Algorithm 1, with evaluation, logging and checkpoints around it."""
    check_config(config)
    run_dir = Path(config.run_dir or f"runs/{config.env}-seed{config.seed}")
    if not resume and (run_dir / "checkpoint.npz").exists():
        raise UserError(
            f"{run_dir} already holds a run; continue it with --resume {run_dir}"
            " or choose another --run-dir"
        )
    env, eval_env = expert.make_env(config.env), expert.make_env(config.env)
    references = expert.references_or_nan(config.env)
    rng = np.random.default_rng(config.seed)  # the run's one Generator, passed explicitly
    spaces, expert_buffer, learner, replay = prepare(config, env, rng)
    run_dir.mkdir(parents=True, exist_ok=True)
    if resume:
        progress = load_checkpoint(run_dir, learner, replay, rng)
        print(f"resumed {run_dir} at {progress.interactions} interactions", flush=True)
    else:
        progress = Progress()
        nets.write_text(
            run_dir / "config.json", json.dumps(dataclasses.asdict(config), indent=2) + "\n"
        )

    started = time.perf_counter() - progress.wall_seconds
    last_checkpoint = last_log = time.perf_counter()
    pace = Pace(progress.interactions)
    while True:
        recent_returns, stats = progress.recent_returns, progress.last_stats
        # Evaluate at 0 and every eval_every interactions (at the episode end that crosses it).
        evaluated_here = bool(progress.rows) and (
            progress.rows[-1]["interactions"] == progress.interactions
        )  # true when resuming a run that had already finished
        due = progress.interactions >= progress.eval_rounds * config.eval_every
        if not evaluated_here and (due or progress.interactions >= config.total_steps):
            returns, falls = evaluate(eval_env, learner, spaces, config, progress.eval_rounds)
            diagnostics = imitation_diagnostics(
                learner,
                expert_buffer,
                np.random.default_rng([config.seed, 2, progress.eval_rounds]),
            ) | {"eval_falls": falls}
            if learner.average_policy is not None:
                average_returns, average_falls = evaluate(
                    eval_env, learner.averaged(), spaces, config, progress.eval_rounds
                )
                average_return = float(average_returns.mean())
                diagnostics |= {
                    "average_return_mean": round(average_return, 2),
                    "average_score": expert.normalized_score(average_return, references),
                    "average_falls": average_falls,
                }
            progress.eval_rounds += 1
            progress.wall_seconds = time.perf_counter() - started
            row = {
                "interactions": progress.interactions,
                "wall_seconds": round(progress.wall_seconds, 1),
                "updates": progress.updates,
                "episodes": progress.episodes,
                "eval_return_mean": round(float(returns.mean()), 2),
                "eval_return_std": round(float(returns.std()), 2),
                "normalized_score": round(
                    expert.normalized_score(float(returns.mean()), references), 4
                ),
                "train_return": round(float(np.mean(recent_returns)), 2) if recent_returns else "",
                **{
                    k: rounded(value[k]) if k in value else ""
                    for k in progress_fields(config)[8:]
                    for value in [{**stats, **diagnostics}]
                },
            }
            progress.rows.append(row)
            recent_returns.clear()
            # Every evaluated policy is kept (tens of kB each), so that one evaluation's
            # five episodes can be checked later on many more (experiments.py evaluate).
            policy = learner.policy_state()
            (run_dir / SNAPSHOTS).mkdir(exist_ok=True)
            nets.save_arrays(snapshot_path(run_dir, progress.interactions), policy)
            if returns.mean() > progress.best_eval_return:
                progress.best_eval_return = float(returns.mean())
                nets.save_arrays(run_dir / "policy_best.npz", policy)
            if learner.average_policy is not None:  # the latest averaged PN
                nets.save_arrays(run_dir / "policy_average.npz", learner.averaged().policy_state())
            print(
                f"eval  {progress.interactions:>8d} steps  return {returns.mean():8.1f}"
                f" ± {returns.std():6.1f}  score {row['normalized_score']:6.3f}"
                f"  q_E {stats.get('q_expert', math.nan):.3f}"
                f"  q_B {stats.get('q_replay', math.nan):.3f}"
                f"  sat {stats.get('saturation', math.nan):.2f}"
                f"  |pi(s_E)-a_E|^2 {diagnostics['expert_action_error']:.3f}"
                + (f"  averaged PN {row['average_score']:6.3f}" if "average_score" in row else ""),
                flush=True,
            )
            save_checkpoint(run_dir, learner, replay, progress, rng)
            last_checkpoint = time.perf_counter()
        if progress.interactions >= config.total_steps:
            break

        # Alg. 1, lines 4-9: one episode with the current policy.
        seed = int(rng.integers(2**31))
        episode_return, length = run_episode(
            env, learner, spaces, rng, seed, replay, config.exploration_noise
        )
        recent_returns.append(episode_return)
        progress.episodes += 1
        # Lines 10-15: as many updates as the episode had steps.
        update_start = time.perf_counter()
        for _ in range(length):
            stats = progress.last_stats = update(
                learner, expert_buffer, replay, config, progress.interactions, rng
            )
            progress.updates += 1
        if config.on_policy:
            # Ours+OnP: the buffer is to hold samples of the current policy only. Once
            # this episode's updates have moved theta, its triplets are another policy's,
            # so they go, and the next updates sample the next episode's triplets alone.
            # Emptying here (not before the episode) keeps exactly Algorithm 1 otherwise:
            # the same episode, the same number of updates, the same batch sizes (drawn
            # with replacement from one episode). Within the episode's updates the
            # triplets are slightly off-policy already, as in any on-policy method that
            # takes several steps per batch (PPO's epochs). A run that is checkpointed
            # here saves an empty buffer, which is what it resumes with.
            replay.clear()
        update_seconds = time.perf_counter() - update_start
        progress.interactions += length

        now = time.perf_counter()
        progress.wall_seconds = now - started
        if now - last_log >= config.log_every:
            eta = pace.eta_seconds(
                config.total_steps - progress.interactions, progress.interactions, now
            )
            score = expert.normalized_score(episode_return, references)
            print(
                f"train {progress.interactions:>8d} steps  return {episode_return:8.1f}"
                f" ({length:4d} steps)  score {score:6.3f}"
                f"  {length / max(update_seconds, 1e-9):5.1f} updates/s"
                f"  ETA {eta / 60:6.1f} min",
                flush=True,
            )
            last_log = now
        if nets.checkpoint_due(now - last_checkpoint, config.checkpoint_every):
            save_checkpoint(run_dir, learner, replay, progress, rng)
            last_checkpoint = now
            nets.stop_if_requested()

    nets.save_arrays(run_dir / "policy_final.npz", learner.policy_state())
    return progress


# ----------------------------------------------------------------------------------------
# Command line, generated from Config.
# ----------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = expert.CommandLineParser(
        description="Off-policy actor-critic imitation learning (Sasaki et al., ICLR 2019).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    expert.add_dataclass_flags(parser, Config)
    parser.add_argument(
        "--paper",
        action="store_true",
        help="Appendix B's values where the defaults deviate ("
        + ", ".join(f"--{k.replace('_', '-')} {v:g}" for k, v in PAPER_SETTINGS.items())
        + "); flags given explicitly still win",
    )
    parser.add_argument(
        "--resume",
        metavar="RUN_DIR",
        default="",
        help="continue the run in RUN_DIR from its last checkpoint, with its "
        "saved settings (other flags are ignored)",
    )
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.paper:  # Appendix B's values become the defaults; explicit flags still win
        parser.set_defaults(**PAPER_SETTINGS)
        args = parser.parse_args(argv)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        if args.resume:
            config = checkpointed_config(args.resume)
        else:
            config = Config(
                **{
                    f.name: (tuple(v) if isinstance(v, list) else v)
                    for f in dataclasses.fields(Config)
                    for v in [getattr(args, f.name)]
                }
            )
        # BLAS threads off: the threads come from map_chunks.
        with threadpool_limits(limits=1, user_api="blas"), nets.stop_at_next_checkpoint():
            train(config, resume=bool(args.resume))
    except UserError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; continue with --resume", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
