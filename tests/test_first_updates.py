"""lab/first_updates.py, the probe of a run's first updates: its bias-corrected RMSProp,
its behavioural-cloning start (the gradient against finite differences, and the check
shown to catch a wrong one), and one short probe of each start on Hopper-v4."""

from __future__ import annotations

import numpy as np
import pytest
from gradcheck import assert_gradient_close, numerical_gradient
from helpers import assert_one_line_error, run_module
from hypothesis import assume, given
from hypothesis import strategies as st
from test_offpac_il import OBJECTIVE_EPS, OBJECTIVE_TOL, away_from_kinks, small_learner

import expert
import nets
import offpac_il
from lab import first_updates


def test_bias_corrected_first_step_is_lr_sized_where_plain_rmsprop_is_not():
    grads = {"w": np.array([3.0, -0.2, 1e-3])}
    lr, decay = 1e-2, 0.995
    corrected, plain = {"w": np.zeros(3)}, {"w": np.zeros(3)}
    first_updates.BiasCorrectedRMSProp(decay, 0.0).step(corrected, grads, lr)
    nets.RMSProp(decay, 0.0).step(plain, grads, lr)
    np.testing.assert_allclose(corrected["w"], -lr * np.sign(grads["w"]), rtol=1e-9)
    np.testing.assert_allclose(plain["w"], -lr * np.sign(grads["w"]) / np.sqrt(1 - decay))


def cloning_case(seed: int, batch: int = 4):
    """A small float64 PN, a batch of (s_E, z, a_E) and PN's cache, drawn from `seed`."""
    learner, _, rng = small_learner(seed)
    policy = learner.policy
    states = rng.standard_normal((batch, 3))
    noise = rng.standard_normal((batch, policy.noise_dim))
    actions = rng.uniform(-1.0, 1.0, (batch, 2))
    return policy, states, noise, actions, policy.forward(states, noise)[1]


# Steps and tolerance as for the learner's objectives (test_offpac_il: eps 1e-4, relative
# 5e-5). Elements behind a leaky-ReLU unit that is off are ~1e-6 of the O(1) loss, below
# what a centered difference resolves (gradcheck's docstring): under this floor the
# comparison is absolute, 5e-5 * 1e-5. A wrong gradient is off by O(1) on the large
# elements (the next test).
CLONING_FLOOR = 1e-5


@given(st.integers(0, 2**31 - 1))
def test_cloning_gradient_matches_finite_differences(seed):
    policy, states, noise, actions, cache = cloning_case(seed)
    assume(away_from_kinks(cache))
    _, grads = first_updates.cloning_loss_and_grads(policy, states, noise, actions)
    for name, param in policy.net.params.items():

        def loss():
            return first_updates.cloning_loss_and_grads(policy, states, noise, actions)[0]

        numeric = numerical_gradient(loss, param, OBJECTIVE_EPS)
        assert_gradient_close(grads[name], numeric, OBJECTIVE_TOL, name, floor=CLONING_FLOOR)


@given(st.integers(0, 2**31 - 1))
def test_cloning_gradient_check_catches_a_missing_factor_2(seed):
    policy, states, noise, actions, cache = cloning_case(seed)
    assume(away_from_kinks(cache))
    _, grads = first_updates.cloning_loss_and_grads(policy, states, noise, actions)
    name = next(iter(policy.net.params))

    def loss():
        return first_updates.cloning_loss_and_grads(policy, states, noise, actions)[0]

    numeric = numerical_gradient(loss, policy.net.params[name], OBJECTIVE_EPS)
    with pytest.raises(AssertionError):
        assert_gradient_close(grads[name] / 2.0, numeric, OBJECTIVE_TOL, name, floor=CLONING_FLOOR)


def test_fit_to_demonstrations_brings_the_policy_to_the_demonstrated_actions():
    config = offpac_il.Config(trajectories=1)
    env = expert.make_env(config.env)
    _, expert_buffer, learner, _, _ = offpac_il.prepare(config, env, np.random.default_rng(0))
    rng = np.random.default_rng(1)

    def error():
        noise = rng.standard_normal((len(expert_buffer.states), learner.policy.noise_dim))
        actions = learner.policy.act(expert_buffer.states, noise.astype(np.float32))
        return float(((actions - expert_buffer.actions) ** 2).mean())

    before = error()
    first_updates.fit_to_demonstrations(learner.policy, expert_buffer, 500, rng)
    assert error() < 0.2 * before


@pytest.mark.parametrize("start", first_updates.STARTS)
def test_each_start_runs_and_reports_shares(start, capsys):
    config = offpac_il.Config(noise_samples=2, target_samples=2)
    rows = first_updates.first_updates(config, interactions=20, start=start, bc_steps=50)
    assert rows and rows[-1]["interactions"] >= 20
    for key in ("sat B", "sat E", "prefers a_E"):
        assert all(0.0 <= row[key] <= 1.0 for row in rows)
    assert "prefers a_E" in capsys.readouterr().out


@pytest.mark.parametrize(
    "args, fragment",
    [
        (("--interactions", "0"), "--interactions"),
        (("--start", "warm"), "--start"),
        (("--policy-expert-states", "2"), "--policy-expert-states"),
        (("--env", "CartPole-v1"), "Box"),
    ],
)
def test_bad_input_is_one_line_and_status_2(args, fragment):
    assert_one_line_error(run_module("lab.first_updates", *args, check=False), fragment)
