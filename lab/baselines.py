"""The paper's baselines, in NumPy: behavioural cloning (BC), GAIL and BC+GAIL.

Sasaki, Yohira & Kawaguchi (ICLR 2019), Sec. 5, compare their method with BC, GAIL
(Ho & Ermon, "Generative Adversarial Imitation Learning", NeurIPS 2016) and GAIL whose
policy starts from BC, all from the openai/imitation code. Here:

- BC: a Gaussian policy pi(a|s) = N(mu(s), diag sigma^2), mu an MLP (100-100, identity
  head) and log sigma a learned state-independent vector (as in openai/imitation),
  fitted by maximum likelihood to the demonstrations' (s, a) pairs in [-1, 1] action
  units, with early stopping on a held-out split.
- GAIL: the same policy, a value MLP and a discriminator MLP D(s, a) (100-100, sigmoid
  head, logistic loss). The policy step is **PPO with GAE** (Schulman et al. 2017; 2016),
  as in today's reference libraries (stable-baselines3 + HumanCompatibleAI/imitation),
  **not TRPO** as in Ho & Ermon and the paper. Reward r(s, a) = -log(1 - D(s, a)), D the
  probability that (s, a) is the expert's (Ho & Ermon's cost log D_pi with D_pi = 1 - D).
  It is always positive, so it also pays for staying alive: on tasks that end at a fall
  (Hopper) it favours long episodes, as Ho & Ermon's and openai/imitation's GAIL did.
- BC+GAIL: GAIL whose policy (mean network and log sigma) starts from a BC run
  (`bc-gail --bc-init BC_RUN_DIR`).

What is shared with the learner (offpac_il.py), not copied: environments, demonstrations
and reference returns (expert.py); action scaling and state standardisation by the
demonstrations' statistics (`offpac_il.Spaces`, `make_spaces`); whole episodes and
seeded evaluation (`offpac_il.run_episode`, `offpac_il.evaluate`: both need only an
object whose `policy` has `act(states, noise)` and `noise_dim`, as the agents here do);
the progress file's columns (`offpac_il.PROGRESS_FIELDS`); the discriminator's loss
(`lab.ablations.reward_loss_and_grads`, the learner's reward-learning ablation); the MLP
(nets.py); and the run directory, its progress rows and checkpoint, the command line and
one-line errors (harness.py).

Actions: the Gaussian is unbounded. Its sample a = mu + sigma * noise is what the
likelihood and the PPO ratio are taken of; the environment gets clip(a, -1, 1) mapped to
its bounds (as stable-baselines3 does), and the discriminator sees that clipped action,
because the expert's actions are in [-1, 1] too (`GaussianSpaces`).

The networks use nets.MLP's leaky-ReLU hidden units (one MLP type for the whole project),
where openai/imitation used tanh.

From the repository root, run `python -m lab.baselines bc --env Hopper-v4`, then
`python -m lab.baselines gail --env Hopper-v4` and
`python -m lab.baselines bc-gail --env Hopper-v4 --bc-init runs/bc-Hopper-v4-seed0`;
`python -m lab.baselines METHOD --help` lists every setting.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

import expert
import harness
import nets
import offpac_il
from harness import UserError
from lab import ablations, optim

LOG_2PI = float(np.log(2.0 * np.pi))

# ----------------------------------------------------------------------------------------
# Settings. Each method's command line is generated from its dataclass: one flag per
# field, the field's docstring as its help.
# ----------------------------------------------------------------------------------------


@dataclass
class RunSettings(offpac_il.RunConfig):
    """Settings every baseline shares: the learner's (task, demonstrations, evaluation, run
    directory), and the Gaussian policy's size."""

    policy_hidden: tuple[int, ...] = (100, 100)
    """Hidden layer sizes of the Gaussian policy's mean network."""


@dataclass
class BCConfig(RunSettings):
    """Behavioural cloning: maximum likelihood on the demonstrations' (s, a) pairs."""

    total_steps: int = 20_000
    """Gradient steps at most (BC never interacts with the environment)."""
    eval_every: int = 250
    """Gradient steps between evaluations (validation likelihood and episodes)."""
    lr: float = 1e-3
    """Adam learning rate."""
    batch_size: int = 64
    """Demonstration pairs per gradient step."""
    validation_fraction: float = 0.3
    """Fraction of the demonstration pairs held out for early stopping."""
    patience: int = 20
    """Stop after this many evaluations without a better validation likelihood."""
    log_std_init: float = 0.0
    """Initial log sigma of every action dimension, in [-1, 1] action units."""


@dataclass
class GAILConfig(RunSettings):
    """GAIL (Ho & Ermon 2016) with PPO + GAE in place of TRPO."""

    total_steps: int = 3_000_000
    """Interaction budget (environment steps)."""
    eval_every: int = 50_000
    """Interactions between evaluations."""
    bc_init: str = ""
    """BC+GAIL: a finished BC run directory whose final policy starts the policy."""
    # BC fits sigma to noise-free demonstrations (log sigma -3.7 to -4.8 on Hopper):
    # PPO started there has almost no exploration noise, and it unlearned (README).
    bc_reset_log_std: bool = False
    """BC+GAIL: start log sigma at log_std_init, not at the BC policy's (the default
    starts from the whole BC policy: the paper's "GAIL initialized by BC")."""
    value_hidden: tuple[int, ...] = (100, 100)
    """Hidden layer sizes of the value network V(s)."""
    discriminator_hidden: tuple[int, ...] = (100, 100)
    """Hidden layer sizes of the discriminator D(s, a)."""
    log_std_init: float = 0.0
    """Initial log sigma of every action dimension, in [-1, 1] action units."""
    rollout_steps: int = 2048
    """Interactions per iteration, as whole episodes (at least this many)."""
    ppo_epochs: int = 10
    """Passes of PPO over each iteration's rollout."""
    minibatch_size: int = 64
    """Rollout steps per PPO minibatch."""
    policy_lr: float = 3e-4
    """Adam learning rate of the policy (mean network and log sigma)."""
    value_lr: float = 3e-4
    """Adam learning rate of the value network."""
    clip_range: float = 0.2
    """PPO's epsilon: the ratio pi/pi_old is clipped to [1 - eps, 1 + eps]."""
    # Without it, Hopper's policy moved by KL 0.1-4 per iteration once its sigma had
    # shrunk, and BC+GAIL's first iteration (KL 18) undid the BC policy (README).
    target_kl: float = 0.01
    """Stop an iteration's PPO epochs at a minibatch whose KL(pi_old || pi) exceeds
    1.5 x this (Spinning Up's rule; TRPO's step in the GAIL code is KL 0.01); 0: never."""
    # A config.json from before target_kl existed ran without the KL stop.
    settings_before_they_existed: ClassVar[dict] = {"target_kl": 0.0}
    entropy_coef: float = 0.0
    """Weight of the policy's entropy bonus."""
    max_grad_norm: float = 0.5
    """Each network's gradient is rescaled to at most this global norm."""
    gamma: float = 0.99
    """Discount factor of the GAIL reward."""
    gae_lambda: float = 0.95
    """GAE's lambda."""
    discriminator_lr: float = 3e-4
    """Adam learning rate of the discriminator."""
    discriminator_steps: int = 10
    """Discriminator steps per iteration, each on fresh policy and expert minibatches."""
    discriminator_batch: int = 128
    """Policy pairs and expert pairs (each) per discriminator step."""


def check_config(config: RunSettings) -> None:
    """Refuse settings that cannot work (NaN anywhere, a count below 1, ...), in one line."""
    harness.check_choices(config, {"sampling": expert.SAMPLING_MODES})
    counts = ("trajectories", "total_steps", "eval_every", "eval_episodes", "batch_size")
    counts += ("patience", "rollout_steps", "ppo_epochs", "minibatch_size", "policy_hidden")
    counts += ("value_hidden", "discriminator_hidden", "discriminator_steps")
    counts += ("discriminator_batch",)
    positive = ("lr", "policy_lr", "value_lr", "discriminator_lr", "clip_range", "max_grad_norm")
    at_least_0 = ("seed", "demo_seed", "checkpoint_every", "log_every", "target_kl")
    harness.check_numbers(
        config,
        {name: (1, math.inf, "[)") for name in counts}
        | {name: (0, math.inf, "()") for name in positive}
        | {name: (0, math.inf, "[)") for name in (*at_least_0, "entropy_coef")}
        | {"validation_fraction": (0, 1, "()"), "gamma": (0, 1, "[)"), "gae_lambda": (0, 1, "[]")},
    )


# ----------------------------------------------------------------------------------------
# The Gaussian policy and its log-likelihood, each derivative beside its forward.
# ----------------------------------------------------------------------------------------


def gaussian_log_prob(actions: np.ndarray, mean: np.ndarray, log_std: np.ndarray):
    """log N(a; mu, diag sigma^2) per row, with its derivatives per row and dimension.

        log pi(a|s) = sum_i [ -(a_i - mu_i)^2 / (2 sigma_i^2) - log sigma_i - log(2 pi)/2 ]
        d log pi / d mu_i       = (a_i - mu_i) / sigma_i^2
        d log pi / d log sigma_i = (a_i - mu_i)^2 / sigma_i^2 - 1

    actions, mean: (N, dim A); log_std: (dim A,). Returns (log_prob (N,),
    d_mean (N, dim A), d_log_std (N, dim A)).
    """
    std = np.exp(log_std)  # (dim A,)
    z = (actions - mean) / std  # (N, dim A): the standardised residual
    log_prob = -0.5 * (z * z).sum(axis=1) - log_std.sum() - 0.5 * LOG_2PI * actions.shape[1]
    return log_prob, z / std, z * z - 1.0


@dataclass
class GaussianPolicy:
    """pi(a|s) = N(mu(s), diag exp(log_std)^2): mu an identity-head MLP, log_std a vector.

    `act(states, noise)` and `noise_dim` are what offpac_il.run_episode and
    offpac_il.evaluate call (as `agent.policy`), so it rolls out exactly like the learner's.
    """

    mean_net: nets.MLP
    log_std: np.ndarray  # (dim A,)

    @classmethod
    def create(cls, state_dim, action_dim, hidden, log_std_init, rng, dtype=np.float32):
        mean_net = nets.MLP.create([state_dim, *hidden, action_dim], "identity", rng, dtype)
        return cls(mean_net, np.full(action_dim, log_std_init, dtype))

    @property
    def noise_dim(self) -> int:
        return len(self.log_std)

    @property
    def params(self) -> dict[str, np.ndarray]:
        """Every parameter by name; the arrays themselves, so an optimiser moves them."""
        return {**self.mean_net.params, "log_std": self.log_std}

    def act(self, states: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """a = mu(s) + sigma * noise, noise ~ N(0, I): a sample of pi(.|s), unclipped."""
        mean, _ = self.mean_net.forward(states)  # (N, dim A)
        return mean + np.exp(self.log_std) * noise

    def log_prob(self, states: np.ndarray, actions: np.ndarray):
        """log pi(a|s) per row (N,), and the cache that `backward` needs."""
        mean, net_cache = self.mean_net.forward(states)  # (N, dim A)
        log_prob, d_mean, d_log_std = gaussian_log_prob(actions, mean, self.log_std)
        return log_prob, (net_cache, d_mean, d_log_std)

    def backward(self, d_log_prob: np.ndarray, cache) -> dict[str, np.ndarray]:
        """Gradients of a loss L from d_log_prob = dL/d log pi(a_n|s_n), shape (N,)."""
        net_cache, d_mean, d_log_std = cache
        weights = np.asarray(d_log_prob, dtype=self.log_std.dtype)[:, None]  # (N, 1)
        _, grads = self.mean_net.backward(weights * d_mean, net_cache, input_grads=False)
        grads["log_std"] = (weights * d_log_std).sum(axis=0)  # (dim A,)
        return grads

    def entropy(self) -> float:
        """H(pi(.|s)) = sum_i log sigma_i + dim A (1 + log 2 pi)/2; dH/d log sigma_i = 1."""
        return float(self.log_std.sum() + 0.5 * len(self.log_std) * (1.0 + LOG_2PI))

    def copy(self) -> GaussianPolicy:
        return GaussianPolicy(self.mean_net.copy(), self.log_std.copy())

    def state(self, prefix: str) -> dict[str, np.ndarray]:
        return {**self.mean_net.state(prefix), f"{prefix}/log_std": self.log_std}

    def load_state(self, arrays, prefix: str) -> None:
        self.mean_net.load_state(arrays, prefix)
        self.log_std[...] = arrays[f"{prefix}/log_std"]


class GaussianSpaces(offpac_il.Spaces):
    """The learner's Spaces, for an unbounded policy: clip(a, -1, 1) before the mapping
    to the environment's bounds (the likelihood is of the unclipped sample)."""

    def to_env_action(self, action: np.ndarray) -> np.ndarray:
        return super().to_env_action(np.clip(action, -1.0, 1.0))


# ----------------------------------------------------------------------------------------
# Optimiser: PPO and BC as published use Adam (lab/optim.py, shared with lab/sac.py).
# ----------------------------------------------------------------------------------------


def clip_global_norm(grads: dict[str, np.ndarray], max_norm: float) -> float:
    """Rescale `grads` in place to a global L2 norm of at most max_norm; return the norm
    before rescaling."""
    norm = float(np.sqrt(sum(float((g * g).sum()) for g in grads.values())))
    if norm > max_norm:
        for g in grads.values():
            g *= max_norm / norm
    return norm


# ----------------------------------------------------------------------------------------
# BC: maximum likelihood on the demonstrations.
# ----------------------------------------------------------------------------------------


def bc_loss_and_grads(policy: GaussianPolicy, states: np.ndarray, actions: np.ndarray):
    """L = -mean_n log pi(a_n|s_n) over demonstration pairs, and dL/d(every parameter)."""
    log_prob, cache = policy.log_prob(states, actions)
    n = len(states)
    return -float(log_prob.mean()), policy.backward(np.full(n, -1.0 / n), cache)


# ----------------------------------------------------------------------------------------
# GAIL: discriminator, reward, GAE, PPO.
# ----------------------------------------------------------------------------------------


def discriminator_loss_and_grads(
    discriminator: nets.MLP,
    expert_states: np.ndarray,
    expert_actions: np.ndarray,
    policy_states: np.ndarray,
    policy_actions: np.ndarray,
):
    """Logistic loss of D(s, a) = sigmoid(x(s, a)), the probability that (s, a) is the
    expert's (Ho & Ermon 2016, Eq. 17, with D labelling the expert 1):

        L = -mean_E log D(s, a) - mean_pi log(1 - D(s, a))
          = mean_E softplus(-x) + mean_pi softplus(x)
        dL/dx = -sigmoid(-x) / N_E on expert rows,  sigmoid(x) / N_pi on policy rows.

    The learner's reward-learning ablation trains its r_omega with the same loss, so both
    share one implementation: ablations.reward_loss_and_grads(..., "discriminator").
    Returns (loss, grads, {"d_expert", "d_policy"}: mean D on each side).
    """
    n_expert = len(expert_states)
    states = np.concatenate([expert_states, policy_states])  # (N_E + N_pi, dim s)
    actions = np.concatenate([expert_actions, policy_actions])  # (N_E + N_pi, dim A)
    loss, grads, cache = ablations.reward_loss_and_grads(
        discriminator, states, actions, n_expert, "discriminator"
    )
    d = cache.output[:, 0]
    return (
        loss,
        grads,
        {"d_expert": float(d[:n_expert].mean()), "d_policy": float(d[n_expert:].mean())},
    )


def gail_reward(discriminator: nets.MLP, states: np.ndarray, actions: np.ndarray):
    """r(s, a) = -log(1 - D(s, a)) = softplus(x(s, a)), from the logit (exact when D -> 1)."""
    _, cache = discriminator.forward((states, actions))
    return nets.softplus(cache.logits[:, 0])  # (N,)


def gae(rewards, values, next_values, terminal, episode_end, gamma: float, lam: float):
    """Generalised advantage estimates (Schulman et al. 2016, Eq. 16), one pass backwards:

        delta_t = r_t + gamma (1 - terminal_t) V(s_{t+1}) - V(s_t)
        A_t     = delta_t + gamma lam (1 - end_t) A_{t+1}

    terminal_t: s_{t+1} is terminal (a fall), so nothing follows it; end_t: the episode
    ends at t, by a fall or by the time limit. A time-limit end still bootstraps from
    V(s_{t+1}) in delta_t (a time limit is not a fall), but the sum A_t stops there.
    All arrays (T,).
    """
    advantages = np.zeros(len(rewards), np.float64)
    following = 0.0  # A_{t+1}
    for t in reversed(range(len(rewards))):
        delta = rewards[t] + gamma * (1.0 - terminal[t]) * next_values[t] - values[t]
        following = delta + gamma * lam * (1.0 - episode_end[t]) * following
        advantages[t] = following
    return advantages


def ppo_policy_loss_and_grads(
    policy: GaussianPolicy,
    states: np.ndarray,
    actions: np.ndarray,
    old_log_prob: np.ndarray,
    advantages: np.ndarray,
    clip_range: float,
    entropy_coef: float = 0.0,
):
    """PPO's clipped surrogate (Schulman et al. 2017, Eq. 7), as a loss to minimise:

        rho_n = pi(a_n|s_n) / pi_old(a_n|s_n) = exp(log pi - log pi_old)
        L = -mean_n min(rho_n A_n, clip(rho_n, 1 - eps, 1 + eps) A_n) - c_H H(pi)

    d min / d log pi = rho A where the unclipped term is the smaller (inside the clip
    range both terms are rho A), and 0 where the clipped term, constant in the
    parameters, is: A > 0 with rho > 1 + eps, or A < 0 with rho < 1 - eps.
    Returns (loss, grads, {"clip_fraction", "approx_kl"}).
    """
    log_prob, cache = policy.log_prob(states, actions)
    ratio = np.exp(log_prob - old_log_prob)  # (N,)
    unclipped = ratio * advantages
    clipped = np.clip(ratio, 1.0 - clip_range, 1.0 + clip_range) * advantages
    n = len(states)
    loss = -float(np.minimum(unclipped, clipped).mean()) - entropy_coef * policy.entropy()
    d_log_prob = -np.where(unclipped <= clipped, unclipped, 0.0) / n  # (N,)
    grads = policy.backward(d_log_prob, cache)
    grads["log_std"] -= entropy_coef  # dH/d log sigma_i = 1
    stats = {
        "clip_fraction": float((unclipped > clipped).mean()),
        # KL(pi_old || pi) estimated as mean((rho - 1) - log rho) >= 0 (as SB3 does).
        "approx_kl": float(((ratio - 1.0) - (log_prob - old_log_prob)).mean()),
    }
    return loss, grads, stats


def value_loss_and_grads(value_net: nets.MLP, states: np.ndarray, returns: np.ndarray):
    """L = 1/2 mean_n (V(s_n) - R_n)^2, R_n = A_n + V_old(s_n) (the GAE return);
    dL/dV(s_n) = (V(s_n) - R_n) / N."""
    values, cache = value_net.forward(states)  # (N, 1)
    error = values[:, 0] - returns  # (N,)
    _, grads = value_net.backward((error / len(states))[:, None], cache, input_grads=False)
    return 0.5 * float((error * error).mean()), grads


# ----------------------------------------------------------------------------------------
# Rollouts: offpac_il.run_episode stores each step through `add`, as into the replay.
# ----------------------------------------------------------------------------------------


class Rollout:
    """One GAIL iteration's steps, whole episodes, in order (s, a unclipped, s', terminal)."""

    def __init__(self):
        self.steps: list[tuple] = []
        self.ends: list[int] = []  # index of each episode's last step

    def add(self, state, action, next_state, terminal: bool) -> None:
        self.steps.append((state, action, next_state, terminal))

    def end_episode(self) -> None:
        self.ends.append(len(self.steps) - 1)

    def __len__(self) -> int:
        return len(self.steps)

    def arrays(self):
        """states (T, dim s), actions (T, dim A), next_states (T, dim s), terminal (T,),
        episode_end (T,), the last two as floats."""
        states, actions, next_states, terminal = (
            np.array(column) for column in zip(*self.steps, strict=True)
        )
        episode_end = np.zeros(len(self.steps))
        episode_end[self.ends] = 1.0
        return states, actions, next_states, terminal.astype(np.float64), episode_end


# ----------------------------------------------------------------------------------------
# What a checkpoint holds for each method (Run.checkpoint saves `state`).
# ----------------------------------------------------------------------------------------


@dataclass
class BCAgent:
    policy: GaussianPolicy
    optimizer: optim.Adam
    best_policy: GaussianPolicy  # the parameters with the best validation likelihood
    best_validation_nll: float = math.inf
    best_update: int = 0
    evaluations_since_best: int = 0
    diagnostics: list[dict] = field(default_factory=list)

    def state(self) -> dict[str, np.ndarray]:
        early_stopping = [self.best_validation_nll, self.best_update, self.evaluations_since_best]
        return {
            **self.policy.state("policy"),
            **self.best_policy.state("best_policy"),
            **self.optimizer.state("adam"),
            "early_stopping": np.array(json.dumps(early_stopping)),
            "diagnostics": np.array(json.dumps(self.diagnostics)),
        }

    def load_state(self, arrays) -> None:
        self.policy.load_state(arrays, "policy")
        self.best_policy.load_state(arrays, "best_policy")
        self.optimizer.load_state(arrays, "adam")
        best, update, since = json.loads(str(arrays["early_stopping"]))
        self.best_validation_nll, self.best_update, self.evaluations_since_best = (
            best,
            update,
            since,
        )
        self.diagnostics = json.loads(str(arrays["diagnostics"]))


@dataclass
class GAILAgent:
    policy: GaussianPolicy
    value: nets.MLP
    discriminator: nets.MLP
    policy_optimizer: optim.Adam = field(default_factory=optim.Adam)
    value_optimizer: optim.Adam = field(default_factory=optim.Adam)
    discriminator_optimizer: optim.Adam = field(default_factory=optim.Adam)
    diagnostics: list[dict] = field(default_factory=list)

    def state(self) -> dict[str, np.ndarray]:
        return {
            **self.policy.state("policy"),
            **self.value.state("value"),
            **self.discriminator.state("discriminator"),
            **self.policy_optimizer.state("policy_adam"),
            **self.value_optimizer.state("value_adam"),
            **self.discriminator_optimizer.state("discriminator_adam"),
            "diagnostics": np.array(json.dumps(self.diagnostics)),
        }

    def load_state(self, arrays) -> None:
        self.policy.load_state(arrays, "policy")
        self.value.load_state(arrays, "value")
        self.discriminator.load_state(arrays, "discriminator")
        self.policy_optimizer.load_state(arrays, "policy_adam")
        self.value_optimizer.load_state(arrays, "value_adam")
        self.discriminator_optimizer.load_state(arrays, "discriminator_adam")
        self.diagnostics = json.loads(str(arrays["diagnostics"]))


# ----------------------------------------------------------------------------------------
# The run: setup, evaluation rows and checkpoints, shared by both training loops.
# ----------------------------------------------------------------------------------------

BC_DIAGNOSTICS = ("updates", "validation_nll", "train_nll", "mean_log_std", "best_update")
GAIL_DIAGNOSTICS = (
    "interactions",
    "discriminator_loss",
    "d_expert",
    "d_policy",
    "reward_mean",
    "value_loss",
    "approx_kl",
    "clip_fraction",
    "entropy",
    "mean_log_std",
)


def method_of(config: RunSettings) -> str:
    if isinstance(config, BCConfig):
        return "bc"
    return "bc-gail" if config.bc_init else "gail"


@dataclass
class Run:
    """What both loops need around their updates: environment, demonstrations in the
    networks' units, reference returns, the progress counters and the run directory."""

    config: RunSettings
    run_dir: Path
    env: object
    spaces: GaussianSpaces
    expert_states: np.ndarray  # (n, dim s), standardised
    expert_actions: np.ndarray  # (n, dim A), in [-1, 1]
    random_return: float
    expert_return: float
    progress: harness.Progress = field(default_factory=harness.Progress)
    rng: np.random.Generator | None = None  # the run's one Generator, set by `start`
    clock: harness.Clock | None = None  # wall time, log and checkpoint pacing, by `start`
    demos_sha256: str | None = None  # recorded in config.json: a resume checks its file

    @classmethod
    def open(cls, config: RunSettings, resume: bool) -> Run:
        """Check everything a user can get wrong before writing anything."""
        check_config(config)
        method = method_of(config)
        run_dir = Path(config.run_dir or f"runs/{method}-{config.env}-seed{config.seed}")
        env = expert.make_env(config.env)
        demos = expert.run_demos(config, resume)
        print(demos.describe(), flush=True)
        random_return, expert_return = expert.references_or_nan(config.env, demos)
        # The learner's own state standardisation and action scaling (absorbing: never).
        learner_spaces = offpac_il.make_spaces(
            env, demos, offpac_il.Config(standardize=config.standardize, termination="zero")
        )
        spaces = GaussianSpaces(
            **{f.name: getattr(learner_spaces, f.name) for f in dataclasses.fields(learner_spaces)}
        )
        return cls(
            config,
            run_dir,
            env,
            spaces,
            spaces.state(demos.observations),
            spaces.from_env_action(demos.actions),
            random_return,
            expert_return,
            demos_sha256=demos.sha256,
        )

    def start(self, agent, rng: np.random.Generator, resume: bool) -> None:
        """Open (check, create, lock) the run directory once everything else is known to
        be right, and write config.json, or restore the checkpoint."""
        self.rng = rng
        harness.open_run_dir(self.run_dir, resume)
        if resume:
            self.progress = harness.load_checkpoint(self.run_dir, rng, agent.load_state)
            print(f"resumed {self.run_dir} at {self.progress.updates} updates", flush=True)
        else:
            method = method_of(self.config)
            settings = {"method": method, harness.PROGRAM: f"python -m lab.baselines {method}"}
            settings |= {expert.DEMOS_SHA256: self.demos_sha256, **dataclasses.asdict(self.config)}
            harness.write_config(self.run_dir, settings)
        config = self.config
        self.clock = harness.Clock(self.progress, config.checkpoint_every, config.log_every)

    def normalized(self, value: float) -> float:
        return expert.normalized_score(value, (self.random_return, self.expert_return))

    def evaluate(self, agent, measured: dict) -> dict:
        """Evaluate agent.policy (offpac_il.evaluate: seeded episodes, their own
        Generator), append a progress row and a diagnostics row, keep the best policy,
        checkpoint.

        measured: the latest training numbers; those named in PROGRESS_FIELDS go to
        progress.csv, the method's own (BC_DIAGNOSTICS, GAIL_DIAGNOSTICS) to
        diagnostics.csv. Returns the progress row.
        """
        progress, config, policy = self.progress, self.config, agent.policy
        returns, falls = offpac_il.evaluate(
            self.env, agent, self.spaces, config, progress.eval_rounds
        )
        # How the policy acts on the expert's own states (as the learner's rows record).
        rng = np.random.default_rng([config.seed, 2, progress.eval_rounds])
        noise = rng.standard_normal(self.expert_actions.shape, np.float32)
        sampled = policy.act(self.expert_states, noise)  # (n, dim A), unclipped
        executed = np.clip(sampled, -1.0, 1.0)
        measured = {
            **measured,
            "saturation": float(np.mean(np.abs(sampled) >= 1.0)),  # components clipped
            "expert_action_error": float(((executed - self.expert_actions) ** 2).mean()),
            "mean_log_std": float(policy.log_std.mean()),
            "eval_falls": falls,
            "interactions": progress.interactions,
            "updates": progress.updates,
        }
        score = self.normalized(float(returns.mean()))
        self.clock.tick()
        row = progress.record(returns, score, measured, offpac_il.PROGRESS_FIELDS)
        diagnostics = {
            name: harness.rounded(measured[name]) if name in measured else ""
            for name in self.diagnostic_fields
        }
        agent.diagnostics.append(diagnostics)
        if returns.mean() > progress.best_eval_return:
            progress.best_eval_return = float(returns.mean())
            harness.save_arrays(self.run_dir / "policy_best.npz", policy.state("policy"))
        shown = {k: v for k, v in diagnostics.items() if k not in ("interactions", "updates")}
        print(
            f"eval  {progress.interactions:>8d} steps  {progress.updates:>7d} updates"
            f"  return {returns.mean():8.1f} ± {returns.std():6.1f}"
            f"  score {row['normalized_score']:6.3f}  "
            + "  ".join(f"{k} {v:.4g}" for k, v in shown.items() if v != ""),
            flush=True,
        )
        self.checkpoint(agent)
        return row

    @property
    def diagnostic_fields(self) -> tuple[str, ...]:
        return BC_DIAGNOSTICS if isinstance(self.config, BCConfig) else GAIL_DIAGNOSTICS

    def checkpoint(self, agent) -> None:
        """The checkpoint (networks, optimisers, Generator, counters, rows, then
        progress.csv), then diagnostics.csv: the method's own numbers per evaluation."""
        self.clock.tick()
        fields = offpac_il.PROGRESS_FIELDS
        harness.save_checkpoint(self.run_dir, agent.state(), self.rng, self.progress, fields)
        diagnostics = harness.progress_csv(agent.diagnostics, self.diagnostic_fields)
        harness.write_text(self.run_dir / "diagnostics.csv", diagnostics)
        self.clock.checkpointed()


# ----------------------------------------------------------------------------------------
# BC's loop: gradient steps on minibatches of demonstration pairs, evaluated every
# eval_every steps; stops early once the held-out likelihood stops improving.
# ----------------------------------------------------------------------------------------


def train_bc(config: BCConfig, resume: bool = False) -> harness.Progress:
    """Maximum likelihood with early stopping. policy_final.npz holds the parameters with
    the best held-out likelihood (evaluated in the progress row at their update count,
    `best_update` in diagnostics.csv); policy_best.npz, as for every method, the best
    evaluated return."""
    run = Run.open(config, resume)
    states, actions = run.expert_states, run.expert_actions
    # The held-out split has its own Generator: fixed by the seed, whatever else happens.
    order = np.random.default_rng([config.seed, 3]).permutation(len(states))
    n_held_out = round(config.validation_fraction * len(order))
    if not 1 <= n_held_out < len(order):
        raise UserError(
            f"--validation-fraction {config.validation_fraction} leaves no training or no "
            f"held-out pairs of {len(order)}"
        )
    held_out, training = order[:n_held_out], order[n_held_out:]

    rng = np.random.default_rng(config.seed)  # the run's one Generator
    policy = GaussianPolicy.create(
        states.shape[1], actions.shape[1], config.policy_hidden, config.log_std_init, rng
    )
    agent = BCAgent(policy, optim.Adam(), policy.copy())
    run.start(agent, rng, resume)
    progress, grad_norm = run.progress, math.nan
    while True:
        if progress.evaluation_due(config.eval_every, config.total_steps, "updates"):
            validation_nll = -float(policy.log_prob(states[held_out], actions[held_out])[0].mean())
            if validation_nll < agent.best_validation_nll:
                agent.best_validation_nll, agent.best_update = validation_nll, progress.updates
                agent.evaluations_since_best = 0
                agent.best_policy = policy.copy()
            else:
                agent.evaluations_since_best += 1
            train_nll = -float(policy.log_prob(states[training], actions[training])[0].mean())
            measured = {
                "validation_nll": validation_nll,
                "train_nll": train_nll,
                "best_update": agent.best_update,
                "policy_grad_norm": grad_norm,
            }
            run.evaluate(agent, {k: v for k, v in measured.items() if np.isfinite(v)})
        if bc_finished(config, progress.updates, agent.evaluations_since_best):
            break
        for _ in range(min(config.eval_every, config.total_steps - progress.updates)):
            batch = training[rng.integers(0, len(training), config.batch_size)]
            _, grads = bc_loss_and_grads(policy, states[batch], actions[batch])
            grad_norm = clip_global_norm(grads, math.inf)  # the norm only: BC does not clip
            agent.optimizer.step(policy.params, grads, config.lr)
            progress.updates += 1

    harness.save_arrays(run.run_dir / "policy_final.npz", agent.best_policy.state("policy"))
    print(
        f"BC done after {progress.updates} updates: best held-out NLL "
        f"{agent.best_validation_nll:.4f} at {agent.best_update} updates, in policy_final.npz",
        flush=True,
    )
    return progress


# ----------------------------------------------------------------------------------------
# GAIL's loop (Ho & Ermon 2016, Algorithm 1, with PPO in place of TRPO).
# ----------------------------------------------------------------------------------------


def ppo_minibatches(n: int, epochs: int, size: int, rng: np.random.Generator):
    """Row indices of each PPO minibatch: `epochs` shuffled passes over n rows, each
    pass's permutation drawn as it starts."""
    for _ in range(epochs):
        order = rng.permutation(n)
        for start in range(0, n, size):
            yield order[start : start + size]


def gail_iteration(
    agent: GAILAgent, rollout: Rollout, run: Run, config: GAILConfig, rng: np.random.Generator
) -> dict[str, float]:
    """Discriminator steps, rewards, GAE, then PPO epochs over the rollout.

    Returns the iteration's mean statistics and the number of PPO minibatch updates.
    """
    states, actions, next_states, terminal, episode_end = rollout.arrays()
    executed = np.clip(actions, -1.0, 1.0)  # what the environment got; D sees this too
    n = len(states)

    # 1. Discriminator (Ho & Ermon, Alg. 1 line 4): expert pairs vs this rollout's pairs.
    d_stats = []
    for _ in range(config.discriminator_steps):
        mine = rng.integers(0, n, config.discriminator_batch)
        theirs = rng.integers(0, len(run.expert_states), config.discriminator_batch)
        loss, grads, stats = discriminator_loss_and_grads(
            agent.discriminator,
            run.expert_states[theirs],
            run.expert_actions[theirs],
            states[mine],
            executed[mine],
        )
        agent.discriminator_optimizer.step(
            agent.discriminator.params, grads, config.discriminator_lr
        )
        d_stats.append({"discriminator_loss": loss, **stats})

    # 2. Rewards from the updated discriminator: r = -log(1 - D(s, a)).
    rewards = gail_reward(agent.discriminator, states, executed)  # (T,)

    # 3. Advantages A_t by GAE(gamma, lambda); value targets R_t = A_t + V(s_t).
    values = agent.value.forward(states)[0][:, 0]  # (T,)
    next_values = agent.value.forward(next_states)[0][:, 0]  # (T,)
    advantages = gae(
        rewards, values, next_values, terminal, episode_end, config.gamma, config.gae_lambda
    )
    returns = advantages + values
    old_log_prob, _ = agent.policy.log_prob(states, actions)  # (T,), pi_old: fixed below

    # 4. PPO (Ho & Ermon's line 5, TRPO there): epochs of shuffled minibatches, stopped
    # early once the policy has moved too far from pi_old (target_kl).
    ppo_stats = []
    for batch in ppo_minibatches(n, config.ppo_epochs, config.minibatch_size, rng):
        adv = advantages[batch]
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)  # per-minibatch, as SB3 does
        _, grads, stats = ppo_policy_loss_and_grads(
            agent.policy,
            states[batch],
            actions[batch],
            old_log_prob[batch],
            adv,
            config.clip_range,
            config.entropy_coef,
        )
        # The first minibatch always steps: the policy is pi_old there, and its KL of 0
        # comes out as rounding noise (up to ~1e-9), which a tiny target_kl would obey.
        if ppo_stats and config.target_kl > 0.0 and stats["approx_kl"] > 1.5 * config.target_kl:
            break
        grad_norm = clip_global_norm(grads, config.max_grad_norm)
        agent.policy_optimizer.step(agent.policy.params, grads, config.policy_lr)
        value_loss, value_grads = value_loss_and_grads(agent.value, states[batch], returns[batch])
        clip_global_norm(value_grads, config.max_grad_norm)
        agent.value_optimizer.step(agent.value.params, value_grads, config.value_lr)
        ppo_stats.append({**stats, "value_loss": value_loss, "policy_grad_norm": grad_norm})

    means = {
        name: float(np.mean([stats[name] for stats in records]))
        for records in (d_stats, ppo_stats)
        for name in records[0]
    }
    return {
        **means,
        "reward_mean": float(rewards.mean()),
        "entropy": agent.policy.entropy(),
        "ppo_updates": len(ppo_stats),
    }


def load_bc_init(config: GAILConfig, policy: GaussianPolicy) -> None:
    """BC+GAIL: start from a finished BC run's final policy (its mean network, and its
    log sigma unless bc_reset_log_std), trained on the same task and demonstrations with
    the same state standardisation."""
    bc_dir = Path(config.bc_init)
    try:
        saved = json.loads((bc_dir / "config.json").read_text())
    except (OSError, ValueError):
        raise UserError(
            f"--bc-init {bc_dir}: no run there (config.json missing or unreadable)"
        ) from None
    if saved.get("method") != "bc":
        raise UserError(f"--bc-init {bc_dir}: a {saved.get('method')} run, not a BC run")
    if not (bc_dir / "policy_final.npz").exists():
        raise UserError(f"--bc-init {bc_dir}: the BC run has not finished (no policy_final.npz)")
    different = [
        name for name in ("env", "standardize") if saved.get(name) != getattr(config, name)
    ]
    if tuple(saved.get("policy_hidden", ())) != config.policy_hidden:
        different.append("policy_hidden")
    theirs = expert.demo_path(saved_settings(saved), make=False)
    if theirs.resolve() != expert.demo_path(config, make=False).resolve():
        different.append("demonstrations")
    if different:
        raise UserError(f"--bc-init {bc_dir}: its {', '.join(different)} differ from this run's")
    policy.load_state(harness.load_arrays(bc_dir / "policy_final.npz"), "policy")
    if config.bc_reset_log_std:
        policy.log_std[...] = config.log_std_init


def train_gail(config: GAILConfig, resume: bool = False) -> harness.Progress:
    """GAIL: iterations of whole-episode rollouts, discriminator steps and PPO epochs."""
    run = Run.open(config, resume)
    state_dim, action_dim = run.expert_states.shape[1], run.expert_actions.shape[1]
    rng = np.random.default_rng(config.seed)  # the run's one Generator
    run.env.action_space.seed(config.seed)
    policy = GaussianPolicy.create(
        state_dim, action_dim, config.policy_hidden, config.log_std_init, rng
    )
    if config.bc_init:
        load_bc_init(config, policy)
    agent = GAILAgent(
        policy,
        nets.MLP.create([state_dim, *config.value_hidden, 1], "identity", rng),
        nets.MLP.create([state_dim + action_dim, *config.discriminator_hidden, 1], "sigmoid", rng),
    )
    run.start(agent, rng, resume)
    progress, clock = run.progress, run.clock
    while True:
        if progress.evaluation_due(config.eval_every, config.total_steps):
            run.evaluate(agent, progress.last_stats)  # and a checkpoint
        if progress.interactions >= config.total_steps:
            break

        # Whole episodes until the rollout holds at least rollout_steps steps: an
        # iteration never carries an unfinished episode, so a checkpoint between
        # iterations needs no environment state.
        rollout = Rollout()
        while len(rollout) < config.rollout_steps:
            seed = int(rng.integers(2**31))
            episode_return, _ = offpac_il.run_episode(
                run.env, agent, run.spaces, rng, seed, rollout
            )
            rollout.end_episode()
            progress.recent_returns.append(episode_return)
            progress.episodes += 1
        progress.interactions += len(rollout)
        stats = gail_iteration(agent, rollout, run, config, rng)
        progress.updates += stats.pop("ppo_updates")
        progress.last_stats = stats

        clock.tick()
        if clock.log_due():
            print(
                f"train {progress.interactions:>8d} steps"
                f"  return {progress.recent_returns[-1]:8.1f}"
                f"  D(expert) {stats['d_expert']:.3f}  D(policy) {stats['d_policy']:.3f}"
                f"  reward {stats['reward_mean']:.3f}  kl {stats['approx_kl']:.4f}"
                f"  ETA {clock.eta_minutes(config.total_steps):6.1f} min",
                flush=True,
            )
        if clock.checkpoint_due():
            run.checkpoint(agent)
            harness.stop_if_requested()

    harness.save_arrays(run.run_dir / "policy_final.npz", policy.state("policy"))
    return progress


# ----------------------------------------------------------------------------------------
# Command line: `python -m lab.baselines {bc,gail,bc-gail} [flags]`, flags from the
# dataclasses.
# ----------------------------------------------------------------------------------------

METHODS = {
    "bc": (BCConfig, "behavioural cloning: maximum likelihood with early stopping"),
    "gail": (GAILConfig, "GAIL (Ho & Ermon 2016) with PPO and GAE in place of TRPO"),
    "bc-gail": (GAILConfig, "GAIL whose policy starts from a BC run (--bc-init)"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = harness.CommandLineParser(
        prog="python -m lab.baselines",
        description="Baselines of Sasaki et al. (ICLR 2019), Sec. 5: BC, GAIL, BC+GAIL.",
    )
    methods = parser.add_subparsers(dest="method", required=True, metavar="METHOD")
    for name, (cls, summary) in METHODS.items():
        sub = methods.add_parser(
            name,
            help=summary,
            description=summary,
            formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        )
        harness.add_dataclass_flags(sub, cls)
        sub.add_argument(
            "--resume",
            metavar="RUN_DIR",
            help="continue the run in RUN_DIR from its last checkpoint, with its "
            "saved settings (other flags are ignored)",
        )
    return parser


def bc_finished(config: BCConfig, updates: int, evaluations_since_best: int) -> bool:
    """BC's end: the update budget, or `patience` evaluations without a better held-out
    likelihood (early stopping)."""
    return updates >= config.total_steps or evaluations_since_best >= config.patience


def saved_settings(saved: dict) -> RunSettings:
    """The settings of a run's config.json (its "method" names the class; a setting the
    file lacks: harness.saved_config)."""
    return harness.saved_config(METHODS[saved["method"]][0], saved, {})


def config_from(args: argparse.Namespace) -> RunSettings:
    """The method's settings: from the flags, or from RUN_DIR/config.json with --resume."""
    cls = METHODS[args.method][0]
    if args.resume is not None:
        if not args.resume:  # `--resume ""`, e.g. an unset shell variable: not a fresh run
            raise UserError("--resume needs a run directory")
        run_dir = Path(args.resume)
        saved = harness.read_config(run_dir)
        if not (run_dir / harness.CHECKPOINT).exists():
            raise UserError(f"{run_dir} holds no checkpoint to resume from")
        harness.check_program(run_dir, saved, f"python -m lab.baselines {args.method}")
        if saved.get("method") not in METHODS:  # a run of an unknown program
            raise UserError(f"{run_dir} is not a run of `python -m lab.baselines`")
        try:
            return saved_settings({**saved, "run_dir": str(run_dir)})
        except UserError as error:
            raise UserError(f"{run_dir / str(error)}") from None
    config = harness.config_from_args(cls, args)
    if args.method == "bc-gail" and not config.bc_init:
        raise UserError("bc-gail needs --bc-init BC_RUN_DIR (a finished `lab.baselines bc` run)")
    if args.method == "gail" and config.bc_init:
        raise UserError("--bc-init makes the run BC+GAIL; use `python -m lab.baselines bc-gail`")
    return config


def run(args: argparse.Namespace, argv: list[str]) -> None:
    config = config_from(args)
    train = train_bc if isinstance(config, BCConfig) else train_gail
    train(config, resume=args.resume is not None)


def main(argv: list[str] | None = None) -> int:
    return harness.cli_main(argv, lambda argv: build_parser().parse_args(argv), run)


if __name__ == "__main__":
    sys.exit(main())
