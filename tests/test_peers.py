"""lab/peers.py: SQIL's batch, a tiny run that resumes exactly, and the command line.

SQIL has no gradient of its own (its update is sac.update, checked in tests/test_sac.py);
what is SQIL's is the batch: which rows, with which rewards.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest
from helpers import ROOT, assert_one_line_error, read_rows, run_module

import harness
import offpac_il
from lab import peers, sac

TINY = ["--env", "Hopper-v4", "--hidden", "8", "8", "--batch-size", "16", "--eval-episodes", "1"]
TINY += ["--total-steps", "600", "--eval-every", "200", "--learning-starts", "100"]
TINY += ["--checkpoint-every", "0", "--log-every", "0"]


def tiny_config(run_dir, demos, seed=0) -> peers.SQILConfig:
    argv = ["sqil", *TINY, "--demos", str(demos), "--seed", str(seed), "--run-dir", str(run_dir)]
    config, method, resume = peers.parse(argv)
    assert (method, resume) == ("sqil", False)
    return config


def test_sqil_batch_takes_half_from_each_buffer_with_rewards_1_and_0():
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
    batch = peers.sqil_batch(demonstrations, replay, rng, 11)
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


def test_sqil_run_resumes_exactly(tmp_path, hopper_demos, monkeypatch):
    whole, other, interrupted = tmp_path / "whole", tmp_path / "other", tmp_path / "cut"
    peers.train(tiny_config(whole, hopper_demos), "sqil")
    peers.train(tiny_config(other, hopper_demos, seed=1), "sqil")
    with monkeypatch.context() as patch:
        patch.setattr(sac, "update", interrupted_after(250))
        with pytest.raises(KeyboardInterrupt):
            peers.train(tiny_config(interrupted, hopper_demos), "sqil")
    partial = progress_rows(interrupted)
    assert 0 < len(partial) < len(progress_rows(whole))
    peers.train(tiny_config(interrupted, hopper_demos), "sqil", resume=True)

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
    assert saved["method"] == "sqil" and saved["standardize"] is False


def test_command_line_help_resume_and_refusals(tmp_path, hopper_demos):
    assert "sqil" in run_module("lab.peers", "--help").stdout
    assert "--learning-starts" in run_module("lab.peers", "sqil", "--help").stdout
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
    ]:
        assert_one_line_error(run_module("lab.peers", *args, check=False), fragment)
    # A run is resumed by the method that made it.
    saved = json.loads((run_dir / "config.json").read_text())
    harness.write_config(run_dir, {**saved, "method": "iq-learn"})
    result = run_module("lab.peers", "sqil", "--resume", run_dir, check=False)
    assert_one_line_error(result, "not a sqil run")


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
