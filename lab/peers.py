"""Off-policy peers on the learner's own demonstrations: SQIL and IQ-Learn, on lab/sac.py.

The paper compares its learner with BC (offline) and GAIL (on-policy). The methods a
reader compares against today are off-policy, maximum-entropy imitation learners built on
SAC. They answer the question the learner's failures raise: do the same 400 triplets,
budget and scoring suffice for a method known to imitate? Here:

- SQIL (Reddy, Dragan & Levine, "SQIL: Imitation Learning via Reinforcement Learning with
  Sparse Rewards", ICLR 2020, https://arxiv.org/abs/1905.11108): SAC whose demonstration
  transitions carry reward 1 and whose own transitions carry reward 0, each minibatch
  half from each buffer (its Algorithm 1). **No new gradient**: the critics, the policy
  and the temperature are SAC's, `sac.update`, every gradient of which is checked in
  tests/test_sac.py; SQIL only chooses the batch (`mixed_batch`) and its rewards.
- IQ-Learn (Garg, Chakraborty, Cundy, Song & Ermon, "IQ-Learn: Inverse soft-Q Learning for
  Imitation", NeurIPS 2021, https://arxiv.org/abs/2106.12142): SAC whose critics are
  trained by the inverse soft-Q objective with the chi-squared regulariser, in the online
  "value" and "v0" forms of its Eq. (10) and of its code (Div99/IQ-Learn, iq.py); the
  actor is SAC's, against the same critics, and the temperature stays at its initial
  value as in the authors' MuJoCo settings. Its critic objective is new here:
  `iq_learn_loss_and_grads` derives and computes its gradient, checked against finite
  differences in tests/test_peers.py.

What is SAC's (lab/sac.py): the networks, the update, the replay buffer (saved in segments
so that a run resumes exactly) and the checkpoint. What is the learner's (offpac_il.py):
the demonstrations, the action scaling and optional state standardisation
(`offpac_il.make_spaces`), whole episodes (`offpac_il.run_episode`) and the seeded
evaluation (`offpac_il.evaluate`), so a peer sees, acts and is scored as Ours is.

The loop is Algorithm 1's, as Ours runs it: one episode with the current policy, then as
many updates as the episode had steps. SAC proper interleaves one update per step; with
the learning rates held fixed the difference is a policy at most one episode older, and
it keeps the peers on the learner's schedule (evaluation at the first episode end past
every `eval_every`). For the first `learning_starts` interactions there are no updates and
the untrained policy acts: its log sigma starts near 0, so its tanh-Gaussian actions
spread over [-1, 1] about as widely as SAC's uniform ones (std 0.63 against 0.58).

Evaluation reports both policies: the deterministic tanh(mu(s)) (`normalized_score`, as
SAC papers report) and the stochastic one (`stochastic_score`), on the same episode seeds.

Settings are those of the SQIL control of the project's record (PyTorch, CleanRL's SAC):
two hidden layers of 256 units, Adam 3e-4, batch 256 (128 demonstration and 128 replay
transitions), gamma 0.99, tau 0.005, a learned temperature, 5 000 interactions before the
first update, no state standardisation (SAC's practice; `--standardize` offers the
learner's).

IQ-Learn's defaults are its authors' for MuJoCo (Div99/IQ-Learn: conf/agent/sac.yaml,
scripts/run_mujoco.sh): two hidden layers of 256 units, critic rate 3e-4, actor rate 3e-5,
a fixed temperature 1e-2, one critic (conf/env/*.yaml: SingleQCritic; `--twin-critics`
gives SAC's two and their minimum, with which the authors report divergence), batches of
256 demonstration and 256 replay transitions, target critics (tau 0.005), updates from
1 280 stored interactions, chi-squared weight 1/(4 * 0.5). Per task they choose the form
of the value term and the temperature: `--value-loss v0` on Hopper, Walker2d and Humanoid
(Humanoid also `--initial-alpha 1`), `value` on HalfCheetah and Ant (Ant also
`--initial-alpha 1e-3`). Where this differs from the authors' code: their log sigma is
squashed into [-5, 2] where SAC here clips it to [-20, 2].

    python -m lab.peers sqil --env Ant-v4 [--demos ... --trajectories 4 --sampling sparse]
    python -m lab.peers iq-learn --env Ant-v4 --value-loss value --initial-alpha 1e-3
    python -m lab.peers sqil --resume RUN_DIR

Files in the run directory: config.json (with "method"), progress.csv, checkpoint.npz and
replay/ (SAC's segments), policy_final.npz and policy_best.npz (the policy MLP, under
the key prefix "policy").
"""

from __future__ import annotations

import dataclasses
import math
import sys
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

import expert
import harness
import nets
import offpac_il
from harness import UserError
from lab import sac

# ----------------------------------------------------------------------------------------
# Settings: one dataclass per method, a --flag per field.
# ----------------------------------------------------------------------------------------


@dataclass
class PeerConfig(offpac_il.RunConfig):
    """What the SAC-based peers share: the learner's task, demonstrations, evaluation and
    run directory (RunConfig), and SAC's settings."""

    standardize: bool = False
    """Standardise states by the demonstrations' mean and std (+1e-3), as the learner does
    (off: SAC's practice, and the record's SQIL control)."""
    total_steps: int = 300_000
    """Interaction budget (the learner's)."""
    eval_every: int = 5_000
    """Interactions between evaluations (the learner's schedule)."""
    hidden: tuple[int, ...] = (256, 256)
    """Hidden layer sizes of the policy and of each critic."""
    lr: float = 3e-4
    """Adam learning rate of the critics and of log alpha."""
    policy_lr: float = 3e-4
    """Adam learning rate of the policy."""
    batch_size: int = 256
    """Transitions per update: half from the demonstrations, half from the replay buffer."""
    replay_size: int = 1_000_000
    """Capacity of the replay buffer (FIFO)."""
    gamma: float = 0.99
    """Discount factor."""
    tau: float = 0.005
    """Target critic tracking rate: theta_bar <- tau theta + (1 - tau) theta_bar."""
    learning_starts: int = 5_000
    """Interactions before the first update (the untrained policy acts)."""
    initial_alpha: float = 1.0
    """Entropy temperature alpha at the start."""
    learn_alpha: bool = True
    """Learn alpha towards the target entropy -dim A (SAC's Eq. 18); off: alpha stays."""

    # Settings measured not to help, which left the code (offpac_il.Config's convention):
    # name -> (its "off" value, the last commit with it). Such a run is not resumed here.
    removed_settings: ClassVar[dict[str, tuple[float | str, str]]] = {
        "lr_decay": (False, "2b793f8"),
    }

    @property
    def twin_critics(self) -> bool:  # SQIL is SAC: always two critics
        return True


@dataclass
class SQILConfig(PeerConfig):
    """SQIL: SAC with reward 1 on demonstration and 0 on replay transitions."""


VALUE_LOSSES = ("value", "v0")


@dataclass
class IQLearnConfig(PeerConfig):
    """IQ-Learn: SAC whose critics minimise the inverse soft-Q objective (authors' settings)."""

    policy_lr: float = 3e-5
    """Adam learning rate of the policy."""
    batch_size: int = 512
    """Transitions per update: half from the demonstrations, half from the replay buffer."""
    learning_starts: int = 1_280
    """Interactions before the first update (the untrained policy acts)."""
    initial_alpha: float = 1e-2
    """Entropy temperature alpha (fixed unless --learn-alpha)."""
    learn_alpha: bool = False
    """Learn alpha towards the target entropy -dim A (SAC's Eq. 18); off: alpha stays."""
    value_loss: str = "value"
    """The value term: value, E over all rows of V(s) - gamma V(s'); v0, (1 - gamma) E over
    the demonstrated states of V(s)."""
    chi2_alpha: float = 0.5
    """The chi-squared regulariser's alpha: the squared residuals weigh 1/(4 alpha)."""
    twin_critics: bool = False
    """Two critics and their minimum, as SAC; off: one critic, as the authors' MuJoCo
    settings (q_net SingleQCritic; with two, their critic diverges, their issue 11)."""
    # IQ-Learn ran SAC's twin critics until one critic became its default: a config.json
    # of that time lacks the setting and is read, and resumed, with two.
    settings_before_they_existed: ClassVar[dict] = {"twin_critics": True}


# A resumed run may extend its budget (no schedule depends on it) and change what only
# logging and checkpoints read.
RESUMABLE_CHANGES = ("total_steps", "checkpoint_every", "log_every")


def check_config(config: PeerConfig) -> None:
    """Refuse settings that cannot work, in one line, before anything is written."""
    harness.check_choices(config, {"sampling": expert.SAMPLING_MODES})
    if isinstance(config, IQLearnConfig):
        harness.check_choices(config, {"value_loss": VALUE_LOSSES})
        harness.check_numbers(config, {"chi2_alpha": (0, math.inf, "()")})
    counts = ("trajectories", "total_steps", "eval_every", "eval_episodes", "hidden")
    counts += ("replay_size", "learning_starts")
    harness.check_numbers(
        config,
        {name: (1, math.inf, "[)") for name in counts}
        | {name: (0, math.inf, "()") for name in ("lr", "policy_lr", "initial_alpha")}
        | {name: (0, math.inf, "[)") for name in ("seed", "demo_seed")}
        | {name: (0, math.inf, "[)") for name in ("checkpoint_every", "log_every")}
        | {"batch_size": (2, math.inf, "[)"), "gamma": (0, 1, "[)"), "tau": (0, 1, "(]")},
    )


# ----------------------------------------------------------------------------------------
# The batch: half demonstrations, half replay (both peers).
# ----------------------------------------------------------------------------------------


def mixed_batch(
    demonstrations: sac.Batch, replay: sac.ReplayBuffer, rng: np.random.Generator, size: int
) -> sac.Batch:
    """size // 2 demonstration transitions first, then the rest from the replay buffer,
    each drawn uniformly with replacement (SQIL's Alg. 1; IQ-Learn's code). Their rewards
    are the buffers': for SQIL 1 and 0, for IQ-Learn 0 (it learns no reward)."""
    n_expert = size // 2
    rows = rng.integers(0, len(demonstrations.rewards), n_expert)
    expert_rows = sac.Batch(*(getattr(demonstrations, f)[rows] for f in sac.ReplayBuffer.FIELDS))
    replay_rows = replay.sample(rng, size - n_expert)
    return sac.Batch(
        *(
            np.concatenate([getattr(expert_rows, f), getattr(replay_rows, f)])
            for f in sac.ReplayBuffer.FIELDS
        )
    )


def demonstration_batch(expert_buffer: offpac_il.Triplets, reward: float) -> sac.Batch:
    """Every demonstration transition as SAC's Batch, in the networks' units."""
    n = len(expert_buffer.states)
    return sac.Batch(
        expert_buffer.states,
        expert_buffer.actions,
        np.full(n, reward, np.float32),
        expert_buffer.next_states,
        expert_buffer.terminal.astype(np.float32),
    )


# ----------------------------------------------------------------------------------------
# IQ-Learn's critic objective and its gradient.
# ----------------------------------------------------------------------------------------


def iq_learn_loss_and_grads(
    q1: nets.MLP,
    q2: nets.MLP,
    batch: sac.Batch,
    policy_actions: np.ndarray,
    policy_log_prob: np.ndarray,
    y: np.ndarray,
    alpha: float,
    n_expert: int,
    value_loss: str,
    chi2_alpha: float,
    gamma: float,
):
    """IQ-Learn's online critic loss with the chi-squared regulariser, and its gradient.

    Rows 0..n_E-1 of `batch` are demonstrations (E), the other n_B replay transitions (B),
    N = n_E + n_B. Per row r, with everything that is not a critic output held fixed:
        y_r   = gamma (1 - d_r) V_bar(s'_r)             target critics, no gradient
        Q_i   = Q_i(s_r, a_r)                            critic i at the stored pair
        P_r   = min(Q_1, Q_2)(s_r, a~_r),  a~_r ~ pi(.|s_r)   (policy_actions)
        V_r   = P_r - alpha log pi(a~_r|s_r)             the soft value, Eq. (2) of SAC
    The loss averages the two critics' losses of the authors' code (iq.py, twin critics):
        L = 1/2 sum_i [ -1/n_E sum_E (Q_i - y) + c/N sum_E (Q_i - y)^2 ]      Eq. (10)'s
            + c/N sum_B (P - y)^2                                              first term,
            + value term                                                       regulariser
    with c = 1/(4 chi2_alpha) (the chi-squared divergence's regulariser, its Sec. 5.1,
    taken at the demonstrations' pairs and at the policy's own actions on replay states),
    and the value term (Eq. 10's second term, two of its estimators):
        value: 1/N sum_all (V - y)        v0: (1 - gamma)/n_E sum_E V.
    The gradient with respect to the critics' outputs:
        dL/dQ_i,r = 1/2 (-1/n_E + 2 c (Q_i,r - y_r)/N)          r in E, else 0
        dL/dP_r   = 2 c (P_r - y_r)/N [r in B] + (value: 1/N;  v0: (1 - gamma)/n_E [r in E])
    and dP_r reaches only the critic attaining the minimum on that row (dV/dP = 1: the
    entropy term is fixed here). Each critic is run once on the 2N stacked inputs
    [(s, a); (s, a~)] and backpropagated once. Returns (loss, q1 grads, q2 grads, stats).
    """
    n_rows = len(y)
    expert = np.arange(n_rows) < n_expert  # (N,)
    c = 1.0 / (4.0 * chi2_alpha)
    states = np.concatenate([batch.observations, batch.observations])  # (2N, dim S)
    actions = np.concatenate([batch.actions, policy_actions])  # (2N, dim A)
    out1, cache1 = q1.forward((states, actions))  # (2N, 1)
    out2, cache2 = q2.forward((states, actions))  # (2N, 1)
    q_data = (out1[:n_rows, 0], out2[:n_rows, 0])  # Q_i(s, a), (N,) each
    first_is_min = out1[n_rows:, 0] <= out2[n_rows:, 0]  # (N,)
    p = np.where(first_is_min, out1[n_rows:, 0], out2[n_rows:, 0])  # P = min Q(s, a~)
    v = p - alpha * policy_log_prob  # (N,)

    loss = 0.0
    d_data = []
    for q in q_data:
        residual = (q - y)[expert]  # (n_E,)
        loss += 0.5 * (-float(residual.mean()) + c * float(residual @ residual) / n_rows)
        d_q = np.zeros(n_rows, q.dtype)
        d_q[expert] = 0.5 * (-1.0 / n_expert + 2.0 * c * residual / n_rows)
        d_data.append(d_q)
    policy_residual = (p - y)[~expert]  # (n_B,)
    loss += c * float(policy_residual @ policy_residual) / n_rows
    d_p = np.zeros(n_rows, p.dtype)
    d_p[~expert] = 2.0 * c * policy_residual / n_rows
    if value_loss == "value":
        loss += float((v - y).mean())
        d_p += 1.0 / n_rows
    else:  # v0: the demonstrated states stand in for the initial ones (authors' code)
        loss += (1.0 - gamma) * float(v[expert].mean())
        d_p[expert] += (1.0 - gamma) / n_expert
    grads = []
    for mlp, cache, d_q, is_min in (
        (q1, cache1, d_data[0], first_is_min),
        (q2, cache2, d_data[1], ~first_is_min),
    ):
        d_out = np.concatenate([d_q, np.where(is_min, d_p, 0.0)])[:, None]  # (2N, 1)
        grads.append(mlp.backward(d_out.astype(mlp.dtype), cache, input_grads=False)[1])
    stats = {
        "critic_loss": loss,
        "q_mean": float(q_data[0].mean()),
        # IQ-Learn's implicit reward r = Q(s, a) - gamma V_bar(s'): at the demonstrated
        # pairs, and at the policy's own actions on replay states (the loss never reads Q
        # at the replay's stored actions).
        "reward_expert": float((q_data[0] - y)[expert].mean()),
        "reward_policy": float(policy_residual.mean()),
    }
    return loss, grads[0], grads[1], stats


def iq_learn_critic_step(agent, batch, actions, log_prob, alpha, config, rng):
    """sac.update's critic step for IQ-Learn: y from the target critics and a fresh
    a' ~ pi(.|s') (sac.critic_targets, the batch's rewards being 0), then the loss above
    at the update's own a~ ~ pi(.|s) and log pi."""
    next_noise = rng.standard_normal(actions.shape, dtype=actions.dtype)
    twin = config.twin_critics
    target_q2, q2 = (agent.target_q2, agent.q2) if twin else (agent.target_q1, agent.q1)
    y = sac.critic_targets(
        agent.target_q1, target_q2, agent.policy, batch, alpha, config.gamma, next_noise
    )
    _, q1_grads, q2_grads, stats = iq_learn_loss_and_grads(
        agent.q1,
        q2,
        batch,
        actions,
        log_prob,
        y,
        alpha,
        len(y) // 2,  # mixed_batch's demonstrations come first
        config.value_loss,
        config.chi2_alpha,
        config.gamma,
    )
    if not twin:  # the loss read Q_1 in both slots: its gradient is the two slots' sum
        return {key: q1_grads[key] + q2_grads[key] for key in q1_grads}, None, stats
    return q1_grads, q2_grads, stats


@dataclass(frozen=True)
class Method:
    """What sets a peer apart: its settings, the demonstrations' reward, its critic step."""

    config_class: type
    summary: str
    demonstration_reward: float
    critic_step: object  # sac.update's steps 3-4


METHODS = {
    "sqil": Method(
        SQILConfig,
        "SQIL (Reddy et al. 2020): SAC, demonstrations rewarded 1, replay 0",
        1.0,
        sac.bellman_critic_step,
    ),
    "iq-learn": Method(
        IQLearnConfig,
        "IQ-Learn (Garg et al. 2021): SAC whose critics minimise the inverse soft-Q objective",
        0.0,
        iq_learn_critic_step,
    ),
}


# ----------------------------------------------------------------------------------------
# SAC's policy as the learner's episodes and evaluation call it, and its replay buffer.
# ----------------------------------------------------------------------------------------


@dataclass
class SquashedGaussian:
    """SAC's policy network with the interface offpac_il.run_episode and evaluate call:
    act(states, noise) and noise_dim (= dim A: one eps per action component)."""

    network: nets.MLP
    noise_dim: int
    deterministic: bool = False

    def act(self, states: np.ndarray, noise: np.ndarray) -> np.ndarray:
        if self.deterministic:
            return sac.deterministic_actions(self.network, states)  # tanh(mu(s))
        return sac.sample_actions(self.network, states, noise)[0]  # tanh(mu + sigma eps)


@dataclass
class Acting:
    """What offpac_il.run_episode and evaluate take as the learner: its `policy`."""

    policy: SquashedGaussian


class ReplayBuffer(sac.ReplayBuffer):
    """SAC's buffer, filled by offpac_il.run_episode with (s, a, s', terminated) triplets
    in the networks' units; their reward is 0 (SQIL's reward of the learner's own
    transitions; another peer does not read it)."""

    def add(self, state, action, next_state, terminal: bool) -> None:
        super().add(state, action, 0.0, next_state, terminal)


# ----------------------------------------------------------------------------------------
# The run: episodes, updates, evaluation of both policies, checkpoints.
# ----------------------------------------------------------------------------------------

UPDATE_STATS = ("alpha", "entropy", "critic_loss", "policy_loss", "q_mean")
UPDATE_STATS += ("reward_expert", "reward_policy")  # IQ-Learn's implicit reward
PROGRESS_FIELDS = (
    *("interactions", "wall_seconds", "updates", "episodes", "eval_return_mean"),
    *("eval_return_std", "normalized_score", "train_return", "eval_falls"),
    *("stochastic_return_mean", "stochastic_score", "stochastic_falls"),
    *UPDATE_STATS,
    *("q_expert", "q_replay", "q_policy_at_expert", "expert_action_error", "saturation"),
)


def diagnostics(agent: sac.Agent, expert_buffer: offpac_il.Triplets, replay, rng) -> dict:
    """How the critics and the policy see the demonstrations: Q1 at the demonstrated pairs,
    at replay pairs and at (s_E, tanh(mu(s_E))); the deterministic policy's squared error
    against a_E; the share of its components beyond 0.99 in magnitude (the policy's corners)."""
    states, actions = expert_buffer.states, expert_buffer.actions
    policy_actions = sac.deterministic_actions(agent.policy, states)
    replay_rows = replay.sample(rng, min(len(states), replay.size))

    def q1(s, a) -> float:
        return float(agent.q1.forward((s, a))[0].mean())

    return {
        "q_expert": q1(states, actions),
        "q_replay": q1(replay_rows.observations, replay_rows.actions),
        "q_policy_at_expert": q1(states, policy_actions),
        "expert_action_error": float(((policy_actions - actions) ** 2).mean()),
        "saturation": float(np.mean(np.abs(policy_actions) > 0.99)),
    }


def train(config: PeerConfig, method: str, resume: bool = False) -> sac.Progress:
    """Algorithm 1's loop with SAC's update on the method's batch; evaluation and
    checkpoints as the learner's."""
    check_config(config)
    env, eval_env = expert.make_env(config.env), expert.make_env(config.env)
    demos = expert.run_demos(config, resume)
    print(demos.describe(), flush=True)
    spaces = offpac_il.make_spaces(env, demos, offpac_il.Config(standardize=config.standardize))
    expert_buffer = offpac_il.expert_buffer_from(demos, spaces)
    demonstrations = demonstration_batch(expert_buffer, METHODS[method].demonstration_reward)
    references = expert.references_or_nan(config.env, demos)
    dim_s, dim_a = expert.env_dimensions(env)
    rng = np.random.default_rng(config.seed)  # the run's one Generator
    env.action_space.seed(config.seed)
    agent = sac.Agent.create(dim_s, dim_a, config, rng)
    replay = ReplayBuffer(config.replay_size, dim_s, dim_a)
    run_dir = harness.open_run_dir(
        config.run_dir or f"runs/{method}-{config.env}-seed{config.seed}", resume
    )
    if resume:
        progress = sac.load_checkpoint(run_dir, agent, replay, rng)
        print(f"resumed {run_dir} at {progress.interactions} interactions", flush=True)
    else:
        progress = sac.Progress()
        harness.write_text(run_dir / harness.PROGRESS, harness.progress_csv([], PROGRESS_FIELDS))
    # Rewritten on a resume too: it may have extended the budget.
    record = {"method": method, harness.PROGRAM: f"python -m lab.peers {method}"}
    record |= {expert.DEMOS_SHA256: demos.sha256}
    harness.write_config(run_dir, record | dataclasses.asdict(config))
    clock = harness.Clock(progress, config.checkpoint_every, config.log_every)
    acting = Acting(SquashedGaussian(agent.policy, dim_a))
    deterministic = Acting(SquashedGaussian(agent.policy, dim_a, deterministic=True))

    def checkpoint() -> None:
        harness.check_finite(agent.state(), f"by {progress.interactions} interactions")
        sac.save_checkpoint(run_dir, agent, replay, progress, rng, PROGRESS_FIELDS)
        clock.checkpointed()

    def evaluate() -> None:
        round_index = progress.eval_rounds
        returns, falls = offpac_il.evaluate(eval_env, deterministic, spaces, config, round_index)
        sampled, sampled_falls = offpac_il.evaluate(eval_env, acting, spaces, config, round_index)
        stochastic = float(sampled.mean())
        measured = {
            name: total / max(progress.stat_count, 1) for name, total in progress.stat_sums.items()
        }
        measured |= {
            "eval_falls": falls,
            "stochastic_return_mean": stochastic,
            "stochastic_score": expert.normalized_score(stochastic, references),
            "stochastic_falls": sampled_falls,
        }
        if replay.size:
            diagnostics_rng = np.random.default_rng([config.seed, 2, round_index])
            measured |= diagnostics(agent, expert_buffer, replay, diagnostics_rng)
        score = expert.normalized_score(float(returns.mean()), references)
        clock.tick()
        row = progress.record(returns, score, measured, PROGRESS_FIELDS)
        progress.stat_sums, progress.stat_count = {}, 0
        if returns.mean() > progress.best_eval_return:
            progress.best_eval_return = float(returns.mean())
            harness.save_arrays(run_dir / "policy_best.npz", agent.policy.state("policy"))
        print(
            f"eval  {progress.interactions:>8d} steps  return {returns.mean():8.1f}"
            f" ± {returns.std():6.1f}  score {row['normalized_score']:6.3f}"
            f"  stochastic {row['stochastic_score']:6.3f}  alpha {agent.alpha:.4f}"
            f"  Q_E {harness.shown(row['q_expert'], '.2f')}"
            f"  Q_B {harness.shown(row['q_replay'], '.2f')}",
            flush=True,
        )
        checkpoint()

    with env, eval_env:
        while True:
            if progress.evaluation_due(config.eval_every, config.total_steps):
                evaluate()
            if progress.interactions >= config.total_steps:
                break
            seed = int(rng.integers(2**31))
            episode_return, length = offpac_il.run_episode(env, acting, spaces, rng, seed, replay)
            progress.recent_returns.append(episode_return)
            progress.episodes += 1
            progress.interactions += length
            updates = min(length, max(0, progress.interactions - config.learning_starts))
            for _ in range(updates):
                batch = mixed_batch(demonstrations, replay, rng, config.batch_size)
                stats = sac.update(agent, batch, config, rng, METHODS[method].critic_step)
                progress.updates += 1
                for name in (name for name in UPDATE_STATS if name in stats):
                    progress.stat_sums[name] = progress.stat_sums.get(name, 0.0) + stats[name]
                progress.stat_count += 1

            clock.tick()
            if clock.log_due():
                score = expert.normalized_score(episode_return, references)
                print(
                    f"train {progress.interactions:>8d} steps  return {episode_return:8.1f}"
                    f" ({length:4d} steps)  score {score:6.3f}  alpha {agent.alpha:.4f}"
                    f"  ETA {clock.eta_minutes(config.total_steps):6.1f} min",
                    flush=True,
                )
            if clock.checkpoint_due():
                checkpoint()
                harness.stop_if_requested()

    harness.save_arrays(run_dir / "policy_final.npz", agent.policy.state("policy"))
    return progress


# ----------------------------------------------------------------------------------------
# Command line: python -m lab.peers METHOD [flags], one flag per field of its dataclass.
# ----------------------------------------------------------------------------------------

USAGE = f"usage: python -m lab.peers {{{','.join(METHODS)}}} [--help] [flags]"


def parse(argv: list[str]) -> tuple[PeerConfig, str, bool]:
    """(config, method, resume). A resume must name the method that made the run."""
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        for name, known in METHODS.items():
            print(f"  {name:10s} {known.summary}")
        raise SystemExit(0 if argv else 2)
    method, argv = argv[0], argv[1:]
    if method not in METHODS:
        raise UserError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    config, resume = harness.config_from_command_line(
        argv,
        METHODS[method].config_class,
        METHODS[method].summary,
        {},
        RESUMABLE_CHANGES,
        prog=f"python -m lab.peers {method}",
    )
    if resume:
        saved = harness.read_config(config.run_dir)
        harness.check_program(config.run_dir, saved, f"python -m lab.peers {method}")
        made_by = saved.get("method")
        if made_by != method:
            raise UserError(f"{config.run_dir} is not a {method} run (its method: {made_by})")
    return config, method, resume


def saved_settings(saved: dict) -> PeerConfig:
    """The settings of a peer run's config.json (its "method" names the class)."""
    return harness.saved_config(METHODS[saved["method"]].config_class, saved, {})


def main(argv: list[str] | None = None) -> int:
    return harness.cli_main(argv, parse, lambda parsed, argv: train(*parsed))


if __name__ == "__main__":
    sys.exit(main())
