"""lab/sac.py: finite-difference checks of every gradient SAC uses, each shown to fail on a
wrong gradient; the targets; resume; learning on a small task; the expert file and CLI.

Gradient checks run in float64 on tiny networks (tests/gradcheck.py): the critics' TD loss
(Eq. 5-6) w.r.t. every critic parameter, the policy loss (Eq. 9-10) w.r.t. every policy
parameter through the reparameterised tanh-Gaussian and its log-probability (App. C), and
the temperature loss (Eq. 18) w.r.t. log alpha. Samples whose leaky-ReLU pre-activations,
log sigma clip edges or twin-critic minimum lie within a finite-difference step of a kink
are rejected: there the difference measures neither side's slope.
"""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from gradcheck import assert_gradient_close, numerical_derivative_elementwise, numerical_gradient
from helpers import read_rows
from hypothesis import assume, given
from hypothesis import strategies as st
from test_nets import FD_FLOOR
from test_offpac_il import OBJECTIVE_EPS, OBJECTIVE_TOL, away_from_kinks

import expert
import harness
import nets
from lab import sac, shipping
from lab import table as lab_table

ROOT = Path(__file__).resolve().parent.parent
DIM_S, DIM_A = 3, 2
seeds = st.integers(0, 2**16)
hidden_layers = st.lists(st.integers(2, 6), min_size=1, max_size=2)


def tiny_net(rng, sizes, bias_scale=0.5) -> nets.MLP:
    """A float64 MLP with nonzero biases (zero at init; nonzero ones test more)."""
    mlp = nets.MLP.create(sizes, "identity", rng, dtype=np.float64)
    for i in range(mlp.n_layers):
        mlp.params[f"b{i}"][...] = rng.normal(scale=bias_scale, size=sizes[i + 1])
    return mlp


def random_batch(rng, n, terminated_fraction=0.3) -> sac.Batch:
    return sac.Batch(
        rng.standard_normal((n, DIM_S)),
        rng.uniform(-1, 1, (n, DIM_A)),
        rng.standard_normal(n),
        rng.standard_normal((n, DIM_S)),
        (rng.random(n) < terminated_fraction).astype(np.float64),
    )


def check_params(loss, grads: dict, mlp: nets.MLP, name: str) -> None:
    """Every parameter's analytic gradient against centered differences of loss()."""
    assert set(grads) == set(mlp.params)
    for key, param in mlp.params.items():
        numeric = numerical_gradient(loss, param, OBJECTIVE_EPS)
        assert_gradient_close(
            grads[key], numeric, OBJECTIVE_TOL, f"{name} d/d{key}", floor=FD_FLOOR
        )


# ---------------------------------------------------------------------------------------
# The tanh-Gaussian's log-probability (App. C).
# ---------------------------------------------------------------------------------------


@given(u=st.lists(st.floats(-300.0, 300.0), min_size=1, max_size=6))
def test_squash_correction_is_stable_and_exact(u):
    """-log(1 - tanh(u)^2) = 2 log cosh(u): the stable form matches it wherever cosh does
    not overflow (|u| < 710), in float64 and float32, although 1 - tanh(u)^2 itself is 0
    from |u| = 19 (float64) or 9 (float32) on."""
    u = np.array([u])
    expected = 2.0 * np.log(np.cosh(u)).sum(axis=1)
    np.testing.assert_allclose(sac.squash_correction(u), expected, rtol=1e-12, atol=1e-12)
    u32 = u.astype(np.float32)
    assert sac.squash_correction(u32).dtype == np.float32
    np.testing.assert_allclose(sac.squash_correction(u32), expected, rtol=1e-5, atol=1e-5)
    column = u.T  # (k, 1): one element per row, so that the per-row sum is the element
    numeric = numerical_derivative_elementwise(lambda x: sac.squash_correction(x)[:, None], column)
    # Near u = 0 the derivative 2 tanh(u) ~ 2u is far below the difference's rounding
    # error (~1e-10 absolute): compare absolutely there, as FD_FLOOR explains.
    analytic = sac.squash_correction_grad(column)
    assert_gradient_close(analytic, numeric, 1e-6, "squash/grad", floor=FD_FLOOR)


@given(seed=seeds, n=st.integers(1, 5))
def test_log_prob_is_the_density_of_the_squashed_action(seed, n):
    """log pi(a|s) against a direct change of variables: the Gaussian density of
    u = atanh(a) at (mu, sigma), times |da/du|^-1 = 1 / (1 - a^2) per dimension."""
    rng = np.random.default_rng(seed)
    policy = tiny_net(rng, [DIM_S, 4, 2 * DIM_A])
    states, noise = rng.standard_normal((n, DIM_S)), rng.standard_normal((n, DIM_A))
    actions, log_prob, sample = sac.sample_actions(policy, states, noise)
    # The direct formula recovers u = atanh(a), which loses digits as a nears +-1 (its
    # error grows like 1e-16 / (1 - |a|)); the stable test above covers large |u|.
    assume(np.abs(sample.u).max() < 5.0)
    out = policy.forward(states)[0]
    mean, log_std = out[:, :DIM_A], np.clip(out[:, DIM_A:], -20, 2)
    u = np.arctanh(actions)
    gaussian = -0.5 * ((u - mean) / np.exp(log_std)) ** 2 - log_std - 0.5 * np.log(2 * np.pi)
    direct = (gaussian - np.log(1 - actions**2)).sum(axis=1)
    np.testing.assert_allclose(log_prob, direct, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sample.u, u, rtol=1e-10, atol=1e-10)
    np.testing.assert_array_equal(sac.deterministic_actions(policy, states), np.tanh(mean))


def test_log_std_is_clipped():
    rng = np.random.default_rng(0)
    policy = tiny_net(rng, [DIM_S, 4, 2 * DIM_A])
    policy.params["b1"][DIM_A:] = [50.0, -50.0]  # far above and below the clip range
    _, _, sample = sac.sample_actions(policy, rng.standard_normal((3, DIM_S)), np.ones((3, 2)))
    np.testing.assert_allclose(sample.std[:, 0], math.exp(sac.LOG_STD_MAX))
    np.testing.assert_allclose(sample.std[:, 1], math.exp(sac.LOG_STD_MIN))
    np.testing.assert_array_equal(sample.log_std_free, 0.0)


# ---------------------------------------------------------------------------------------
# The critics: targets (Eq. 2-3) and the TD loss (Eq. 5-6).
# ---------------------------------------------------------------------------------------


def tiny_agent(seed, hidden=(5, 4)):
    rng = np.random.default_rng(seed)
    q_sizes = [DIM_S + DIM_A, *hidden, 1]
    policy = tiny_net(rng, [DIM_S, *hidden, 2 * DIM_A])
    q1, q2 = tiny_net(rng, q_sizes), tiny_net(rng, q_sizes)
    return rng, policy, q1, q2


def test_critic_targets_bootstrap_unless_terminated():
    """y = r at a terminal s'; otherwise y = r + gamma (min_i Q'_i(s', a') - alpha log pi),
    with a' drawn with the same noise; a truncated episode is not terminated."""
    rng, policy, target_q1, target_q2 = tiny_agent(0)
    batch = random_batch(rng, 8, terminated_fraction=0.5)
    terminal = batch.terminated.astype(bool)
    assert terminal.any() and not terminal.all()
    noise = rng.standard_normal((8, DIM_A))
    y = sac.critic_targets(target_q1, target_q2, policy, batch, 0.3, 0.9, noise)
    next_actions, next_log_prob, _ = sac.sample_actions(policy, batch.next_observations, noise)
    q1 = target_q1.forward(np.hstack([batch.next_observations, next_actions]))[0][:, 0]
    q2 = target_q2.forward(np.hstack([batch.next_observations, next_actions]))[0][:, 0]
    expected = batch.rewards + 0.9 * (np.minimum(q1, q2) - 0.3 * next_log_prob)
    expected[terminal] = batch.rewards[terminal]
    np.testing.assert_allclose(y, expected, rtol=1e-12, atol=1e-12)


@given(seed=seeds, n=st.integers(1, 6), hidden=hidden_layers)
def test_critic_loss_gradient(seed, n, hidden):
    rng, _, critic, _ = tiny_agent(seed, hidden)
    batch, targets = random_batch(rng, n), rng.normal(scale=2.0, size=n)
    assume(away_from_kinks(critic.forward((batch.observations, batch.actions))[1]))
    loss, grads, q = sac.critic_loss_and_grads(critic, batch, targets)
    assert loss == pytest.approx(0.5 * np.mean((q - targets) ** 2), rel=1e-12)

    def f():
        return sac.critic_loss_and_grads(critic, batch, targets)[0]

    check_params(f, grads, critic, "critic loss (5)")


def test_critic_loss_check_catches_the_other_critics_error():
    """A twin-critic mix-up, Q1's gradient taken with Q2's TD error, fails the check."""
    rng, _, q1, q2 = tiny_agent(3)
    batch, targets = random_batch(rng, 5), rng.normal(scale=2.0, size=5)
    _, right, _ = sac.critic_loss_and_grads(q1, batch, targets)
    q2_values = q2.forward((batch.observations, batch.actions))[0][:, 0]
    cache = q1.forward((batch.observations, batch.actions))[1]
    _, wrong = q1.backward(((q2_values - targets) / 5)[:, None], cache, input_grads=False)

    def f():
        return sac.critic_loss_and_grads(q1, batch, targets)[0]

    numeric = numerical_gradient(f, q1.params["W0"], OBJECTIVE_EPS)
    assert_gradient_close(right["W0"], numeric, OBJECTIVE_TOL, floor=FD_FLOOR)
    with pytest.raises(AssertionError, match="relative error"):
        assert_gradient_close(wrong["W0"], numeric, OBJECTIVE_TOL, floor=FD_FLOOR)


# ---------------------------------------------------------------------------------------
# The policy: J_pi = E[alpha log pi(a|s) - min_i Q_i(s, a)] (Eq. 9-10).
# ---------------------------------------------------------------------------------------


def policy_loss_setup(seed, n, hidden, log_std_offset):
    """A tiny policy and twin critics; log sigma's bias moved by `log_std_offset`, so that
    some draws put log sigma outside [-20, 2], where the clip passes no gradient."""
    rng, policy, q1, q2 = tiny_agent(seed, hidden)
    policy.params[f"b{policy.n_layers - 1}"][DIM_A:] += log_std_offset
    states, noise = rng.standard_normal((n, DIM_S)), rng.standard_normal((n, DIM_A))
    alpha = float(rng.uniform(0.05, 2.0))

    def loss_and_grads():
        actions, log_prob, sample = sac.sample_actions(policy, states, noise)
        return sac.policy_loss_and_grads(policy, q1, q2, states, actions, log_prob, sample, alpha)

    # Reject draws that a finite-difference step could carry across a kink.
    actions, _, sample = sac.sample_actions(policy, states, noise)
    q1_values, q1_cache = q1.forward((states, actions))
    q2_values, q2_cache = q2.forward((states, actions))
    raw_log_std = policy.forward(states)[0][:, DIM_A:]
    smooth = (
        away_from_kinks(sample.cache, q1_cache, q2_cache)
        and np.abs(q1_values - q2_values).min() > 1e-2
        and np.abs(raw_log_std - sac.LOG_STD_MAX).min() > 1e-2
        and np.abs(raw_log_std - sac.LOG_STD_MIN).min() > 1e-2
    )
    return policy, loss_and_grads, smooth


@given(
    seed=seeds,
    n=st.integers(1, 5),
    hidden=hidden_layers,
    log_std_offset=st.sampled_from([0.0, 0.0, 2.0, -20.0]),
)
def test_policy_loss_gradient(seed, n, hidden, log_std_offset):
    policy, loss_and_grads, smooth = policy_loss_setup(seed, n, hidden, log_std_offset)
    assume(smooth)
    _, grads = loss_and_grads()
    check_params(lambda: loss_and_grads()[0], grads, policy, "policy loss (9)")


def test_policy_loss_check_catches_a_dropped_squash_correction(monkeypatch):
    """Without the gradient of -sum log(1 - tanh(u)^2) (its forward value kept), the
    policy gradient is wrong, and the check says so."""
    policy, loss_and_grads, smooth = policy_loss_setup(5, 4, (5, 4), 0.0)
    assert smooth
    _, right = loss_and_grads()

    def f():
        return loss_and_grads()[0]

    numeric = numerical_gradient(f, policy.params["W0"], OBJECTIVE_EPS)
    assert_gradient_close(right["W0"], numeric, OBJECTIVE_TOL, floor=FD_FLOOR)
    monkeypatch.setattr(sac, "squash_correction_grad", np.zeros_like)
    _, wrong = loss_and_grads()
    with pytest.raises(AssertionError, match="relative error"):
        assert_gradient_close(wrong["W0"], numeric, OBJECTIVE_TOL, floor=FD_FLOOR)


def test_policy_loss_check_catches_a_policy_step_on_one_critic():
    """A twin mix-up, the policy stepped on Q2 alone (min over Q2, Q2), fails the check
    when Q1 is the smaller critic on some row."""
    rng, policy, q1, q2 = tiny_agent(6)
    states, noise = rng.standard_normal((6, DIM_S)), rng.standard_normal((6, DIM_A))
    actions, log_prob, sample = sac.sample_actions(policy, states, noise)
    q1_values, q2_values = (q.forward((states, actions))[0] for q in (q1, q2))
    assert (q1_values < q2_values).any()

    def loss_and_grads(first_critic):
        actions, log_prob, sample = sac.sample_actions(policy, states, noise)
        return sac.policy_loss_and_grads(
            policy, first_critic, q2, states, actions, log_prob, sample, 0.5
        )

    numeric = numerical_gradient(lambda: loss_and_grads(q1)[0], policy.params["W0"], OBJECTIVE_EPS)
    assert_gradient_close(loss_and_grads(q1)[1]["W0"], numeric, OBJECTIVE_TOL, floor=FD_FLOOR)
    with pytest.raises(AssertionError, match="relative error"):
        assert_gradient_close(loss_and_grads(q2)[1]["W0"], numeric, OBJECTIVE_TOL, floor=FD_FLOOR)


# ---------------------------------------------------------------------------------------
# The temperature: J(alpha) = E[-alpha log pi - alpha H_bar] (Eq. 18), w.r.t. log alpha.
# ---------------------------------------------------------------------------------------


@given(
    log_alpha=st.floats(-5.0, 2.0),
    log_prob=st.lists(st.floats(-10.0, 10.0), min_size=1, max_size=8),
    target_entropy=st.floats(-17.0, 0.0),
)
def test_temperature_loss_gradient(log_alpha, log_prob, target_entropy):
    log_prob = np.array(log_prob)
    loss, grad = sac.temperature_loss_and_grad(log_alpha, log_prob, target_entropy)
    alpha = math.exp(log_alpha)
    assert loss == pytest.approx(np.mean(-alpha * log_prob - alpha * target_entropy), rel=1e-12)
    variable = np.array([log_alpha])

    def f():
        return sac.temperature_loss_and_grad(float(variable[0]), log_prob, target_entropy)[0]

    numeric = numerical_gradient(f, variable)[0]
    assert_gradient_close(grad, numeric, 1e-6, "temperature (18)", floor=FD_FLOOR)


def test_temperature_check_catches_the_missing_alpha_factor():
    """-mean(log pi + H_bar), the gradient of -log alpha (log pi + H_bar) (SB3's variant
    of Eq. 18), is not the gradient of Eq. (18) itself unless alpha = 1."""
    log_prob, log_alpha = np.array([-1.0, 0.5, 2.0]), math.log(0.2)
    variable = np.array([log_alpha])
    _, right = sac.temperature_loss_and_grad(log_alpha, log_prob, -2.0)
    numeric = numerical_gradient(
        lambda: sac.temperature_loss_and_grad(float(variable[0]), log_prob, -2.0)[0], variable
    )[0]
    assert_gradient_close(right, numeric, 1e-6)
    with pytest.raises(AssertionError, match="relative error"):
        assert_gradient_close(-(np.mean(log_prob) - 2.0), numeric, 1e-6)


def test_temperature_moves_towards_the_target_entropy():
    """alpha rises while the entropy -E log pi is below H_bar, and falls above it."""
    assert sac.temperature_loss_and_grad(0.0, np.array([3.0]), -2.0)[1] < 0  # descent: up
    assert sac.temperature_loss_and_grad(0.0, np.array([1.0]), -2.0)[1] > 0  # descent: down


# ---------------------------------------------------------------------------------------
# Runs: resume, learning, the expert file and the command line.
# ---------------------------------------------------------------------------------------


def numbered_transitions(replay: sac.ReplayBuffer, count: int, offset: float = 0.0) -> None:
    """Add `count` transitions whose fields all hold their number (plus offset)."""
    for _ in range(count):
        t = replay.added + offset
        replay.add([t, -t], [t], t, [t + 1, -t - 1], t % 2)


def assert_same_buffer(loaded: sac.ReplayBuffer, original: sac.ReplayBuffer) -> None:
    assert (loaded.added, loaded.size) == (original.added, original.size)
    for name in sac.ReplayBuffer.FIELDS:
        np.testing.assert_array_equal(getattr(loaded, name), getattr(original, name), name)


@given(
    capacity=st.integers(1, 12),
    increments=st.lists(st.integers(0, 15), min_size=1, max_size=8),
)
def test_replay_segments_restore_the_buffer_at_every_checkpoint(
    tmp_path_factory, capacity, increments
):
    """Checkpoints every few transitions, through several wraps of the FIFO: each one's
    segments rebuild the buffer exactly, and the files hold little more than the buffer."""
    folder = tmp_path_factory.mktemp("replay")
    replay = sac.ReplayBuffer(capacity, 2, 1)
    for increment in increments:
        numbered_transitions(replay, increment)
        replay.save_new_rows(folder)
        replay.prune(folder)  # after the checkpoint that counts `added` transitions
        loaded = sac.ReplayBuffer(capacity, 2, 1)
        loaded.load_rows(folder, replay.added)
        assert_same_buffer(loaded, replay)
        on_disk = sum(end - first for first, end, _ in replay.segments(folder))
        assert on_disk <= replay.size + max(increments)


def test_replay_segments_of_a_killed_run_are_replaced(tmp_path):
    """A segment written just before a kill (its checkpoint never written) is dropped on
    resume; the resumed run's own transitions take its place."""
    replay = sac.ReplayBuffer(8, 2, 1)
    numbered_transitions(replay, 5)
    replay.save_new_rows(tmp_path)  # checkpoint at 5
    numbered_transitions(replay, 4)
    replay.save_new_rows(tmp_path)  # killed before the checkpoint at 9

    resumed = sac.ReplayBuffer(8, 2, 1)
    resumed.load_rows(tmp_path, 5)
    assert [(first, end) for first, end, _ in resumed.segments(tmp_path)] == [(0, 5)]
    numbered_transitions(resumed, 6, offset=100.0)  # not what the killed run saw
    resumed.save_new_rows(tmp_path)
    again = sac.ReplayBuffer(8, 2, 1)
    again.load_rows(tmp_path, 11)
    assert_same_buffer(again, resumed)


def test_replay_segments_missing_rows_are_reported(tmp_path):
    replay = sac.ReplayBuffer(10, 2, 1)
    for _ in range(3):
        numbered_transitions(replay, 4)
        replay.save_new_rows(tmp_path)
    _, _, middle = replay.segments(tmp_path)[1]
    middle.unlink()
    with pytest.raises(expert.UserError, match=r"transitions 4\.\.11 are missing"):
        sac.ReplayBuffer(10, 2, 1).load_rows(tmp_path, 12)


PENDULUM = "InvertedPendulum-v4"
TINY = sac.SACConfig(
    env=PENDULUM,
    steps=600,
    hidden=(16, 16),
    batch_size=32,
    learning_starts=200,
    eval_every=200,
    eval_episodes=2,
    checkpoint_every=0.0,
    log_every=1e9,
)


def read_progress(run_dir: Path) -> list[dict]:
    return read_rows(run_dir / "progress.csv", drop=("wall_seconds", "steps_per_second"))


def final_params(run_dir: Path) -> dict[str, np.ndarray]:
    arrays = harness.load_arrays(run_dir / "checkpoint.npz")
    return {k: v for k, v in arrays.items() if not k.startswith(("rows", "counters"))}


def run_tiny(run_dir: Path, resume=False, seed=0, config=TINY) -> sac.Progress:
    config = dataclasses.replace(config, seed=seed, run_dir=str(run_dir))
    config = dataclasses.replace(config, out=str(run_dir / "expert.npz"))
    return sac.train(config, resume=resume, log=lambda _: None)


def interrupted_after(updates: int):
    """sac.update, raising as a kill would once `updates` updates ran."""
    original, calls = sac.update, {"n": 0}

    def update(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] > updates:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    return update


def test_resume_reproduces_an_uninterrupted_run(tmp_path, monkeypatch):
    whole, other = tmp_path / "whole", tmp_path / "other"
    run_tiny(whole)
    run_tiny(other, seed=1)
    interrupted = tmp_path / "interrupted"
    with monkeypatch.context() as patch:
        patch.setattr(sac, "update", interrupted_after(250))
        with pytest.raises(KeyboardInterrupt):
            run_tiny(interrupted)
    counters = json.loads(str(harness.load_arrays(interrupted / "checkpoint.npz")["counters"]))
    assert 200 < counters["interactions"] < 450  # checkpointed after some updates, not at 0
    run_tiny(interrupted, resume=True)

    expected = read_progress(whole)
    assert [int(row["interactions"]) for row in expected] == [200, 400, 600]
    assert read_progress(other) != expected
    assert read_progress(interrupted) == expected
    final = final_params(whole)
    for name, value in final_params(interrupted).items():
        np.testing.assert_array_equal(value, final[name], err_msg=name)
    # The expert file holds the best evaluated policy, loadable by expert.load_expert.
    best = max(expected, key=lambda row: float(row["eval_return_mean"]))
    policy = expert.load_expert(PENDULUM, interrupted / "expert.npz")
    assert policy.network is not None  # a SAC expert
    assert policy.metadata["env_steps"] == int(best["interactions"])
    assert policy.metadata["eval_return_mean"] == pytest.approx(float(best["eval_return_mean"]))


def test_sac_improves_pendulum(tmp_path):
    """4000 steps on Pendulum-v1 (small networks, lr 1e-3) take the deterministic policy
    from about -1600 to better than -800.

    Measured with these settings over seeds 0-11 (evaluations at 1k, 2k, 3k, 4k steps,
    3 episodes each): first evaluation -1409 to -1805; best evaluation -83 to -502
    (median -150). The threshold -800 leaves a margin of 300 below the worst seed.
    """
    config = sac.SACConfig(
        env="Pendulum-v1",
        run_dir=str(tmp_path / "run"),
        out=str(tmp_path / "e.npz"),
        steps=4000,
        hidden=(64, 64),
        lr=1e-3,
        batch_size=128,
        learning_starts=500,
        eval_every=1000,
        eval_episodes=3,
        checkpoint_every=1e9,
        log_every=1e9,
    )
    progress = sac.train(config, log=lambda _: None)
    returns = [row["eval_return_mean"] for row in progress.rows]
    assert len(returns) == 4 and returns[0] < -1000, returns
    assert max(returns) > -800, returns


# ---------------------------------------------------------------------------------------
# The expert file: a SAC policy serves load_expert, demos and table like an ARS one.
# ---------------------------------------------------------------------------------------


def balancing_sac_expert() -> expert.ExpertPolicy:
    """A SAC-format expert for InvertedPendulum-v4 built by hand: the PD controller of
    test_expert.py, a = 3 tanh(w.s / 3), w = (1, 10, 1, 1). Its network computes the mean
    w.s/3 through two leaky-ReLU units, since f(x) - f(-x) = 1.01 x for f = leaky ReLU;
    the log std outputs are 0."""
    w = np.array([1.0, 10.0, 1.0, 1.0]) / 3.0
    params = {
        "W0": np.stack([w, -w], axis=1).astype(np.float32),  # (4, 2)
        "b0": np.zeros(2, np.float32),
        "W1": np.array([[1.0, 0.0], [-1.0, 0.0]], np.float32) / 1.01,  # (2, 2): mean, log std
        "b1": np.zeros(2, np.float32),
    }
    return expert.ExpertPolicy(
        PENDULUM,
        np.array([-3.0]),
        np.array([3.0]),
        network=nets.MLP([4, 2, 2], "identity", params),
        metadata={"commands": ["hand-made test controller"], "seed": 0},
    )


def test_sac_expert_file_serves_load_demos_and_table(tmp_path, monkeypatch):
    policy = balancing_sac_expert()
    monkeypatch.setattr(expert, "EXPERTS_DIR", tmp_path)
    shipping.save_expert(policy, expert.default_expert_path(PENDULUM), eval_return_mean=1000.0)
    loaded = expert.load_expert(PENDULUM)
    assert loaded.network is not None and loaded.weights is None  # a SAC expert
    assert loaded.metadata["commands"] == ["hand-made test controller"]
    for observation in np.random.default_rng(0).normal(size=(5, 4)):
        action = loaded.act(observation)
        expected = 3.0 * np.tanh(np.dot([1.0, 10.0, 1.0, 1.0], observation) / 3.0)
        np.testing.assert_allclose(action, [expected], rtol=1e-5, atol=1e-5)
    # demos: through the command line, from the shipped location.
    out = tmp_path / "demos.npz"
    assert expert.main(["demos", "--env", PENDULUM, "--trajectories", "1", "--out", str(out)]) == 0
    demos = expert.load_demos(out, PENDULUM)
    assert len(demos) == 100 and demos.returns.tolist() == [1000.0]
    # table: the expert row is measured with the SAC policy.
    table = lab_table.measure_table(episodes=2, tasks=(PENDULUM,), log=lambda _: None)
    assert table[PENDULUM]["expert_mean"] == 1000.0
    # ... and records what its last bits depend on (library versions, BLAS kernel).
    assert set(table[PENDULUM]["measured_with"]) == {"numpy", "mujoco", "gymnasium", "blas_kernel"}


def test_expert_files_of_both_kinds_and_broken_ones(tmp_path):
    # A file written before SAC (no "kind") is an ARS linear policy.
    with np.load(expert.default_expert_path("Hopper-v4")) as shipped:
        assert "kind" not in shipped.files
    assert expert.load_expert("Hopper-v4").network is None  # an ARS expert
    path = tmp_path / "sac.npz"
    shipping.save_expert(balancing_sac_expert(), path)
    arrays = harness.load_arrays(path)
    for name, change in {
        "unknown kind": {"kind": np.array("transformer")},
        "missing layer": {"policy/W1": None},
        "odd output width": {"sizes": np.array([4, 2, 3])},
        "wrong action bounds": {"action_low": np.zeros(2)},
    }.items():
        broken = {**arrays, **{k: v for k, v in change.items() if v is not None}}
        for key in [k for k, v in change.items() if v is None]:
            broken.pop(key)
        broken_path = tmp_path / f"{name.replace(' ', '-')}.npz"
        harness.save_arrays(broken_path, broken)
        with pytest.raises(expert.UserError, match=broken_path.name):
            expert.load_expert(PENDULUM, broken_path)


# ---------------------------------------------------------------------------------------
# The command line: python -m lab.sac.
# ---------------------------------------------------------------------------------------

TINY_FLAGS = [
    "--steps", "600", "--hidden", "16", "16", "--batch-size", "32",
    "--learning-starts", "200", "--eval-every", "200", "--eval-episodes", "2",
    "--checkpoint-every", "0",
]  # fmt: skip


def train_command(run_dir: Path, *extra: str) -> list[str]:
    return ["--env", PENDULUM, "--run-dir", str(run_dir),
            "--out", str(run_dir.parent / f"{run_dir.name}.npz"), *extra]  # fmt: skip


def test_command_line_trains_resumes_and_refuses_mixed_flags(tmp_path, capsys):
    run_dir = tmp_path / "run"
    assert sac.main(train_command(run_dir, *TINY_FLAGS, "--log-every", "0")) == 0
    printed = capsys.readouterr().out
    assert "eval   env steps       200" in printed and "updates/s" in printed
    policy = expert.load_expert(PENDULUM, tmp_path / "run.npz")
    assert policy.network is not None and policy.metadata["seed"] == 0
    assert "lab.sac --env" in policy.metadata["commands"][0]
    # A bigger budget continues the run; other settings cannot change on resume.
    assert sac.main(["--resume", str(run_dir), "--steps", "800"]) == 0
    assert [r["interactions"] for r in read_progress(run_dir)] == ["200", "400", "600", "800"]
    capsys.readouterr()
    for refused, message in [
        (["--resume", str(run_dir), "--lr", "1e-3"], "may change only: --steps"),
        (train_command(run_dir, *TINY_FLAGS), "already holds a run"),
        # an ARS flag; the line names the command as typed
        (
            train_command(tmp_path / "new", "--directions", "8"),
            "--directions 8 (see python -m lab.sac",
        ),
        (train_command(tmp_path / "new", "--gamma", "nan"), "--gamma"),
        (["--resume", str(tmp_path / "absent")], "holds no run"),
        (["--run-dir", str(tmp_path / "new")], "--env is required"),
    ]:
        assert sac.main(refused) == 2
        error = capsys.readouterr().err
        assert error.startswith("error: ") and message in error and error.count("\n") == 1


def test_kill_and_resume_from_the_command_line(tmp_path):
    """kill -9 as soon as the first checkpoint exists, then --resume: the same progress
    as a run never killed."""
    run_dir = tmp_path / "killed"
    process = subprocess.Popen(
        [sys.executable, "-m", "lab.sac", *train_command(run_dir, *TINY_FLAGS)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 120
    while not (run_dir / "checkpoint.npz").exists() and time.time() < deadline:
        time.sleep(0.02)
    process.kill()
    process.wait()
    assert sac.main(["--resume", str(run_dir)]) == 0
    whole = tmp_path / "whole"
    assert sac.main(train_command(whole, *TINY_FLAGS)) == 0
    assert read_progress(run_dir) == read_progress(whole)
