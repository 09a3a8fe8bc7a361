"""The learner: finite-difference checks of objective (18) and gradient (6) as the
learner computes them, the targets, the pieces of Algorithm 1, and the command line end
to end. The ablations are tested in test_ablations.py, the run harness in test_harness.py."""

from __future__ import annotations

import copy
import dataclasses
import errno
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from gradcheck import assert_gradient_close, numerical_gradient
from helpers import ROOT, interrupted_after, read_rows, release, run_script
from hypothesis import assume, given
from hypothesis import strategies as st

import harness
import nets
import offpac_il

# The losses are O(0.1-1) while units on the leaky side of their ReLU give parameter
# gradients of O(1e-7), where a centered difference's rounding error (~1e-16 |f| / eps)
# dominates. Measured worst relative error over 40 seeds of the critic objective:
# eps 1e-6: 9e-4, 1e-5: 1e-4, 1e-4: 9e-6, 1e-3: 0.2 (steps cross ReLU kinks). Hence
# eps = 1e-4 and a tolerance of 5e-5; a wrong gradient is off by O(1) (see the tests
# that check the check).
OBJECTIVE_EPS, OBJECTIVE_TOL = 1e-4, 5e-5
SMALL = dict(policy_hidden=(6, 5), critic_hidden=(7, 6))


def small_learner(
    seed: int,
    state_dim=3,
    action_dim=2,
    dtype=np.float64,
    config_class=offpac_il.Config,
    variant_of=lambda config: offpac_il.OURS,
    **overrides,
):
    """A small learner made as `offpac_il.prepare` makes one (PN, QN, then the variant's
    extras, from one Generator), with a target critic that differs from the critic, as
    it does during training. Returns (learner, config, rng)."""
    config = config_class(**{**SMALL, **overrides})
    rng = np.random.default_rng(seed)
    variant = variant_of(config)
    policy = variant.make_policy(state_dim, state_dim, action_dim, config, rng, dtype)
    learner = offpac_il.Learner.create(policy, state_dim, action_dim, config, rng, dtype)
    variant.make_extras(learner, state_dim, action_dim, config, rng)
    for value in learner.target_critic.params.values():
        value += 0.1 * rng.standard_normal(value.shape)
    return learner, config, rng


def away_from_kinks(*caches, margin=1e-2) -> bool:
    """True when every hidden pre-activation is at least `margin` from the ReLU kink, so
    that finite-difference steps of 1e-4 cannot cross it (as in cs231n's checks)."""
    for cache in caches:
        for activation in cache.activations:
            pre_activation = np.where(activation > 0, activation, activation / 0.01)
            if np.abs(pre_activation).min() < margin:
                return False
    return True


def random_triplets(rng, n, state_dim=3, action_dim=2, terminal_fraction=0.0):
    return offpac_il.Triplets(
        rng.standard_normal((n, state_dim)),
        rng.uniform(-1, 1, (n, action_dim)),
        rng.standard_normal((n, state_dim)),
        rng.random(n) < terminal_fraction,
    )


# ---------------------------------------------------------------------------------------
# Objective (18): the critic's loss, w.r.t. every critic parameter, target frozen.
# ---------------------------------------------------------------------------------------


@given(seed=st.integers(0, 2**16), n=st.integers(1, 5))
def test_critic_objective_gradient_matches_finite_differences(seed, n):
    learner, _, rng = small_learner(seed)
    batch = random_triplets(rng, 2 * n)
    t = rng.uniform(0.0, 1.0, (2 * n, 1))
    t[n:] *= 0.5  # replay rows' targets are halved, as in Eq. (18)
    assume(away_from_kinks(learner.critic.forward((batch.states, batch.actions))[1]))

    def loss():
        return offpac_il.critic_loss_and_grads(learner.critic, batch, t, n)[0]

    # The loss written out: the expert rows' mean of D_JS plus the replay rows' mean.
    q, _ = learner.critic.forward((batch.states, batch.actions))
    js = nets.js_divergence(np.log(q) - np.log1p(-q), t)[:, 0]
    np.testing.assert_allclose(loss(), js[:n].mean() + js[n:].mean(), rtol=1e-10)

    _, grads, _ = offpac_il.critic_loss_and_grads(learner.critic, batch, t, n)
    assert set(grads) == set(learner.critic.params)
    for name, param in learner.critic.params.items():
        assert_gradient_close(
            grads[name],
            numerical_gradient(loss, param, OBJECTIVE_EPS),
            OBJECTIVE_TOL,
            f"objective (18) d/d{name}",
        )


def test_critic_objective_check_catches_a_wrong_gradient():
    """The check above fails if the JS gradient loses its factor 1/2."""
    learner, _, rng = small_learner(1)
    batch = random_triplets(rng, 4)
    t = rng.uniform(0.0, 1.0, (4, 1))
    _, grads, _ = offpac_il.critic_loss_and_grads(learner.critic, batch, t, 2)

    def loss():
        return offpac_il.critic_loss_and_grads(learner.critic, batch, t, 2)[0]

    numeric = numerical_gradient(loss, learner.critic.params["W0"], OBJECTIVE_EPS)
    assert_gradient_close(grads["W0"], numeric, OBJECTIVE_TOL)  # the right one passes
    with pytest.raises(AssertionError):
        assert_gradient_close(2.0 * grads["W0"], numeric, OBJECTIVE_TOL)


# ---------------------------------------------------------------------------------------
# Gradient (6): the policy objective, through the critic's action Jacobian and the tanh.
# ---------------------------------------------------------------------------------------


@given(seed=st.integers(0, 2**16), states=st.integers(1, 4), noise_samples=st.integers(1, 5))
def test_policy_gradient_matches_finite_differences(seed, states, noise_samples):
    learner, _, rng = small_learner(seed)
    s = rng.standard_normal((states, 3))
    z = rng.standard_normal((states * noise_samples, 3))
    critic_before = {k: v.copy() for k, v in learner.critic.params.items()}
    actions, policy_cache = learner.policy.forward(s, z)
    assume(away_from_kinks(policy_cache, learner.critic.forward((s, actions))[1]))

    def loss():
        return offpac_il.policy_loss_and_grads(learner, s, z)[0]

    # The loss is -mean log q(s, pi(s, z)) over every (state, noise) pair.
    repeated = np.repeat(s, noise_samples, axis=0)
    q, _ = learner.critic.forward((repeated, learner.policy.act(repeated, z)))
    np.testing.assert_allclose(loss(), -np.log(q).mean(), rtol=1e-12)

    _, grads, stats = offpac_il.policy_loss_and_grads(learner, s, z)
    assert stats["q_policy"] == pytest.approx(q.mean(), rel=1e-12)
    assert set(grads) == set(learner.policy.net.params)
    for name, param in learner.policy.net.params.items():
        assert_gradient_close(
            grads[name],
            numerical_gradient(loss, param, OBJECTIVE_EPS),
            OBJECTIVE_TOL,
            f"gradient (6) d/d{name}",
        )
    for name, value in learner.critic.params.items():  # the critic is not updated here
        np.testing.assert_array_equal(value, critic_before[name])


def test_policy_gradient_check_catches_a_wrong_gradient():
    """Dropping the tanh derivative (a common slip) is caught."""
    learner, _, rng = small_learner(2)
    s, z = rng.standard_normal((2, 3)), rng.standard_normal((6, 3))
    actions, policy_cache = learner.policy.forward(s, z)
    _, critic_cache = learner.critic.forward((s, actions))
    d_x = -(1 - critic_cache.output) / len(z)
    (_, d_actions), _ = learner.critic.backward(
        d_x, critic_cache, through_head=False, param_grads=False
    )
    _, wrong = learner.policy.net.backward(d_actions, policy_cache, through_head=False)

    def loss():
        return offpac_il.policy_loss_and_grads(learner, s, z)[0]

    numeric = numerical_gradient(loss, learner.policy.net.params["W1"], OBJECTIVE_EPS)
    right = offpac_il.policy_loss_and_grads(learner, s, z)[1]["W1"]
    assert_gradient_close(right, numeric, OBJECTIVE_TOL)
    with pytest.raises(AssertionError):
        assert_gradient_close(wrong["W1"], numeric, OBJECTIVE_TOL)


def test_policy_step_draws_noise_samples_per_state_and_moves_pn_only(monkeypatch):
    """One policy step: `noise_samples` z per state from the run's Generator, an RMSProp
    step on PN by gradient (6), QN untouched; the stats report the gradient's norm."""
    learner, config, rng = small_learner(5, noise_samples=3)
    states = rng.standard_normal((4, 3))
    before = copy.deepcopy(learner)
    stats = offpac_il.policy_step(learner, states, config, 1e-3, np.random.default_rng(8))
    noise = np.random.default_rng(8).standard_normal((4 * 3, 3), np.float32)
    _, grads, _ = offpac_il.policy_loss_and_grads(before, states, noise)
    before.policy_optimizer.step(before.policy.net.params, grads, 1e-3)
    for name, value in learner.policy.net.params.items():
        np.testing.assert_array_equal(value, before.policy.net.params[name])
    for name, value in learner.critic.params.items():
        np.testing.assert_array_equal(value, before.critic.params[name])
    norm = np.sqrt(sum((g**2).sum() for g in grads.values()))
    assert stats["policy_grad_norm"] == pytest.approx(norm, rel=1e-12)
    assert {"q_policy", "saturation"} <= set(stats)
    assert any(grads[name].any() for name in grads)


# ---------------------------------------------------------------------------------------
# The critic's targets t (Eq. 17-18), the termination treatments and the critic step.
# ---------------------------------------------------------------------------------------


def targets_and_continuation(learner, config, rng, targets=offpac_il.critic_targets):
    """`targets` (critic_targets) on 6 random triplets (3 expert, 3 replay; terminal s'
    included), and the same expectation written out: mean over 4 noise vectors of
    q'(s', a')^gamma, 0 at a terminal s' under zero continuation."""
    batch = random_triplets(rng, 6, terminal_fraction=0.5)
    batch.terminal[:2] = [True, False]
    from_replay = np.arange(6) >= 3
    t, stats = targets(learner, batch, 3, config, np.random.default_rng(9))
    assert stats == {}
    noise = np.random.default_rng(9).standard_normal((6 * 4, 3), np.float32)
    next_states = np.repeat(batch.next_states, 4, axis=0)
    next_actions = learner.policy.act(next_states, noise)
    q_next, _ = learner.target_critic.forward((next_states, next_actions))
    continuation = (q_next[:, 0] ** config.gamma).reshape(6, 4).mean(axis=1)
    if config.termination == "zero":
        continuation[batch.terminal] = 0.0
    return t, continuation, batch, from_replay


@pytest.mark.parametrize("termination", offpac_il.TERMINATIONS)
def test_critic_targets(termination):
    learner, config, rng = small_learner(3, termination=termination, target_samples=4)
    t, expected, _, from_replay = targets_and_continuation(learner, config, rng)
    expected[from_replay] /= 2
    np.testing.assert_allclose(t, expected, rtol=1e-10)
    assert np.all((t >= 0) & (t <= 1))


def test_critic_step_is_objective_18_then_the_target_update(monkeypatch):
    """critic_step: expert rows then replay rows, t from `targets`, one RMSProp step on
    (18), then nu' <- tau nu + (1 - tau) nu'. A variant's `targets` takes the place of
    critic_targets, and its stats join the step's."""
    learner, config, rng = small_learner(6, tau=0.25, target_samples=2)
    expert_rows, replay_rows = random_triplets(rng, 3), random_triplets(rng, 3)
    seen = {}

    def targets(learner, batch, n_expert, config, rng):
        seen["batch"], seen["n_expert"] = batch, n_expert
        return np.full(len(batch.states), 0.3), {"my_stat": 1.5}

    critic, target = learner.critic.copy(), learner.target_critic.copy()
    stats = offpac_il.critic_step(
        learner, expert_rows, replay_rows, config, 1e-3, rng, targets=targets
    )
    assert seen["n_expert"] == 3
    np.testing.assert_array_equal(
        seen["batch"].states, np.concatenate([expert_rows.states, replay_rows.states])
    )
    loss, grads, cache = offpac_il.critic_loss_and_grads(
        critic, seen["batch"], np.full((6, 1), 0.3), 3
    )
    nets.RMSProp(config.rmsprop_decay, config.rmsprop_eps).step(critic.params, grads, 1e-3)
    for name, value in learner.critic.params.items():
        np.testing.assert_allclose(value, critic.params[name], rtol=1e-12)
        expected = 0.25 * critic.params[name] + 0.75 * target.params[name]
        np.testing.assert_allclose(learner.target_critic.params[name], expected, rtol=1e-12)
    assert stats["critic_loss"] == pytest.approx(loss, rel=1e-12)
    assert stats["q_expert"] == pytest.approx(cache.output[:3].mean(), rel=1e-12)
    assert stats["q_replay"] == pytest.approx(cache.output[3:].mean(), rel=1e-12)
    assert stats["my_stat"] == 1.5


def test_triplets_take_sample_and_concatenated():
    rng = np.random.default_rng(0)
    triplets = random_triplets(rng, 5, terminal_fraction=0.5)
    taken = triplets.take(np.array([4, 0]))
    for field in dataclasses.fields(offpac_il.Triplets):
        np.testing.assert_array_equal(
            getattr(taken, field.name), getattr(triplets, field.name)[[4, 0]]
        )
    sampled = triplets.sample(np.random.default_rng(1), 7)
    index = np.random.default_rng(1).integers(0, 5, 7)
    np.testing.assert_array_equal(sampled.next_states, triplets.next_states[index])
    both = offpac_il.concatenated(taken, triplets)
    np.testing.assert_array_equal(
        both.terminal, np.concatenate([taken.terminal, triplets.terminal])
    )
    np.testing.assert_array_equal(both.actions[:2], taken.actions)


def test_replay_buffer_is_a_fifo_and_round_trips():
    replay = offpac_il.ReplayBuffer(3, 1, 1)
    for i in range(5):
        replay.add([i], [i / 10], [i + 1], i == 4)
    assert (replay.size, replay.next_index) == (3, 2)
    assert sorted(replay.data.states[:, 0].tolist()) == [2.0, 3.0, 4.0]  # 0 and 1 went
    assert replay.data.terminal.tolist() == [False, True, False]
    copy = offpac_il.ReplayBuffer(3, 1, 1)
    copy.load_state(replay.state())
    assert (copy.size, copy.next_index) == (3, 2)
    for field in dataclasses.fields(offpac_il.Triplets):
        np.testing.assert_array_equal(
            getattr(copy.data, field.name), getattr(replay.data, field.name)
        )
    assert set(replay.sample(np.random.default_rng(0), 50).states[:, 0]) == {2.0, 3.0, 4.0}


def test_learner_state_round_trips_and_copies_are_independent():
    learner, config, rng = small_learner(7, dtype=np.float32)
    offpac_il.policy_step(learner, rng.standard_normal((2, 3)), config, 1e-3, rng)  # RMSProp state
    arrays = learner.state()
    assert {"policy/W0", "critic/W0", "target_critic/W0", "average_policy/W0"} <= set(arrays)
    assert "policy_rmsprop/W0" in arrays
    other, _, _ = small_learner(8, dtype=np.float32)
    other.load_state(arrays)
    for key, value in other.state().items():
        np.testing.assert_array_equal(value, arrays[key])
    copy = learner.policy.copy()
    copy.net.params["W0"] += 1.0
    assert not np.array_equal(copy.net.params["W0"], learner.policy.net.params["W0"])
    assert learner.policy.samples_per_state(128) == 128


@pytest.mark.parametrize("fraction", [0.0, 0.5, 1.0])
def test_policy_expert_states_fraction(monkeypatch, fraction):
    """--policy-expert-states draws that share of the policy step's states from B_pi_E."""
    learner, config, rng = small_learner(
        4, policy_expert_states=fraction, batch_size=8, noise_samples=2, target_samples=2
    )
    expert_buffer = random_triplets(rng, 20)
    replay = offpac_il.ReplayBuffer(50, 3, 2)
    for _ in range(30):
        replay.add(rng.standard_normal(3) + 100.0, rng.uniform(-1, 1, 2), np.zeros(3), False)
    seen = {}

    def capture(learner, states, config, lr, rng):
        seen["states"] = states
        return {}

    monkeypatch.setattr(offpac_il, "policy_step", capture)
    offpac_il.update(learner, expert_buffer, replay, config, 0, rng)
    from_expert = (np.abs(seen["states"]) < 50).all(axis=1)  # replay states sit near 100
    assert from_expert.sum() == round(fraction * 8)


def test_update_decays_the_learning_rates_linearly_and_uses_the_variants_critic_step(
    monkeypatch,
):
    """Alg. 1, lines 11-14 at interactions n of a budget N: the critic step at
    critic_lr (1 - n/N), the policy step at policy_lr (1 - n/N), each once."""
    learner, config, rng = small_learner(9, total_steps=1000, batch_size=4)
    replay = offpac_il.ReplayBuffer(10, 3, 2)
    for _ in range(5):
        replay.add(*(x[0] for x in dataclasses.astuple(random_triplets(rng, 1))))
    calls = []

    def critic_step(learner, expert_batch, replay_batch, config, lr, rng):
        calls.append(("critic", lr, len(expert_batch.states), len(replay_batch.states)))
        return {"critic_loss": 0.0}

    def policy_step(learner, states, config, lr, rng):
        calls.append(("policy", lr, len(states)))
        return {"q_policy": 0.5}

    monkeypatch.setattr(offpac_il, "policy_step", policy_step)
    variant = offpac_il.Variant(critic_step=critic_step)
    stats = offpac_il.update(learner, random_triplets(rng, 6), replay, config, 250, rng, variant)
    assert calls == [
        ("critic", 0.75 * config.critic_lr, 4, 4),
        ("policy", 0.75 * config.policy_lr, 4),
    ]
    assert stats == {"critic_loss": 0.0, "q_policy": 0.5}


# ---------------------------------------------------------------------------------------
# Acting and evaluating.
# ---------------------------------------------------------------------------------------


def test_action_scaling_round_trip():
    spaces = offpac_il.Spaces(
        np.array([-0.4, 0.0]), np.array([0.4, 2.0]), np.zeros(2), np.ones(2), absorbing=False
    )
    a = np.array([[-1.0, 1.0], [0.0, 0.5]])
    env_a = spaces.to_env_action(a)
    np.testing.assert_allclose(env_a, [[-0.4, 2.0], [0.0, 1.5]])
    np.testing.assert_allclose(spaces.from_env_action(env_a), a, atol=1e-6)
    assert spaces.from_env_action(np.array([9.0, -9.0])).tolist() == [1.0, -1.0]


def hopper_learner(config):
    """An untrained Hopper-v4 learner and its spaces (zero demonstrations: no scaling)."""
    import expert

    env = expert.make_env("Hopper-v4", max_episode_steps=config.total_steps)
    zeros = np.zeros((2, 11), np.float32)
    demos = expert.Demos(zeros, np.zeros((2, 3), np.float32), zeros, np.zeros(2, bool))
    spaces = offpac_il.make_spaces(env, demos, config)
    rng = np.random.default_rng(0)
    policy = offpac_il.BoundedPolicy.create(11, 11, 3, config, rng)
    return env, spaces, offpac_il.Learner.create(policy, 11, 3, config, rng)


def test_critic_input_grad_diagnostic_is_half_the_squared_input_gradient():
    """The progress column critic_input_grad: 1/2 mean_n ||dx_n/d[s_n, a_n]||^2 at the
    expert's states and the policy's actions there, against finite differences of x."""
    learner, _, rng = small_learner(3)
    expert = random_triplets(rng, 4)
    diagnostics = offpac_il.imitation_diagnostics(learner, expert, np.random.default_rng(0))
    noise = np.random.default_rng(0).standard_normal((4, learner.policy.noise_dim), np.float32)
    inputs = np.concatenate([expert.states, learner.policy.act(expert.states, noise)], axis=1)
    squared = []
    for row in inputs:

        def logit(row=row):
            return float(learner.critic.forward(row[None])[1].logits[0, 0])

        squared.append((numerical_gradient(logit, row) ** 2).sum())
    assert diagnostics["critic_input_grad"] == pytest.approx(0.5 * np.mean(squared), rel=1e-6)


def test_policy_noise_spread_is_how_much_the_action_moves_with_z():
    """It grows with PN's weights on z, the rows of the first layer that read the noise."""
    rng = np.random.default_rng(0)
    expert = random_triplets(rng, 5)

    def spread(learner):
        diagnostics = offpac_il.imitation_diagnostics(learner, expert, np.random.default_rng(1))
        return diagnostics["policy_noise_spread"]

    learner = small_learner(3)[0]
    before = spread(learner)
    learner.policy.net.params["W0"][3:] *= 3.0  # the rows of W0 that read z (state_dim = 3)
    assert 0.0 < before < spread(learner)


def test_rows_written_before_a_column_existed_leave_it_blank():
    later = ("critic_input_grad", "policy_noise_spread", "eval_falls")
    old = {name: 1.0 for name in offpac_il.PROGRESS_FIELDS if name not in later}
    new = {name: 2.0 for name in offpac_il.PROGRESS_FIELDS}
    header, first, second = harness.progress_csv([old, new], offpac_il.PROGRESS_FIELDS).splitlines()
    assert header.split(",") == list(offpac_il.PROGRESS_FIELDS)
    assert first.split(",")[-3:] == ["", "", ""] and second.split(",")[-3:] == ["2.0"] * 3


@pytest.mark.parametrize("time_limit, falls", [(1000, 3), (4, 0)])
def test_evaluation_counts_the_episodes_that_fell(time_limit, falls):
    """An untrained Hopper falls within a few dozen steps: with the 1000-step limit every
    episode ends by a fall; cut off by a 4-step limit first, none does."""
    config = offpac_il.Config(
        policy_hidden=(4, 4), critic_hidden=(4, 4), eval_episodes=3, total_steps=time_limit
    )
    env, spaces, learner = hopper_learner(config)
    returns, counted = offpac_il.evaluate(env, learner, spaces, config, round_index=0)
    assert returns.shape == (3,) and counted == falls


def test_exploration_noise_is_executed_and_stored():
    """With --exploration-noise sigma, step t executes and stores
    clip(pi(s_t, z_t) + sigma * eps_t, -1, 1), z_t and eps_t drawn in turn from the
    run's Generator; with sigma = 0 no eps is drawn and pi(s_t, z_t) is used."""
    config = offpac_il.Config(policy_hidden=(4, 4), critic_hidden=(4, 4), total_steps=1000)
    env, spaces, learner = hopper_learner(config)
    executed = []
    step = env.step
    env.step = lambda a: executed.append(a) or step(a)
    for sigma in (0.0, 0.5):
        replay, executed[:] = offpac_il.ReplayBuffer(2000, 11, 3), []
        _, length = offpac_il.run_episode(
            env, learner, spaces, np.random.default_rng(1), 0, replay, sigma
        )
        draws, expected = np.random.default_rng(1), []
        for state in replay.data.states[:length]:
            noise = draws.standard_normal((1, 11), np.float32)
            action = learner.policy.act(state[None], noise)[0]
            if sigma:
                action = np.clip(action + sigma * draws.standard_normal(3, np.float32), -1, 1)
            expected.append(action)
        stored = replay.data.actions[:length]
        np.testing.assert_array_equal(stored, np.array(expected))
        np.testing.assert_allclose(np.array(executed), spaces.to_env_action(stored), rtol=1e-6)
    assert np.abs(stored).max() == 1.0  # sigma = 0.5 pushes some components to the bound


def test_prepare_draws_pn_then_qn_from_the_runs_generator(hopper_demos):
    """prepare: B_pi_E from the demonstrations in the networks' units, a learner whose PN
    and QN are the first draws of the Generator (in that order), an empty B_beta."""
    import expert

    config = offpac_il.Config(**SMALL, demos=str(hopper_demos), replay_size=50)
    env = expert.make_env("Hopper-v4")
    spaces, expert_buffer, learner, replay, loaded = offpac_il.prepare(
        config, env, np.random.default_rng(4)
    )
    demos = expert.load_demos(hopper_demos, "Hopper-v4")
    assert loaded.path == Path(hopper_demos) and replay.size == 0 and replay.capacity == 50
    np.testing.assert_array_equal(expert_buffer.states, spaces.state(demos.observations))
    np.testing.assert_array_equal(expert_buffer.actions, spaces.from_env_action(demos.actions))
    rng = np.random.default_rng(4)
    policy = offpac_il.BoundedPolicy.create(11, 11, 3, config, rng)
    expected = offpac_il.Learner.create(policy, 11, 3, config, rng)
    for key, value in expected.state().items():
        np.testing.assert_array_equal(learner.state()[key], value)
    assert learner.policy.noise_dim == 11  # dim z = dim s (Appendix B)


# ---------------------------------------------------------------------------------------
# The command line, end to end on Hopper-v4 with small networks.
# ---------------------------------------------------------------------------------------

TINY_RUN = [
    "--env",
    "Hopper-v4",
    "--total-steps",
    "300",
    "--eval-every",
    "100",
    "--eval-episodes",
    "1",
    "--policy-hidden",
    "8",
    "8",
    "--critic-hidden",
    "16",
    "16",
    "--noise-samples",
    "4",
    "--target-samples",
    "2",
    "--batch-size",
    "8",
    "--checkpoint-every",
    "0",
    "--log-every",
    "0",
]


def run_cli(*args, check=True):
    return run_script("offpac_il.py", *args, check=check)


def read_progress(run_dir: Path) -> list[dict]:
    return read_rows(run_dir / "progress.csv")


def parse(argv, config_class=offpac_il.Config):
    """(config, resume) as `python offpac_il.py argv` reads them."""
    return harness.config_from_command_line(
        [str(a) for a in argv],
        config_class,
        "",
        offpac_il.PAPER_SETTINGS,
        offpac_il.RESUMABLE_CHANGES,
    )


def tiny_config(run_dir: Path, demos: Path, seed=0, extra=(), config_class=offpac_il.Config):
    """The Config of TINY_RUN with `extra` flags, as the command line makes it."""
    argv = [*TINY_RUN, *extra, "--demos", demos, "--seed", seed, "--run-dir", run_dir]
    config, resume = parse(argv, config_class)
    assert not resume
    return config


def no_run_files(run_dir: Path) -> bool:
    """Nothing of a run was written: no directory, or one holding at most its lock file
    (the lock comes first, so that two processes never write one run)."""
    return not run_dir.exists() or {p.name for p in run_dir.iterdir()} <= {harness.LOCK}


def test_command_line_run_writes_its_files(tmp_path, hopper_demos):
    run_dir = tmp_path / "run"
    result = run_cli(*TINY_RUN, "--demos", hopper_demos, "--run-dir", run_dir)
    for name in (
        "config.json",
        "progress.csv",
        "checkpoint.npz",
        "policy_best.npz",
        "policy_final.npz",
        "policy_average.npz",
    ):
        assert (run_dir / name).is_file(), name
    rows = read_progress(run_dir)
    assert all(int(r["interactions"]) >= 100 * i for i, r in enumerate(rows))
    assert int(rows[-1]["interactions"]) >= 300
    fields = (*offpac_il.PROGRESS_FIELDS, *offpac_il.AVERAGE_FIELDS, *offpac_il.HANDOVER_FIELDS)
    assert list(rows[0]) == [f for f in fields if f != "wall_seconds"]
    assert all(np.isfinite(float(r["normalized_score"])) for r in rows)
    assert "eval" in result.stdout
    snapshots = sorted((run_dir / offpac_il.SNAPSHOTS).glob("*.npz"))
    assert [int(p.stem) for p in snapshots] == [int(r["interactions"]) for r in rows]
    assert not list(run_dir.rglob("*.tmp"))
    config = json.loads((run_dir / "config.json").read_text())
    assert config["run_dir"] == str(run_dir) and config["policy_hidden"] == [8, 8]
    # A second start in the same directory is refused rather than overwriting the run.
    again = run_cli(*TINY_RUN, "--demos", hopper_demos, "--run-dir", run_dir, check=False)
    assert again.returncode == 2 and "--resume" in again.stderr


def test_resume_reproduces_an_uninterrupted_run(tmp_path, hopper_demos, monkeypatch):
    offpac_il.train(tiny_config(tmp_path / "whole", hopper_demos))
    same_seed = tmp_path / "again"
    offpac_il.train(tiny_config(same_seed, hopper_demos))
    other_seed = tmp_path / "other"
    offpac_il.train(tiny_config(other_seed, hopper_demos, seed=1))

    interrupted = tmp_path / "interrupted"
    with monkeypatch.context() as patch:
        patch.setattr(offpac_il, "run_episode", interrupted_after(3))
        with pytest.raises(KeyboardInterrupt):
            offpac_il.train(tiny_config(interrupted, hopper_demos))
    partial = read_progress(interrupted)
    assert 0 < int(partial[-1]["interactions"]) < 300
    offpac_il.train(tiny_config(interrupted, hopper_demos), resume=True)

    whole = read_progress(tmp_path / "whole")
    # Resuming a finished run adds nothing.
    offpac_il.train(tiny_config(tmp_path / "whole", hopper_demos), resume=True)
    assert read_progress(tmp_path / "whole") == whole
    assert read_progress(same_seed) == whole
    assert read_progress(other_seed) != whole
    assert read_progress(interrupted) == whole


def test_a_disk_that_fills_mid_run_is_one_line_and_the_run_resumes_exactly(
    tmp_path, hopper_demos, monkeypatch, capsys
):
    """The third checkpoint write fails with ENOSPC, as on a full disk, halfway through
    the file: one line, exit status 2, the second checkpoint kept whole and no temporary
    left; freed, --resume ends with the rows of a run that never stopped."""
    args = [*TINY_RUN, "--demos", str(hopper_demos)]
    whole = tmp_path / "whole"
    run_cli(*args, "--run-dir", whole)
    run_dir = tmp_path / "full"
    real_savez, checkpoints = np.savez, []

    def savez(file, **arrays):
        if "rows" in arrays:  # a checkpoint, not a policy
            checkpoints.append(json.loads(str(arrays["counters"]))["interactions"])
            if len(checkpoints) == 3:
                file.write(b"half a checkpoint")
                raise OSError(errno.ENOSPC, "No space left on device", str(file.name))
        return real_savez(file, **arrays)

    with monkeypatch.context() as patch:
        patch.setattr(np, "savez", savez)
        status = offpac_il.main([*args, "--run-dir", str(run_dir)])
    release(run_dir)
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1, err
    assert err[0].startswith("error: disk full writing") and "--resume" in err[0]
    kept = json.loads(str(harness.load_arrays(run_dir / "checkpoint.npz")["counters"]))
    assert kept["interactions"] == checkpoints[1] < checkpoints[2]
    assert not [p.name for p in run_dir.iterdir() if p.name.endswith(".tmp")]
    run_cli("--resume", run_dir)
    assert read_progress(run_dir) == read_progress(whole)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # NaN through the networks
def test_a_run_whose_networks_went_non_finite_stops_at_its_next_evaluation(
    tmp_path, hopper_demos, monkeypatch
):
    """One line naming the array and when; the checkpoint before it is kept."""
    update = offpac_il.update

    def poisoned(learner, *args):
        stats = update(learner, *args)
        learner.critic.params["W1"][0, 0] = np.nan
        return stats

    monkeypatch.setattr(offpac_il, "update", poisoned)
    monkeypatch.chdir(tmp_path)  # MuJoCo logs the NaN actions to MUJOCO_LOG.TXT there
    run_dir = tmp_path / "run"
    with pytest.raises(harness.UserError) as error:
        offpac_il.train(tiny_config(run_dir, hopper_demos))
    message = "(policy|critic)/W[01] became non-finite by [1-9][0-9]* interactions; the last"
    assert re.match(message, str(error.value)), error.value
    checkpoint = harness.load_arrays(run_dir / "checkpoint.npz")
    assert np.isfinite(checkpoint["critic/W1"]).all()
    assert [r["interactions"] for r in read_progress(run_dir)] == ["0"]


def test_restore_gives_back_the_checkpoints_learner(tmp_path, hopper_demos):
    from lab import experiments

    offpac_il.train(tiny_config(tmp_path / "run", hopper_demos))
    _, _, _, learner, replay, progress = experiments.restored(tmp_path / "run")
    assert progress.interactions >= 300 and replay.size == progress.interactions
    saved = harness.load_arrays(tmp_path / "run" / "policy_final.npz")
    for name, value in learner.policy.state().items():
        np.testing.assert_array_equal(value, saved[name])
    checkpoint = harness.load_arrays(tmp_path / "run" / "checkpoint.npz")
    for name, value in learner.state().items():
        np.testing.assert_array_equal(value, checkpoint[name])


def test_policy_average_is_evaluated_beside_pn_and_changes_nothing_else(
    tmp_path, hopper_demos, monkeypatch
):
    """--policy-average r: after each update theta_avg <- r theta + (1 - r) theta_avg;
    training (episodes, updates, PN's evaluation) is the run without the flag, row for
    row; the averaged PN is evaluated on the same episode seeds and resumes exactly."""
    plain = tmp_path / "plain"
    offpac_il.train(tiny_config(plain, hopper_demos, extra=["--policy-average", "0"]))
    averaged = tmp_path / "averaged"
    offpac_il.train(tiny_config(averaged, hopper_demos, extra=["--policy-average", "0.05"]))
    rows, plain_rows = read_progress(averaged), read_progress(plain)
    own = offpac_il.AVERAGE_FIELDS + offpac_il.HANDOVER_FIELDS
    assert [{k: v for k, v in row.items() if k not in own} for row in rows] == [
        {k: v for k, v in row.items() if k not in own} for row in plain_rows
    ]
    # The hand-over column names the policy a user gets, and scores it.
    assert {(r["handover"], r["handover_score"]) for r in rows} == {
        ("policy_average.npz", r["average_score"]) for r in rows
    }
    assert {r["handover"] for r in plain_rows} == {"policy_final.npz"}
    for r in plain_rows:  # normalized_score is rounded to 4 decimals, measurements to 5 digits
        assert abs(float(r["handover_score"]) - float(r["normalized_score"])) <= 5e-5
    assert not (plain / "policy_average.npz").exists()
    # At the start the average is PN itself: the same episodes, the same return.
    assert rows[0]["average_return_mean"] == rows[0]["eval_return_mean"]
    assert rows[-1]["average_return_mean"] != rows[-1]["eval_return_mean"]
    assert {int(r["average_falls"]) for r in rows} <= set(range(2))
    saved = harness.load_arrays(averaged / "policy_average.npz")
    checkpoint = harness.load_arrays(averaged / "checkpoint.npz")
    for name, value in saved.items():
        np.testing.assert_array_equal(value, checkpoint[name.replace("policy", "average_policy")])

    # The update rule, on one update.
    learner, config, rng = small_learner(4, policy_average=0.25, batch_size=3)
    before = {k: v.copy() for k, v in learner.average_policy.net.params.items()}
    replay = offpac_il.ReplayBuffer(10, 3, 2)
    for row in range(5):
        replay.add(*(x[row] for x in dataclasses.astuple(random_triplets(rng, 5))))
    offpac_il.update(learner, random_triplets(rng, 4), replay, config, 0, rng)
    for name, value in learner.average_policy.net.params.items():
        expected = 0.75 * before[name] + 0.25 * learner.policy.net.params[name]
        np.testing.assert_allclose(value, expected)

    # A killed run resumes to the same rows, averaged PN included.
    interrupted = tmp_path / "interrupted"
    flags = ["--policy-average", "0.05"]
    with monkeypatch.context() as patch:
        patch.setattr(offpac_il, "run_episode", interrupted_after(3))
        with pytest.raises(KeyboardInterrupt):
            offpac_il.train(tiny_config(interrupted, hopper_demos, extra=flags))
    offpac_il.train(tiny_config(interrupted, hopper_demos, extra=flags), resume=True)
    assert read_progress(interrupted) == rows


def test_kill_and_resume_from_the_command_line(tmp_path, hopper_demos):
    run_dir = tmp_path / "run"
    process = subprocess.Popen(
        [
            sys.executable,
            str(ROOT / "offpac_il.py"),
            *TINY_RUN,
            "--demos",
            str(hopper_demos),
            "--run-dir",
            str(run_dir),
        ],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    # Kill -9 as soon as the first checkpoint exists (the run may be anywhere after it).
    deadline = time.time() + 300
    while not (run_dir / "checkpoint.npz").exists() and time.time() < deadline:
        time.sleep(0.05)
    process.kill()
    process.wait()
    run_cli("--resume", run_dir)
    whole = tmp_path / "whole"
    run_cli(*TINY_RUN, "--demos", hopper_demos, "--run-dir", whole)
    assert read_progress(run_dir) == read_progress(whole)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--env", "CartPole-v1"], "action space"),
        (["--env", "NoSuchEnv-v0"], "NoSuchEnv-v0"),
        (["--termination", "sometimes"], "--termination"),
        (["--sampling", "often"], "--sampling"),
        (["--reward-learning", "gail"], "--reward-learning"),  # an ablation's: lab/ablations
        (["--resume", "/nonexistent/run"], "/nonexistent/run"),
        (["--paper", "--resume", "/nonexistent/run"], "--paper"),
        (["--bogus-flag"], "--bogus-flag"),
        (["--seed", "many"], "--seed"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, args, message):
    result = run_cli(*args, "--run-dir", tmp_path / "r", check=False)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0]
    assert no_run_files(tmp_path / "r")


def test_bad_demo_file_is_refused(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"PK\x03\x04 truncated")
    result = run_cli("--demos", bad, "--run-dir", tmp_path / "r", check=False)
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1 and str(bad) in result.stderr
    assert no_run_files(tmp_path / "r")


def test_paper_flag_restores_appendix_b_and_explicit_flags_win():
    defaults, _ = parse([])
    assert defaults.policy_expert_states == 0.5 and defaults.policy_lr == 2.3e-5
    paper, _ = parse(["--paper"])
    for name, value in offpac_il.PAPER_SETTINGS.items():
        assert getattr(paper, name) == value
    assert (paper.policy_lr, paper.critic_lr, paper.policy_expert_states) == (1e-4, 1e-3, 0.0)
    assert paper.policy_average == 0.0
    mixed, _ = parse(["--critic-lr", "5e-4", "--paper"])
    assert (mixed.critic_lr, mixed.policy_lr) == (5e-4, 1e-4)
    assert paper.noise_samples == defaults.noise_samples == 128  # gradient (6) as specified


def test_a_config_saved_before_a_setting_existed_keeps_the_papers_behaviour():
    """config.json of an old run lacks policy_expert_states: that run drew its policy
    states from the replay only, and must resume (and be labelled) that way. Settings
    the code no longer has (critic_reg, removed as measured not to help) are dropped."""
    saved = dataclasses.asdict(offpac_il.Config(policy_lr=1e-4, critic_lr=1e-3))
    del saved["policy_expert_states"], saved["policy_average"]
    saved["policy_hidden"] = list(saved["policy_hidden"])  # as JSON gives it back
    saved["critic_reg"] = 0.0
    config = harness.saved_config(offpac_il.Config, saved, offpac_il.PAPER_SETTINGS)
    assert config.policy_expert_states == 0.0
    assert config.policy_average == 0.0  # and its checkpoint holds no averaged PN
    assert config.policy_hidden == (100, 100)
    saved["policy_expert_states"] = 0.5
    config = harness.saved_config(offpac_il.Config, saved, offpac_il.PAPER_SETTINGS)
    assert config.policy_expert_states == 0.5


def test_resume_takes_the_saved_settings_and_a_new_budget(tmp_path):
    saved = dataclasses.asdict(offpac_il.Config(seed=3, run_dir=str(tmp_path)))
    harness.write_config(tmp_path, saved)
    config, resume = parse(["--resume", tmp_path, "--total-steps", "7", "--seed", "3"])
    assert resume and (config.seed, config.total_steps, config.run_dir) == (3, 7, str(tmp_path))
    for allowed in offpac_il.RESUMABLE_CHANGES:
        assert allowed in {f.name for f in dataclasses.fields(offpac_il.Config)}
    with pytest.raises(harness.UserError, match="--seed conflicts"):
        parse(["--resume", tmp_path, "--seed", "4"])


# ---------------------------------------------------------------------------------------
# lab/experiments.py's tools on a learner run. They read the run as experiments.restored
# gives it back.
# ---------------------------------------------------------------------------------------


def test_restore_and_the_critic_probe(tmp_path, hopper_demos, monkeypatch):
    """`experiments.probe_critic` compares the critic at the expert's and the policy's
    actions. Checked with stand-in experts whose action is the policy's own (no
    difference), and the policy's moved a small step along d log q / da (cosine 1,
    expert action preferred everywhere)."""
    import expert
    from lab import experiments

    offpac_il.train(tiny_config(tmp_path / "run", hopper_demos))
    _, spaces, _, learner, _, _ = experiments.restored(tmp_path / "run")

    def policy_action(observation):
        state = spaces.state(observation)[None]
        return learner.policy.act(state, np.zeros((1, learner.policy.noise_dim), np.float32))

    def along_gradient(observation):
        action = policy_action(observation)
        state = spaces.state(observation)[None]
        q, cache = learner.critic.forward((state, action))
        grad = learner.critic.backward(1.0 - q, cache, through_head=False, param_grads=False)
        step = grad[0][1] / np.linalg.norm(grad[0][1])
        return spaces.to_env_action(np.clip(action + 1e-3 * step, -1, 1))[0]

    class StandIn:
        def __init__(self, act):
            self.act = act

    monkeypatch.setattr(
        expert,
        "load_expert",
        lambda env_id: StandIn(lambda o: spaces.to_env_action(policy_action(o))[0]),
    )
    (same,) = experiments.probe_critic(tmp_path / "run", episodes=1, steps=20)
    assert same["squared_distance"] < 1e-10  # up to the round trip through env units
    assert same["q_at_expert_action"] == pytest.approx(same["q_at_policy_action"], rel=1e-5)
    monkeypatch.setattr(expert, "load_expert", lambda env_id: StandIn(along_gradient))
    (better,) = experiments.probe_critic(tmp_path / "run", episodes=1, steps=20)
    assert 0 < better["steps"] <= 20
    assert better["gradient_cosine"] > 0.99 and better["expert_action_preferred"] == 1.0


def test_evaluate_plays_the_saved_policy_from_new_starts(tmp_path, hopper_demos):
    """`experiments.evaluate_policy` plays the run's policy file, episode i from reset
    seed `seed + i` with noise from a Generator seeded by `seed`, as run_episode does
    with the restored learner, and says which episodes fell."""
    import expert
    from lab import experiments

    offpac_il.train(tiny_config(tmp_path / "run", hopper_demos, extra=["--policy-average", "0.05"]))
    rows = experiments.evaluate_policy(tmp_path / "run", "final", episodes=3, seed=7)
    assert rows == experiments.evaluate_policy(tmp_path / "run", "checkpoint", 3, seed=7)
    _, spaces, _, learner, _, _ = experiments.restored(tmp_path / "run")
    env, rng = expert.make_env("Hopper-v4"), np.random.default_rng(7)
    random_return, expert_return = expert.reference_returns("Hopper-v4")
    for i, row in enumerate(rows):
        total, length = offpac_il.run_episode(env, learner, spaces, rng, 7 + i)
        assert (row["seed"], row["return"], row["length"]) == (7 + i, round(total, 1), length)
        assert row["fell"] == (length < 1000)
        assert row["normalized_score"] == pytest.approx(
            (total - random_return) / (expert_return - random_return)
        )
    # One snapshot per evaluation, the last one the final policy.
    rows_of_run = read_progress(tmp_path / "run")
    snapshots = sorted((tmp_path / "run" / offpac_il.SNAPSHOTS).glob("*.npz"))
    assert [int(p.stem) for p in snapshots] == [int(r["interactions"]) for r in rows_of_run]
    last = experiments.evaluate_policy(tmp_path / "run", snapshots[-1].stem, 3, seed=7)
    assert last == rows
    table = experiments.evaluate_snapshots(tmp_path / "run", episodes=3, seed=7)
    assert [row["interactions"] for row in table] == [int(p.stem) for p in snapshots]
    scores = [row["normalized_score"] for row in rows]
    assert table[-1]["normalized_score"] == pytest.approx(np.mean(scores))
    assert (table[-1]["lowest"], table[-1]["fell"]) == (min(scores), sum(r["fell"] for r in rows))
    # The averaged PN plays differently; so does a different policy in the file.
    assert experiments.evaluate_policy(tmp_path / "run", "average", 3, seed=7) != rows
    arrays = harness.load_arrays(tmp_path / "run" / "policy_final.npz")
    harness.save_arrays(
        tmp_path / "run" / "policy_final.npz", {k: 2 * v for k, v in arrays.items()}
    )
    assert experiments.evaluate_policy(tmp_path / "run", "final", 3, seed=7) != rows


def test_action_error_along_the_experts_episodes(tmp_path, hopper_demos, monkeypatch):
    """`experiments.action_error_along_expert` bins the saved policy's squared action
    error by time step along the expert's episodes. Checked with the policy made blind to
    z and stand-in experts: one that acts as that policy (no error), and one that departs
    from it by 0.1 per component from step 5 on (0 in the first bin, 0.01 after)."""
    import expert
    from lab import experiments

    run = tmp_path / "run"
    offpac_il.train(tiny_config(run, hopper_demos))
    arrays = harness.load_arrays(run / "policy_final.npz")
    state_dim = arrays["policy/W0"].shape[0] // 2  # PN's input is [s, z], dim z = dim s
    arrays["policy/W0"][state_dim:] = 0.0  # now pi(s, z) = pi(s, 0)
    harness.save_arrays(run / "policy_final.npz", arrays)
    _, _, spaces, expert_buffer, _, learner = experiments.learner_of_run(run)
    experiments.load_policy(learner, run / "policy_final.npz")

    def policy_action(observation):  # in [-1, 1] units
        state = spaces.state(observation)[None]
        return learner.policy.act(state, np.zeros((1, state_dim), np.float32))[0]

    class StandIn:
        def __init__(self, departure):
            self.departure, self.steps = departure, 0

        def act(self, observation):
            action = policy_action(observation)
            action = action - (self.steps >= 5) * self.departure * np.sign(action)
            self.steps += 1
            return spaces.to_env_action(action[None])[0]

    def table(departure):
        monkeypatch.setattr(expert, "load_expert", lambda env_id: StandIn(departure))
        return experiments.action_error_along_expert(run, "final", 1, 7, edges=(0, 5, 1000))

    same, departing = table(0.0), table(0.1)
    assert [row["steps"] for row in same] == ["0-5", "5-1000", "demonstrated"]
    assert same[0]["states"] == 5 and same[1]["states"] >= 1  # the episode outlives step 5
    assert same[0]["squared_error"] < 1e-10 and same[1]["squared_error"] < 1e-10
    assert departing[0]["squared_error"] < 1e-10
    assert departing[1]["squared_error"] == pytest.approx(0.01, rel=1e-4)
    zero = np.zeros((len(expert_buffer.states), state_dim), np.float32)
    chosen = learner.policy.act(expert_buffer.states, zero)
    at_demos = ((chosen - expert_buffer.actions) ** 2).mean()
    assert same[-1]["states"] == len(expert_buffer.states)
    assert same[-1]["squared_error"] == pytest.approx(at_demos, rel=1e-5)


def test_exponential_averages_are_the_polyak_average_seen_at_the_snapshots():
    """`experiments.exponential_averages`: after a gap of t interactions the old average
    keeps exp(-t / horizon) of its weight, as t soft updates at rate 1 / horizon towards
    a fixed PN would leave it; z_0 is never averaged; dtypes are kept."""
    from lab import experiments

    rng = np.random.default_rng(0)
    first, second = (
        {"policy/w": rng.normal(size=(3, 2)).astype(np.float32), "policy/fixed_noise": z}
        for z in (np.zeros(2, np.float32), np.ones(2, np.float32))
    )
    horizon, gap = 10_000.0, 5_000
    start, after = experiments.exponential_averages([(0, first), (gap, second)], horizon)
    np.testing.assert_array_equal(start["policy/w"], first["policy/w"])
    kept = np.exp(-gap / horizon)
    expected = kept * first["policy/w"] + (1 - kept) * second["policy/w"]
    np.testing.assert_allclose(after["policy/w"], expected, rtol=1e-5)
    np.testing.assert_array_equal(after["policy/fixed_noise"], second["policy/fixed_noise"])
    assert after["policy/w"].dtype == np.float32

    initial = nets.MLP.create([3, 2], "identity", np.random.default_rng(1), np.float64)
    policy = nets.MLP.create([3, 2], "identity", np.random.default_rng(2), np.float64)
    average = initial.copy()
    for _ in range(gap):
        nets.soft_update(average, policy, 1 / horizon)
    snapshots = [(0, initial.state("policy")), (gap, policy.state("policy"))]
    offline = experiments.exponential_averages(snapshots, horizon)[-1]
    for name, online in average.state("policy").items():
        np.testing.assert_allclose(offline[name], online, atol=1e-4)  # (1 - 1/h)^t ~ e^(-t/h)


def test_averaged_snapshots_with_a_tiny_horizon_play_the_snapshots(tmp_path, hopper_demos):
    """`experiments.averaged_snapshots`: one row per snapshot; a horizon far shorter than
    the gap between snapshots averages nothing, so it scores what PN scored."""
    from lab import experiments

    offpac_il.train(tiny_config(tmp_path / "run", hopper_demos))
    rows = experiments.averaged_snapshots(tmp_path / "run", [1e-9, 1e15], episodes=2, seed=7)
    snapshots = sorted((tmp_path / "run" / offpac_il.SNAPSHOTS).glob("*.npz"))
    assert [row["interactions"] for row in rows] == [int(p.stem) for p in snapshots]
    for row in rows:
        assert (row["h1e-09_score"], row["h1e-09_fell"]) == (row["pn_score"], row["pn_fell"])
    # A horizon far longer than the run keeps the initial PN throughout.
    assert len({row["h1e+15_score"] for row in rows}) == 1
    assert rows[0]["h1e+15_score"] == rows[0]["pn_score"]


def test_gradient_noise_separates_the_noise_part_of_gradient_6(tmp_path, hopper_demos):
    """`experiments.gradient_noise`: with the states fixed, what varies is the mean over
    Z noise rows, whose variance shrinks as 1/Z (a deterministic policy has none:
    test_ablations.py)."""
    from lab import experiments

    offpac_il.train(tiny_config(tmp_path / "stochastic", hopper_demos))
    low, high = experiments.gradient_noise(tmp_path / "stochastic", samples=(2, 32), draws=40)
    assert (low["noise_samples"], high["noise_samples"]) == (2, 32)
    assert 0 < high["noise_variance"] < low["noise_variance"]
    assert 8 < low["noise_variance"] / high["noise_variance"] < 32  # 16 in expectation
    for row in (low, high):
        assert (
            0 < row["noise_share"] == pytest.approx(row["noise_variance"] / row["total_variance"])
        )
        assert 0 < row["mean_step_fraction"] <= 1  # |E g| <= sqrt(E g^2)
