"""Ctrl-C or `kill` (SIGINT, SIGTERM) stop a training run at its next checkpoint point
(nets.stop_at_next_checkpoint): the run saves a checkpoint there, says how to continue and
exits with status 130, so nothing since its last periodic checkpoint is lost."""

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
from test_baselines import TINY_GAIL_FLAGS
from test_offpac_il import TINY_RUN
from test_sac import PENDULUM, TINY_FLAGS

import expert
import nets

LONG = ["--eval-every", "100000", "--checkpoint-every", "1e9", "--log-every", "0"]


def command_of(kind: str, run_dir: Path, demos: Path) -> tuple[list[str], str]:
    """(the command line of a long run whose only periodic checkpoint is at its start,
    the checkpoint counter of its interactions)."""
    if kind == "learner":
        args = ["offpac_il.py", *TINY_RUN, "--demos", demos, "--total-steps", "100000"]
        return [*args, *LONG, "--run-dir", run_dir], "interactions"
    if kind == "gail":
        args = ["baselines.py", "gail", *TINY_GAIL_FLAGS, "--demos", demos]
        return [*args, "--total-steps", "100000", *LONG, "--run-dir", run_dir], "interactions"
    if kind == "ars":  # rollouts in 2 worker processes; a line per iteration
        args = ["expert.py", "train", "--env", PENDULUM, "--workers", "2", "--steps", "1e8"]
        args += ["--eval-every", "1", "--checkpoint", run_dir / "checkpoint.npz"]
        return [*args, "--out", run_dir.parent / "x.npz"], "iteration"
    args = ["expert.py", "train", "--env", PENDULUM, "--method", "sac", *TINY_FLAGS]
    args += ["--steps", "100000", *LONG, "--run-dir", run_dir, "--out", run_dir.parent / "x.npz"]
    return args, "env_steps"


def checkpointed_interactions(run_dir: Path, counter: str) -> int:
    if counter == "iteration":
        return expert.ARSState.load(run_dir / "checkpoint.npz").iteration
    counters = nets.load_arrays(run_dir / "checkpoint.npz")["counters"]
    return json.loads(str(counters))[counter]


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
@pytest.mark.parametrize("kind", ["learner", "gail", "sac", "ars"])
def test_a_signal_stops_the_run_at_its_next_checkpoint(tmp_path, hopper_demos, kind, signum):
    run_dir = tmp_path / "run"
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
        if signum == signal.SIGINT:  # Ctrl-C: the whole process group, workers included
            os.killpg(process.pid, signum)
        else:  # kill PID: the run's own process
            process.send_signal(signum)
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:  # it ignored the signal: the test fails, nothing is left
            process.kill()
            process.wait()

    assert process.returncode == 130, stderr
    assert stderr.strip().splitlines()[-1] == "interrupted; continue with --resume"
    assert checkpointed_interactions(run_dir, counter) > 0
    if kind == "ars":  # checkpointed at the signal, not only by the 10 s clock
        assert checkpointed_interactions(run_dir, counter) >= int(last.split()[1])
