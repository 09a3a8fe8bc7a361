"""Ctrl-C or `kill` (SIGINT, SIGTERM) stop a training run at its next checkpoint point
(harness.stop_at_next_checkpoint): the run saves a checkpoint there, says how to continue
and exits with status 130, so nothing since its last periodic checkpoint is lost. Every
trainer: the learner, an ablation, GAIL, SAC and ARS, each as its command line runs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import ROOT
from test_offpac_il import TINY_RUN

import harness

LONG = ["--eval-every", "100000", "--checkpoint-every", "1e9", "--log-every", "0"]
PENDULUM = "InvertedPendulum-v4"
TINY_GAIL = ["--env", "Hopper-v4", "--eval-episodes", "1", "--policy-hidden", "8", "8"]
TINY_GAIL += ["--value-hidden", "8", "8", "--discriminator-hidden", "8", "8"]
TINY_GAIL += ["--rollout-steps", "50", "--ppo-epochs", "2", "--minibatch-size", "16"]
TINY_GAIL += ["--discriminator-steps", "2", "--discriminator-batch", "16"]
TINY_SAC = ["--env", PENDULUM, "--hidden", "16", "16", "--batch-size", "32"]
TINY_SAC += ["--learning-starts", "200", "--eval-episodes", "1"]


def command_of(kind: str, run_dir: Path, demos: Path) -> tuple[list[str], str]:
    """(the command line of a long run whose only periodic checkpoint is at its start,
    the checkpoint counter of its progress)."""
    if kind == "learner":
        args = ["offpac_il.py", *TINY_RUN, "--demos", demos, "--total-steps", "100000"]
        return [*args, *LONG, "--run-dir", run_dir], "interactions"
    if kind == "ablation":  # Ours+IRL(E): a variant with networks of its own
        args = ["-m", "lab.ablations", *TINY_RUN, "--reward-learning", "entropy"]
        args += ["--demos", demos, "--total-steps", "100000"]
        return [*args, *LONG, "--run-dir", run_dir], "interactions"
    if kind == "gail":
        args = ["-m", "lab.baselines", "gail", *TINY_GAIL, "--demos", demos]
        return [*args, "--total-steps", "100000", *LONG, "--run-dir", run_dir], "interactions"
    if kind == "ars":  # rollouts in 2 worker processes; a line per iteration
        args = ["-m", "lab.ars", "--env", PENDULUM, "--workers", "2", "--steps", "1e8"]
        args += ["--eval-every", "1", "--checkpoint", run_dir / "checkpoint.npz"]
        return [*args, "--out", run_dir.parent / "x.npz"], "iteration"
    args = ["-m", "lab.sac", *TINY_SAC, "--steps", "100000", *LONG]
    return [*args, "--run-dir", run_dir, "--out", run_dir.parent / "x.npz"], "interactions"


def checkpointed(run_dir: Path, counter: str) -> int:
    if counter == "iteration":
        from lab import ars

        return ars.ARSState.load(run_dir / "checkpoint.npz").iteration
    counters = harness.load_arrays(run_dir / "checkpoint.npz")["counters"]
    return json.loads(str(counters))[counter]


# kill PID: the run's own process; Ctrl-C, and `timeout` or `kill -- -PGID`: the whole
# process group, ARS's worker processes included.
SIGNALS = [(signal.SIGTERM, False), (signal.SIGINT, True), (signal.SIGTERM, True)]


@pytest.mark.parametrize(
    ("signum", "to_group"), SIGNALS, ids=["SIGTERM", "SIGINT-group", "SIGTERM-group"]
)
@pytest.mark.parametrize("kind", ["learner", "ablation", "gail", "sac", "ars"])
def test_a_signal_stops_the_run_at_its_next_checkpoint(
    tmp_path, hopper_demos, kind, signum, to_group
):
    run_dir = tmp_path / "run"
    run_dir.mkdir()  # ARS's checkpoint file lives in it
    command, counter = command_of(kind, run_dir, hopper_demos)
    process = subprocess.Popen(
        [sys.executable, *map(str, command)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # a process group of its own, as a shell job has
    )
    try:
        # Once a few training lines are out, the run is past any checkpoint from its start.
        deadline, trained, last = time.time() + 120, 0, ""
        while trained < 3 and time.time() < deadline:
            line = process.stdout.readline()
            assert line, f"the run ended early: {process.communicate()[1]}"
            trained += line.startswith(("train", "iteration"))
            last = line if line.startswith("iteration") else last
        if to_group:
            os.killpg(process.pid, signum)
        else:
            process.send_signal(signum)
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:  # it ignored the signal: the test fails, nothing is left
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()

    assert process.returncode == 130, stderr
    assert stderr.strip().splitlines()[-1] == "interrupted; continue with --resume"
    assert checkpointed(run_dir, counter) > 0
    if kind == "ars":  # checkpointed at the signal, not only by the 10 s clock
        assert checkpointed(run_dir, counter) >= int(last.split()[1])


def test_an_interrupt_that_a_c_extension_reports_as_its_own_error_still_stops_the_run(capsys):
    """MuJoCo's first import calls into ctypes; the second signal's KeyboardInterrupt raised
    there comes out as ctypes.ArgumentError. The run still ends as interrupted (130)."""

    def body_interrupted_inside_a_ctypes_call():
        os.kill(os.getpid(), signal.SIGTERM)  # the first: stop at the next checkpoint
        try:
            os.kill(os.getpid(), signal.SIGTERM)  # the second: stop at once
            time.sleep(1)  # the handler runs here, in the main thread
        except KeyboardInterrupt:
            raise RuntimeError("argument 1: KeyboardInterrupt: ") from None

    def body_with_an_error_of_its_own():
        raise RuntimeError("a bug")

    assert harness.run_cli(body_interrupted_inside_a_ctypes_call) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith("interrupted")
    with pytest.raises(RuntimeError, match="a bug"):  # no signal: an error stays an error
        harness.run_cli(body_with_an_error_of_its_own)
