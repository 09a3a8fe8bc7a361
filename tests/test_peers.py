"""lab/peers.py: the mixed batch, IQ-Learn's critic gradient, tiny runs that resume
exactly, and the command line.

SQIL has no gradient of its own (its update is sac.update, checked in tests/test_sac.py);
what is SQIL's is the batch: which rows, with which rewards. IQ-Learn's critic objective
is new: its value is checked against the authors' formulation written out directly, and
its gradient against centred finite differences in float64, the check shown to catch two
plausible mistakes.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import time

import numpy as np
import pytest
from helpers import ROOT, assert_one_line_error, read_rows, run_module
from hypothesis import assume, given
from hypothesis import strategies as st
from test_offpac_il import away_from_kinks
from test_sac import DIM_A, DIM_S, check_params, random_batch, tiny_net

import harness
import offpac_il
from lab import peers, sac

TINY = ["--env", "Hopper-v4", "--hidden", "8", "8", "--batch-size", "16", "--eval-episodes", "1"]
TINY += ["--total-steps", "600", "--eval-every", "200", "--learning-starts", "100"]
TINY += ["--checkpoint-every", "0", "--log-every", "0"]


def tiny_config(run_dir, demos, seed=0, method="sqil") -> peers.PeerConfig:
    argv = [method, *TINY, "--demos", str(demos), "--seed", str(seed), "--run-dir", str(run_dir)]
    config, parsed_method, resume = peers.parse(argv)
    assert (parsed_method, resume) == (method, False)
    return config


def test_mixed_batch_takes_half_from_each_buffer_with_their_rewards():
    rng = np.random.default_rng(0)
    dim_s, dim_a, n_demos = 3, 2, 7
    expert_buffer = offpac_il.Triplets(
        rng.standard_normal((n_demos, dim_s)).astype(np.float32),
        rng.uniform(-1, 1, (n_demos, dim_a)).astype(np.float32),
        rng.standard_normal((n_demos, dim_s)).astype(np.float32),
        np.arange(n_demos) == 3,
    )
    demonstrations = peers.demonstration_batch(expert_buffer, reward=1.0)
    replay = peers.ReplayBuffer(50, dim_s, dim_a)
    for _ in range(20):
        replay.add(rng.standard_normal(dim_s), rng.uniform(-1, 1, dim_a), rng.normal(size=3), 0)
    batch = peers.mixed_batch(demonstrations, replay, rng, 11)
    assert len(batch.rewards) == 11
    np.testing.assert_array_equal(batch.rewards, [1.0] * 5 + [0.0] * 6)
    # Each row is a whole transition of the buffer its reward says it came from.
    for row in range(11):
        source = expert_buffer.states if row < 5 else replay.observations[: replay.size]
        index = int(np.flatnonzero((source == batch.observations[row]).all(axis=1))[0])
        if row < 5:
            np.testing.assert_array_equal(batch.actions[row], expert_buffer.actions[index])
            np.testing.assert_array_equal(
                batch.next_observations[row], expert_buffer.next_states[index]
            )
            assert batch.terminated[row] == float(index == 3)
        else:
            np.testing.assert_array_equal(batch.actions[row], replay.actions[index])
            np.testing.assert_array_equal(
                batch.next_observations[row], replay.next_observations[index]
            )


# ---------------------------------------------------------------------------------------
# IQ-Learn's critic objective.
# ---------------------------------------------------------------------------------------


def iq_case(seed, n_expert, n_replay, hidden):
    """Tiny float64 twin critics and a batch; `smooth` is False where a finite-difference
    step could cross a leaky-ReLU kink or swap which critic is the minimum."""
    rng = np.random.default_rng(seed)
    q1 = tiny_net(rng, [DIM_S + DIM_A, *hidden, 1])
    q2 = tiny_net(rng, [DIM_S + DIM_A, *hidden, 1])
    n = n_expert + n_replay
    batch = random_batch(rng, n)
    case = dict(
        batch=batch,
        policy_actions=rng.uniform(-1, 1, (n, DIM_A)),
        policy_log_prob=rng.normal(scale=2.0, size=n),
        y=rng.normal(scale=2.0, size=n),
        alpha=float(rng.uniform(0.01, 1.0)),
        n_expert=n_expert,
        chi2_alpha=float(rng.uniform(0.2, 2.0)),
        gamma=float(rng.uniform(0.5, 0.99)),
    )
    states = np.concatenate([batch.observations, batch.observations])
    actions = np.concatenate([batch.actions, case["policy_actions"]])
    out1, cache1 = q1.forward((states, actions))
    out2, cache2 = q2.forward((states, actions))
    smooth = away_from_kinks(cache1, cache2) and np.abs(out1[n:] - out2[n:]).min() > 1e-2
    return q1, q2, case, smooth


def iq_loss_by_definition(
    q1,
    q2,
    value_loss,
    batch,
    policy_actions,
    policy_log_prob,
    y,
    alpha,
    n_expert,
    chi2_alpha,
    gamma,
) -> float:
    """The authors' formulation (iq.py, twin critics, regularize=True), term by term:
    L = 1/2 (L_1 + L_2), L_i = -mean_E(Q_i - y) + value term
    + 1/(4 chi2_alpha) mean over [(Q_i - y) on E; (min Q(s, a~) - y) on B] of the square."""
    expert = np.arange(len(y)) < n_expert
    p = np.minimum(
        q1.forward((batch.observations, policy_actions))[0][:, 0],
        q2.forward((batch.observations, policy_actions))[0][:, 0],
    )
    v = p - alpha * policy_log_prob
    if value_loss == "value":
        value_term = np.mean(v - y)
    else:
        value_term = (1 - gamma) * np.mean(v[expert])
    losses = []
    for critic in (q1, q2):
        q = critic.forward((batch.observations, batch.actions))[0][:, 0]
        regularised = np.concatenate([(q - y)[expert], (p - y)[~expert]])
        losses.append(
            -np.mean((q - y)[expert]) + value_term + np.mean(regularised**2) / (4 * chi2_alpha)
        )
    return 0.5 * (losses[0] + losses[1])


@given(
    seed=st.integers(0, 2**16),
    n_expert=st.integers(1, 4),
    n_replay=st.integers(1, 4),
    hidden=st.lists(st.integers(2, 6), min_size=1, max_size=2),
    value_loss=st.sampled_from(peers.VALUE_LOSSES),
)
def test_iq_learn_critic_loss_and_gradient(seed, n_expert, n_replay, hidden, value_loss):
    q1, q2, case, smooth = iq_case(seed, n_expert, n_replay, hidden)
    assume(smooth)
    loss, grads1, grads2, stats = peers.iq_learn_loss_and_grads(
        q1, q2, value_loss=value_loss, **case
    )
    assert loss == pytest.approx(iq_loss_by_definition(q1, q2, value_loss, **case), rel=1e-10)

    def f():
        return peers.iq_learn_loss_and_grads(q1, q2, value_loss=value_loss, **case)[0]

    check_params(f, grads1, q1, f"IQ-Learn ({value_loss}) Q1")
    check_params(f, grads2, q2, f"IQ-Learn ({value_loss}) Q2")


def test_iq_learn_gradient_check_catches_wrong_gradients():
    """Two plausible mistakes fail the check: the twin critics' losses summed instead of
    averaged (the gradient doubled), and the other form's value term."""
    for seed in range(100):
        q1, q2, case, smooth = iq_case(seed, 3, 3, [5])
        if smooth:
            break
    assert smooth

    def f():
        return peers.iq_learn_loss_and_grads(q1, q2, value_loss="value", **case)[0]

    def check_both(grads1, grads2):
        check_params(f, grads1, q1, "Q1")
        check_params(f, grads2, q2, "Q2")

    _, *right, _ = peers.iq_learn_loss_and_grads(q1, q2, value_loss="value", **case)
    _, *other_form, _ = peers.iq_learn_loss_and_grads(q1, q2, value_loss="v0", **case)
    check_both(*right)
    doubled = [{key: 2.0 * value for key, value in grads.items()} for grads in right]
    for wrong in (doubled, other_form):
        with pytest.raises(AssertionError, match="relative error"):
            check_both(*wrong)


def iq_critic_step_case(seed: int, **settings):
    """An IQ-Learn agent, a 6-row batch with zero rewards, a~ and log pi, and the critic
    step's output at alpha 0.1 with next-action noise from Generator 9."""
    rng = np.random.default_rng(seed)
    config = peers.IQLearnConfig(hidden=(6,), **settings)
    agent = sac.Agent.create(DIM_S, DIM_A, config, rng, dtype=np.float64)
    batch = random_batch(rng, 6)
    batch.rewards[:] = 0.0
    actions, log_prob = rng.uniform(-1, 1, (6, DIM_A)), rng.normal(size=6)
    step = peers.iq_learn_critic_step(
        agent, batch, actions, log_prob, 0.1, config, np.random.default_rng(9)
    )
    return rng, config, agent, batch, actions, log_prob, step


def test_iq_learn_critic_step_uses_the_target_critics_bootstrap():
    """y = gamma (1 - d) V_bar(s') with the batch's zero rewards: the step's gradient is the
    loss's at sac.critic_targets' y, drawn from the same noise."""
    case = iq_critic_step_case(5, value_loss="v0", twin_critics=True)
    rng, config, agent, batch, actions, log_prob, (grads1, grads2, _) = case
    next_noise = np.random.default_rng(9).standard_normal(actions.shape)
    y = sac.critic_targets(
        agent.target_q1, agent.target_q2, agent.policy, batch, 0.1, config.gamma, next_noise
    )
    assert np.all(y[batch.terminated == 1] == 0.0)
    _, expected1, expected2, _ = peers.iq_learn_loss_and_grads(
        agent.q1, agent.q2, batch, actions, log_prob, y, 0.1, 3, "v0", 0.5, config.gamma
    )
    for got, expected in ((grads1, expected1), (grads2, expected2)):
        for key in expected:
            np.testing.assert_array_equal(got[key], expected[key])


def test_iq_learn_with_one_critic():
    """--no-twin-critics (the authors' MuJoCo critic): the step's gradient is that of the
    loss with Q_1 in both slots, y bootstrapped from Q_bar_1 alone, checked against finite
    differences and shown to catch the one slot's gradient alone; an update leaves Q_2
    and its target untouched."""
    case = iq_critic_step_case(3, twin_critics=False)
    rng, config, agent, batch, actions, log_prob, (grads, second, _) = case
    assert second is None
    next_noise = np.random.default_rng(9).standard_normal(actions.shape)
    y = sac.critic_targets(
        agent.target_q1, agent.target_q1, agent.policy, batch, 0.1, config.gamma, next_noise
    )
    case = dict(
        batch=batch, policy_actions=actions, policy_log_prob=log_prob, y=y, alpha=0.1,
        n_expert=3, value_loss="value", chi2_alpha=0.5, gamma=config.gamma,
    )  # fmt: skip

    def f():
        return peers.iq_learn_loss_and_grads(agent.q1, agent.q1, **case)[0]

    assert f() == pytest.approx(iq_loss_by_definition(agent.q1, agent.q1, **case), rel=1e-10)
    check_params(f, grads, agent.q1, "IQ-Learn, one critic")
    _, one_slot, _, _ = peers.iq_learn_loss_and_grads(agent.q1, agent.q1, **case)
    with pytest.raises(AssertionError, match="relative error"):
        check_params(f, one_slot, agent.q1, "IQ-Learn, one critic")

    untouched = {key: value.copy() for key, value in agent.q2.params.items()}
    untouched_target = {key: value.copy() for key, value in agent.target_q2.params.items()}
    q1_before = agent.q1.params["W0"].copy()
    sac.update(agent, batch, config, rng, critic_step=peers.iq_learn_critic_step)
    assert not np.array_equal(agent.q1.params["W0"], q1_before)
    for key in untouched:
        np.testing.assert_array_equal(agent.q2.params[key], untouched[key])
        np.testing.assert_array_equal(agent.target_q2.params[key], untouched_target[key])


# ---------------------------------------------------------------------------------------
# Tiny runs and the command line.
# ---------------------------------------------------------------------------------------


def interrupted_after(updates: int):
    """sac.update, raising as a kill would once `updates` updates ran."""
    original, calls = sac.update, {"n": 0}

    def update(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] > updates:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    return update


def progress_rows(run_dir):
    return read_rows(run_dir / "progress.csv", drop=("wall_seconds",))


@pytest.mark.parametrize("method", list(peers.METHODS))
def test_run_resumes_exactly(tmp_path, hopper_demos, monkeypatch, method):
    whole, other, interrupted = tmp_path / "whole", tmp_path / "other", tmp_path / "cut"
    peers.train(tiny_config(whole, hopper_demos, method=method), method)
    peers.train(tiny_config(other, hopper_demos, seed=1, method=method), method)
    with monkeypatch.context() as patch:
        patch.setattr(sac, "update", interrupted_after(250))
        with pytest.raises(KeyboardInterrupt):
            peers.train(tiny_config(interrupted, hopper_demos, method=method), method)
    partial = progress_rows(interrupted)
    assert 0 < len(partial) < len(progress_rows(whole))
    peers.train(tiny_config(interrupted, hopper_demos, method=method), method, resume=True)

    expected = progress_rows(whole)
    assert [int(row["interactions"]) // 200 for row in expected] == [0, 1, 2, 3]
    assert int(expected[-1]["updates"]) == int(expected[-1]["interactions"]) - 100
    assert all(row["stochastic_score"] != "" for row in expected)
    assert progress_rows(other) != expected
    assert progress_rows(interrupted) == expected
    final = harness.load_arrays(whole / "policy_final.npz")
    for name, value in harness.load_arrays(interrupted / "policy_final.npz").items():
        np.testing.assert_array_equal(value, final[name], err_msg=name)
    saved = json.loads((whole / "config.json").read_text())
    assert saved["method"] == method and saved["standardize"] is False


def test_a_run_made_with_the_removed_lr_decay_is_not_resumed_without_it(tmp_path, hopper_demos):
    """--lr-decay (the learner's schedule for the peers) left the code after 2b793f8: a
    resume that dropped it would silently keep the rates constant, so it is refused."""
    run_dir = tmp_path / "run"
    peers.train(tiny_config(run_dir, hopper_demos), "sqil")
    saved = json.loads((run_dir / "config.json").read_text())
    harness.write_text(run_dir / "config.json", json.dumps({**saved, "lr_decay": True}))
    refused = run_module("lab.peers", "sqil", "--resume", str(run_dir), check=False)
    assert_one_line_error(refused, "--lr-decay True", "no longer has", "commit 2b793f8")
    harness.write_text(run_dir / "config.json", json.dumps({**saved, "lr_decay": False}))
    assert peers.main(["sqil", "--resume", str(run_dir)]) == 0  # in-process: the run's lock


def test_command_line_help_resume_and_refusals(tmp_path, hopper_demos):
    assert "sqil" in run_module("lab.peers", "--help").stdout
    method_help = run_module("lab.peers", "sqil", "--help").stdout
    assert "--learning-starts" in method_help
    assert method_help.startswith("usage: python -m lab.peers sqil ")  # the command as typed
    run_dir = tmp_path / "run"
    common = [*TINY, "--demos", hopper_demos, "--run-dir", run_dir]
    run_module("lab.peers", "sqil", *common, "--total-steps", "300")
    run_module("lab.peers", "sqil", "--resume", run_dir, "--total-steps", "500")
    assert [row["interactions"][:1] for row in progress_rows(run_dir)] == ["0", "2", "3", "5"]
    for args, fragment in [
        (["gail-ish", "--env", "Hopper-v4"], "unknown method"),
        (["sqil", "--resume", run_dir, "--gamma", "0.5"], "may change only"),
        (["sqil", *common], "already holds a run"),
        (["sqil", *TINY, "--batch-size", "1", "--run-dir", tmp_path / "b"], "--batch-size"),
        (["sqil", "--env", "CartPole-v1", "--run-dir", tmp_path / "c"], "CartPole-v1"),
        (["iq-learn", "--bogus"], "(see python -m lab.peers iq-learn --help)"),
    ]:
        assert_one_line_error(run_module("lab.peers", *args, check=False), fragment)
    # A run is resumed by the method that made it.
    saved = json.loads((run_dir / "config.json").read_text())
    harness.write_config(run_dir, {**saved, "method": "iq-learn"})
    result = run_module("lab.peers", "sqil", "--resume", run_dir, check=False)
    assert_one_line_error(result, "not a sqil run")


def test_an_iq_learn_run_saved_before_twin_critics_existed_keeps_its_two_critics(
    tmp_path, hopper_demos
):
    """IQ-Learn ran SAC's two critics until one became its default; a config.json of that
    time lacks `twin_critics`, and its resume and its reading must not turn it into a
    one-critic run."""
    run_dir = tmp_path / "old"
    config = tiny_config(run_dir, hopper_demos, method="iq-learn")
    assert config.twin_critics is False  # today's default
    saved = {"method": "iq-learn", **dataclasses.asdict(config)}
    del saved["twin_critics"]
    run_dir.mkdir()
    harness.write_config(run_dir, saved)
    assert peers.saved_settings(saved).twin_critics is True
    resumed, method, resume = peers.parse(["iq-learn", "--resume", str(run_dir)])
    assert (method, resume, resumed.twin_critics) == ("iq-learn", True, True)
    # A run that records the setting keeps what it recorded.
    harness.write_config(run_dir, {**saved, "twin_critics": False})
    assert peers.parse(["iq-learn", "--resume", str(run_dir)])[0].twin_critics is False


def test_kill_and_resume_from_the_command_line(tmp_path, hopper_demos):
    """kill -9 once the first checkpoint after some updates exists, then --resume: the same
    progress as a run never killed."""
    killed, whole = tmp_path / "killed", tmp_path / "whole"
    command = [sys.executable, "-m", "lab.peers", "sqil", *TINY, "--demos", str(hopper_demos)]
    process = subprocess.Popen(
        [*command, "--run-dir", str(killed)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 120
    while len(list((killed / "replay").glob("*.npz"))) < 3 and time.time() < deadline:
        time.sleep(0.02)
    process.kill()
    process.wait()
    assert len(progress_rows(killed)) < 4  # killed before its budget's end
    run_module("lab.peers", "sqil", "--resume", killed)
    subprocess.run([*command, "--run-dir", str(whole)], cwd=ROOT, check=True, capture_output=True)
    assert progress_rows(killed) == progress_rows(whole)
