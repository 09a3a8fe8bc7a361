"""What a resume checks (issue 46): the program that made the run, the demonstrations it
started on, its config.json; and that a stopped run's last line tells the truth about
what can be resumed. Real processes and real signals, tiny runs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import ROOT, assert_one_line_error, read_rows, run_module, run_script
from test_offpac_il import TINY_RUN

import expert
import harness

SHORT = [*TINY_RUN, "--total-steps", "100"]


def start(*args, cwd=ROOT) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, *map(str, args)],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


def stopped(process: subprocess.Popen, timeout: float) -> tuple[str, str]:
    """(stdout, stderr) of a process that must end within `timeout` s (killed if not)."""
    try:
        return process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.communicate()
        pytest.fail(f"the run held the signal for more than {timeout} s")


def wait_for_signal_handlers(process: subprocess.Popen, timeout: float = 120) -> None:
    """Until the process catches SIGTERM (run_cli has installed its handler): a signal
    before that would kill it without a word, which is not what these tests are about."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        status = Path(f"/proc/{process.pid}/status").read_text()
        caught = int(
            next(line for line in status.splitlines() if line.startswith("SigCgt:")).split()[1], 16
        )
        if caught >> (signal.SIGTERM - 1) & 1:
            return
        time.sleep(0.005)
    pytest.fail("the run never installed its signal handler")


def wait_for_line(process: subprocess.Popen, prefix: str) -> None:
    while True:
        line = process.stdout.readline()
        assert line, f"the run ended early: {process.communicate()[1]}"
        if line.startswith(prefix):
            return


def other_demos(path: Path) -> Path:
    expert.write_demos(path, expert.make_demos("Hopper-v4", 1, "sparse", seed=1))
    return path


# --- 1. a run is resumed by the program that made it ---


def test_an_ablation_run_resumed_by_the_learner_is_refused(tmp_path, hopper_demos):
    run_dir = tmp_path / "ablation"
    run_module(
        "lab.ablations", *SHORT, "--reward-learning", "entropy", "--demos", hopper_demos,
        "--run-dir", run_dir,
    )  # fmt: skip
    config = (run_dir / harness.CONFIG).read_text()
    refused = run_script("offpac_il.py", "--resume", run_dir, "--total-steps", "600", check=False)
    assert_one_line_error(refused, f"resume it with `python -m lab.ablations --resume {run_dir}`")
    assert (run_dir / harness.CONFIG).read_text() == config
    # A run made before config.json named its program is known by its switches.
    saved = json.loads(config)
    del saved[harness.PROGRAM]
    harness.write_config(run_dir, saved)
    refused = run_script("offpac_il.py", "--resume", run_dir, "--total-steps", "600", check=False)
    assert_one_line_error(refused, "python -m lab.ablations --resume")
    # Nor do lab.baselines and lab.peers resume it, nor a learner run (issue 46, item 13).
    for module, method in (("lab.baselines", "gail"), ("lab.peers", "sqil")):
        refused = run_module(module, method, "--resume", run_dir, check=False)
        assert_one_line_error(refused, "python -m lab.ablations --resume")
    run_module("lab.ablations", "--resume", run_dir, "--total-steps", "200")
    assert int(read_rows(run_dir / harness.PROGRESS)[-1]["interactions"]) >= 200


def test_a_resume_flag_given_an_empty_run_directory_is_refused(tmp_path):
    for result in (
        run_script("offpac_il.py", "--resume", "", "--run-dir", tmp_path / "r", check=False),
        run_module(
            "lab.baselines", "gail", "--resume", "", "--run-dir", tmp_path / "r", check=False
        ),
    ):
        assert_one_line_error(result, "--resume needs a run directory")
    assert not (tmp_path / "r").exists() and not any(tmp_path.iterdir())


# --- 2. a resume continues on the demonstrations the run started on ---


def test_a_resume_on_changed_demonstrations_is_refused(tmp_path, hopper_demos):
    """A relative --demos is stored absolute (a resume from elsewhere reads the same file)
    with its sha256; replacing the file between a kill -9 and --resume is refused."""
    demos = tmp_path / "demos.npz"
    demos.write_bytes(hopper_demos.read_bytes())
    run_dir = tmp_path / "run"
    args = ["offpac_il.py", *TINY_RUN, "--total-steps", "600", "--demos", "demos.npz"]
    process = start(ROOT / args[0], *args[1:], "--run-dir", run_dir, cwd=tmp_path)
    deadline = time.time() + 300
    while not (run_dir / harness.CHECKPOINT).exists() and time.time() < deadline:
        time.sleep(0.02)
    process.kill()
    process.communicate()
    config = json.loads((run_dir / harness.CONFIG).read_text())
    assert config["demos"] == str(demos)
    assert config[expert.DEMOS_SHA256] == expert.load_demos(demos, "Hopper-v4").sha256
    original = demos.read_bytes()
    other_demos(demos)
    refused = run_script("offpac_il.py", "--resume", run_dir, check=False)
    assert_one_line_error(refused, f"{demos} is not the demonstration file {run_dir} started on")
    demos.write_bytes(original)
    run_script("offpac_il.py", "--resume", run_dir)  # from ROOT, not from tmp_path
    assert int(read_rows(run_dir / harness.PROGRESS)[-1]["interactions"]) >= 600


# --- 3. config.json deleted mid-run ---


def test_a_config_deleted_mid_run_is_written_again_at_the_next_checkpoint(tmp_path, hopper_demos):
    run_dir = tmp_path / "run"
    args = [*TINY_RUN, "--total-steps", "600", "--demos", hopper_demos, "--run-dir", run_dir]
    process = start(ROOT / "offpac_il.py", *args)
    deadline = time.time() + 300
    while not (run_dir / harness.CHECKPOINT).exists() and time.time() < deadline:
        time.sleep(0.01)
    config = (run_dir / harness.CONFIG).read_text()
    (run_dir / harness.CONFIG).unlink()
    _, stderr = stopped(process, 300)
    assert process.returncode == 0, stderr
    assert (run_dir / harness.CONFIG).read_text() == config
    run_script("offpac_il.py", "--resume", run_dir, "--total-steps", "700")
    # Deleted after the last checkpoint: the resume says exactly what is missing.
    (run_dir / harness.CONFIG).unlink()
    refused = run_script("offpac_il.py", "--resume", run_dir, check=False)
    assert_one_line_error(refused, f"{run_dir} cannot be resumed: its config.json is missing")


# --- 4 and 5. signals: honoured soon, and the last line tells the truth ---


def test_two_signals_before_the_first_checkpoint_tell_the_truth(tmp_path, hopper_demos):
    run_dir = tmp_path / "run"
    args = [ROOT / "offpac_il.py", *SHORT, "--demos", hopper_demos, "--run-dir", run_dir]
    process = start(*args)
    wait_for_signal_handlers(process)
    process.send_signal(signal.SIGTERM)
    time.sleep(0.05)  # two signals at once would be delivered as one
    process.send_signal(signal.SIGTERM)
    _, stderr = stopped(process, 60)
    assert process.returncode == 130, stderr
    last = stderr.strip().splitlines()[-1]
    if last == "interrupted; continue with --resume":
        run_script("offpac_il.py", "--resume", run_dir)
    else:  # stopped before the first checkpoint: nothing to resume, and it says so
        assert "run the same command again" in last and "--resume" not in last, last
        assert not (run_dir / harness.CHECKPOINT).exists()
        run_script(*args)
    assert int(read_rows(run_dir / harness.PROGRESS)[-1]["interactions"]) >= 100


def test_a_signal_stops_a_long_evaluation_between_its_episodes(tmp_path, hopper_demos):
    """The first evaluation, of 100 000 episodes, is stopped after a signal within
    seconds; the state before it is checkpointed, so the run resumes (and evaluates again)."""
    run_dir = tmp_path / "run"
    args = [*SHORT, "--eval-episodes", "100000", "--demos", hopper_demos, "--run-dir", run_dir]
    process = start(ROOT / "offpac_il.py", *args)
    wait_for_line(process, "hands over")
    time.sleep(0.5)
    process.send_signal(signal.SIGTERM)
    _, stderr = stopped(process, 30)
    assert process.returncode == 130, stderr
    assert stderr.strip().splitlines()[-1] == "interrupted; continue with --resume"
    counters = json.loads(str(harness.load_arrays(run_dir / harness.CHECKPOINT)["counters"]))
    assert counters["interactions"] == 0 and counters["eval_rounds"] == 0


def test_a_signal_stops_the_making_of_demonstrations_between_trajectories(tmp_path):
    """150 trajectories of default demonstrations take about 25 s to make; a signal stops
    it within seconds, with nothing written (neither the cache file nor the run)."""
    seed = 46_046_046  # a cache file of its own
    cached = expert.default_demos_path("Hopper-v4", 150, "sparse", seed)
    assert not cached.exists()
    run_dir = tmp_path / "run"
    args = [*SHORT, "--trajectories", "150", "--demo-seed", seed, "--run-dir", run_dir]
    process = start(ROOT / "offpac_il.py", *args)
    try:
        wait_for_signal_handlers(process)
        time.sleep(3)  # into the trajectories
        process.send_signal(signal.SIGTERM)
        _, stderr = stopped(process, 10)
    finally:
        cached.unlink(missing_ok=True)  # were the signal ignored
    assert process.returncode == 130, stderr
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("interrupted before the run started, nothing written"), last
    assert not run_dir.exists()


def test_run_clis_last_line_says_whether_a_run_can_be_resumed(tmp_path, capsys):
    def interrupted_run(checkpointed: bool):
        def body():
            harness.open_run_dir(tmp_path / str(checkpointed), resume=False)
            if checkpointed:
                harness.save_arrays(tmp_path / str(checkpointed) / harness.CHECKPOINT, {})
            raise KeyboardInterrupt

        return body

    assert harness.run_cli(interrupted_run(True)) == 130
    assert capsys.readouterr().err == "interrupted; continue with --resume\n"
    assert harness.run_cli(interrupted_run(False)) == 130
    assert "before the first checkpoint" in capsys.readouterr().err
    assert harness.run_cli(interrupted_run(False), at_once=True) == 130
    assert capsys.readouterr().err == "interrupted\n"
