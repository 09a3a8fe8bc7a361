"""The paper's ablations (Sec. 5.3, Figure 4), each hooked into the learner at one place.

    python -m lab.ablations --env Ant-v4 --policy-type gaussian      # Ours+GP
    python -m lab.ablations --env Ant-v4 --policy-type deterministic # Ours+DP
    python -m lab.ablations --env Ant-v4 --reward-learning discriminator  # Ours+IRL(D)
    python -m lab.ablations --env Ant-v4 --reward-learning entropy   # Ours+IRL(E)
    python -m lab.ablations --env Ant-v4 --on-policy                 # Ours+OnP

Every other flag is offpac_il.py's. With all three switches off this is Ours, draw for
draw. Each switch replaces one field of `offpac_il.Variant`:
- policy_type: the policy object. "gaussian" (Ours+GP, Figure 1a): PN([s]) = [mu, log
  sigma], a = mu + sigma * eps, unbounded. "deterministic" (Ours+DP): Ours' PN with P_z
  replaced by a point mass at one draw z_0 ~ N(0, I), made once per run (not z = 0,
  which would make PN's z inputs dead weights: a different network).
- reward_learning: the critic's targets. A reward network r_omega, learned by objective
  (2) (discriminator) or (8) (entropy), and the critic trained by objective (15) with
  Eq. (13)'s P = r_omega(s, a) q_nu'(s', a')^gamma in place of (18)'s constants.
- on_policy: after each episode's updates the replay buffer is emptied, so every update
  samples the latest episode's triplets only.
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

import nets
import offpac_il
from harness import UserError
from offpac_il import BoundedPolicy, Config, Learner, Triplets, Variant

# Bounds of the Gaussian policy's log-std, as in SAC's reference implementation:
# sigma in [2e-9, 7.4] in [-1, 1] action units. An output outside gets no gradient.
LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0
REWARD_LEARNINGS = ("none", "discriminator", "entropy")
POLICY_TYPES = ("bounded", "gaussian", "deterministic")


@dataclass
class AblationConfig(Config):
    program: ClassVar[str] = "python -m lab.ablations"  # offpac_il.py would drop the switches

    on_policy: bool = False
    """Ours+OnP: empty the replay buffer after each episode's updates (only fresh samples)."""
    reward_learning: str = "none"
    """Ours+IRL(D)/(E): learn r_omega by objective (2) (discriminator) or (8) (entropy)."""
    policy_type: str = "bounded"
    """bounded: tanh(PN(s, z)) (Ours); gaussian (Ours+GP); deterministic, fixed z (Ours+DP)."""


# ----------------------------------------------------------------------------------------
# Ours+GP and Ours+DP: policy objects with BoundedPolicy's methods.
# ----------------------------------------------------------------------------------------


@dataclass
class GaussianCache:
    """net: PN's cache; noise (G, Z, dim A), the eps of each row grouped by state;
    std (G, dim A); inside (G, dim A): 1 where the log-std output lies within bounds."""

    net: nets.Cache
    noise: np.ndarray
    std: np.ndarray
    inside: np.ndarray


@dataclass
class GaussianPolicy:
    """a = mu(s) + sigma(s) * eps, eps ~ N(0, I), [mu, log sigma] = PN([s]) (Ours+GP).
    `noise_dim` is dim A: eps enters after PN (Figure 1a)."""

    net: nets.MLP
    noise_dim: int

    @classmethod
    def create(cls, state_dim, noise_dim, action_dim, config, rng, dtype=np.float32):
        net = nets.MLP.create(
            [state_dim, *config.policy_hidden, 2 * action_dim], "identity", rng, dtype
        )
        # The log-std head starts at 0 (sigma = 1 everywhere), as the paper's GAIL code and
        # lab/baselines.py do; Xavier weights would start sigma at state-dependent values.
        net.params[f"W{net.n_layers - 1}"][:, action_dim:] = 0.0
        return cls(net, action_dim)

    def samples_per_state(self, samples: int) -> int:
        return samples

    def forward(self, states: np.ndarray, noise: np.ndarray):
        out, net_cache = self.net.forward(states)  # (G, 2 dim A): PN once per state
        groups = len(out)
        mean, log_std = out[:, : self.noise_dim], out[:, self.noise_dim :]  # (G, dim A) each
        std = np.exp(np.clip(log_std, LOG_STD_MIN, LOG_STD_MAX))
        eps = noise.reshape(groups, -1, self.noise_dim)  # (G, Z, dim A)
        actions = (mean[:, None, :] + std[:, None, :] * eps).reshape(-1, self.noise_dim)
        inside = ((log_std > LOG_STD_MIN) & (log_std < LOG_STD_MAX)).astype(std.dtype)
        return actions, GaussianCache(net_cache, eps, std, inside)

    def backward(self, d_actions: np.ndarray, cache: GaussianCache) -> dict[str, np.ndarray]:
        """The reparameterisation of gradient (6): da/dmu = 1, da/dl = sigma * eps inside
        the bounds (0 outside). A state's mu and l serve its Z rows, so their gradients
        sum over them: dL/dmu = sum_z dL/da, dL/dl = sum_z dL/da * eps * sigma * inside."""
        d_a = d_actions.reshape(cache.noise.shape)  # (G, Z, dim A)
        d_mean = d_a.sum(axis=1)  # (G, dim A)
        d_log_std = (d_a * cache.noise).sum(axis=1) * cache.std * cache.inside  # (G, dim A)
        d_out = np.concatenate([d_mean, d_log_std], axis=1)  # (G, 2 dim A)
        return self.net.backward(d_out, cache.net, input_grads=False)[1]

    def act(self, states: np.ndarray, noise: np.ndarray) -> np.ndarray:
        return self.forward(states, noise)[0]

    def std(self, states: np.ndarray) -> np.ndarray:
        """sigma(s) (G, dim A), as it acts (clipped log-std)."""
        out, _ = self.net.forward(states)
        return np.exp(np.clip(out[:, self.noise_dim :], LOG_STD_MIN, LOG_STD_MAX))

    state, load_state = BoundedPolicy.state, BoundedPolicy.load_state
    copy = BoundedPolicy.copy


@dataclass
class FixedNoisePolicy(BoundedPolicy):
    """tanh(PN([s, z_0])) whatever noise the caller draws (Ours+DP). z_0 is drawn after
    QN (`fix_noise`), so at one seed Ours+DP starts from Ours' PN and QN."""

    fixed_noise: np.ndarray | None = None  # (dim z,)

    def samples_per_state(self, samples: int) -> int:
        return 1  # every row would be equal: the same mean, `samples` times the work

    def forward(self, states: np.ndarray, noise: np.ndarray):
        return super().forward(states, np.broadcast_to(self.fixed_noise, noise.shape))

    def state(self, prefix: str = "policy") -> dict[str, np.ndarray]:
        return {**super().state(prefix), f"{prefix}/fixed_noise": self.fixed_noise}

    def load_state(self, arrays, prefix: str = "policy") -> None:
        super().load_state(arrays, prefix)
        self.fixed_noise[...] = arrays[f"{prefix}/fixed_noise"]

    def copy(self) -> FixedNoisePolicy:
        return dataclasses.replace(self, net=self.net.copy())


def fix_noise(learner: Learner, state_dim, action_dim, config, rng) -> None:
    fixed = rng.standard_normal(learner.policy.noise_dim).astype(learner.critic.dtype)
    learner.policy.fixed_noise = fixed
    if learner.average_policy is not None:
        learner.average_policy.fixed_noise = fixed.copy()


# ----------------------------------------------------------------------------------------
# The entropy of a Bernoulli distribution (Eq. 9), for Ours+IRL(E)'s objective (8).
# ----------------------------------------------------------------------------------------


def sigmoid_grad(x: np.ndarray) -> np.ndarray:
    """d nets.sigmoid(x)/dx = p(1 - p), from the logit: exp(log p + log(1-p)), never NaN."""
    return np.exp(-nets.softplus(-x) - nets.softplus(x))


def bernoulli_entropy(x: np.ndarray) -> np.ndarray:
    """H(Bern(p)) = -p log p - (1-p) log(1-p) for p = nets.sigmoid(x), element-wise, in nats.

    From the logit: -log p = nets.softplus(-x) and -log(1-p) = nets.softplus(x), so
    H = p nets.softplus(-x) + (1-p) nets.softplus(x), finite for any x (0 log 0 = 0 in the limit).
    """
    p = nets.sigmoid(x)
    return p * nets.softplus(-x) + (1.0 - p) * nets.softplus(x)


def bernoulli_entropy_grad(x: np.ndarray) -> np.ndarray:
    """dH(Bern(nets.sigmoid(x)))/dx = -x p (1 - p).

    Derivation. dH/dp = -log p - 1 + log(1-p) + 1 = -log(p / (1-p)) = -logit p = -x,
    and dp/dx = p(1-p). So H rises towards x = 0 (p = 1/2, H = log 2) from either side.
    """
    return -x * sigmoid_grad(x)


# ----------------------------------------------------------------------------------------
# Ours+IRL(D) and Ours+IRL(E): a learned reward and the critic's objective (15).
# ----------------------------------------------------------------------------------------


def reward_loss_and_grads(
    reward: nets.MLP, states: np.ndarray, actions: np.ndarray, n_expert: int, objective: str
):
    """The reward network's loss and its gradient w.r.t. every reward parameter.

    r_omega(s, a) = sigmoid(x): the probability that the expert would take a at s,
    R_omega = log r_omega (Sec. 3.1.1). Rows: n_expert expert pairs, then the learner's
    (from B_beta). The loss is the objective's negative, each expectation a row mean.

    "discriminator", objective (2): read literally, E_E[log r] - E_pi[log r] has no
    maximum; the paper reads (2) as assigning r = 1 to expert pairs and r = 0 to the
    learner's (Sec. 3.1.1), which GAIL's discriminator does (Ho & Ermon 2016, Eq. 17):
        L = mean_E softplus(-x) + mean_pi softplus(x)
        dL/dx = -(1 - r) / n_E on expert rows,  r / n_pi on the learner's rows.
    "entropy", objective (8): E_E[r] + E_pi[H(r)] with H the Bernoulli entropy (9):
        L = -mean_E r - mean_pi H(r)
        dL/dx = -r(1 - r) / n_E on expert rows,  x r(1 - r) / n_pi on the learner's rows.
    Returns (loss, grads, cache).
    """
    _, cache = reward.forward((states, actions))
    x_expert, x_learner = cache.logits[:n_expert], cache.logits[n_expert:]
    n_learner = len(x_learner)
    if objective == "discriminator":  # objective (2), as a logistic discriminator
        loss = nets.softplus(-x_expert).mean() + nets.softplus(x_learner).mean()
        d_x = np.concatenate(
            [-nets.sigmoid(-x_expert) / n_expert, nets.sigmoid(x_learner) / n_learner]
        )
    elif objective == "entropy":  # objective (8), with H of Eq. (9)
        loss = -nets.sigmoid(x_expert).mean() - bernoulli_entropy(x_learner).mean()
        d_x = np.concatenate(
            [
                -sigmoid_grad(x_expert) / n_expert,
                -bernoulli_entropy_grad(x_learner) / n_learner,
            ]
        )
    else:
        raise ValueError(f"unknown reward objective {objective!r}")
    _, grads = reward.backward(d_x, cache, through_head=False, input_grads=False)
    return float(loss), grads, cache


@dataclass
class RewardLearning:
    """The reward network r_omega (QN's size, trained like QN) and its RMSProp: the
    learner's extra_state under "reward", checkpointed with it."""

    net: nets.MLP
    optimizer: nets.RMSProp
    objective: str

    def state(self, prefix: str) -> dict[str, np.ndarray]:
        return {**self.net.state(prefix), **self.optimizer.state(f"{prefix}_rmsprop")}

    def load_state(self, arrays, prefix: str) -> None:
        self.net.load_state(arrays, prefix)
        self.optimizer.load_state(arrays, f"{prefix}_rmsprop")


def add_reward(learner: Learner, state_dim, action_dim, config, rng) -> None:
    sizes = [state_dim + action_dim, *config.critic_hidden, 1]
    net = nets.MLP.create(sizes, "sigmoid", rng, learner.critic.dtype)
    optimizer = nets.RMSProp(config.rmsprop_decay, config.rmsprop_eps)
    learner.extra_state["reward"] = RewardLearning(net, optimizer, config.reward_learning)


def irl_targets(learner: Learner, batch: Triplets, n_expert: int, config, rng):
    """Objective (15)'s targets: t = E[P_omega-nu-gamma(pi_E | s, a, s', a')]
    = r_omega(s, a) E_z q_nu'(s', pi(s', z))^gamma (Eq. 13) on every row, expert or
    replay: r_omega takes the place of (18)'s halving. No gradient flows through t."""
    continuation, _ = offpac_il.critic_targets(learner, batch, len(batch.states), config, rng)
    reward, _ = learner.extra_state["reward"].net.forward((batch.states, batch.actions))
    return continuation * reward[:, 0], {}


def irl_critic_step(learner: Learner, expert_batch, replay_batch, config, lr, rng):
    """A reward step on objective (2) or (8), then the critic step on objective (15).

    The reward step uses the critic step's triplets, QN's optimiser settings and
    learning rate (the paper gives none for a reward network), and comes first, so each
    update alternates the three processes of Sec. 1 (b) in order: reward, value, policy.
    """
    reward, n = learner.extra_state["reward"], len(expert_batch.states)
    batch = offpac_il.concatenated(expert_batch, replay_batch)
    loss, grads, cache = reward_loss_and_grads(
        reward.net, batch.states, batch.actions, n, reward.objective
    )
    reward.optimizer.step(reward.net.params, grads, lr)
    r = cache.output[:, 0]
    stats = offpac_il.critic_step(learner, expert_batch, replay_batch, config, lr, rng, irl_targets)
    return stats | {
        "reward_loss": loss,
        "r_expert": float(r[:n].mean()),
        "r_replay": float(r[n:].mean()),
    }


# ----------------------------------------------------------------------------------------
# Choosing the variant, and the command line.
# ----------------------------------------------------------------------------------------


def gaussian_diagnostics(learner: Learner, states: np.ndarray) -> dict[str, float]:
    return {"policy_std": float(learner.policy.std(states).mean())}


def empty(replay) -> None:
    """Ours+OnP: once this episode's updates have moved theta, its triplets are another
    policy's, so they go; the next updates sample the next episode's alone (with
    replacement, the same batch sizes). Emptying here keeps Algorithm 1 otherwise."""
    replay.size, replay.next_index = 0, 0


def variant_of(config: AblationConfig) -> Variant:
    if config.reward_learning not in REWARD_LEARNINGS:
        raise UserError(f"--reward-learning must be one of {', '.join(REWARD_LEARNINGS)}")
    if config.policy_type not in POLICY_TYPES:
        raise UserError(f"--policy-type must be one of {', '.join(POLICY_TYPES)}")
    hooks: dict = {}
    if config.policy_type == "gaussian":
        hooks |= {"make_policy": GaussianPolicy.create, "diagnostics": gaussian_diagnostics}
        hooks["progress_fields"] = ("policy_std",)
    if config.policy_type == "deterministic":
        hooks |= {"make_policy": FixedNoisePolicy.create, "make_extras": fix_noise}
    if config.reward_learning != "none":
        if "make_extras" in hooks:
            raise UserError("--reward-learning and --policy-type deterministic are not combined")
        hooks |= {"make_extras": add_reward, "critic_step": irl_critic_step}
        hooks["progress_fields"] = (
            "reward_loss",
            "r_expert",
            "r_replay",
            *hooks.get("progress_fields", ()),
        )
    if config.on_policy:
        hooks["after_updates"] = empty
    return Variant(**hooks)


def main(argv: list[str] | None = None) -> int:
    return offpac_il.main(argv, config_class=AblationConfig, variant_of=variant_of)


if __name__ == "__main__":
    sys.exit(main())
