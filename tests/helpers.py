"""Helpers shared by the command-line tests of the learner and the baselines."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def release(run_dir) -> None:
    """Give up this process's lock on run_dir (harness holds it for the process's life;
    the tests train many runs in one process)."""
    import harness

    harness._checkpoint_files.discard((Path(run_dir) / harness.CHECKPOINT).resolve())
    fd = harness._held_locks.pop(Path(run_dir).resolve(), None)
    if fd is not None:
        os.close(fd)


def run_script(script: str, *args, check: bool = True) -> subprocess.CompletedProcess:
    """python ROOT/script args..., from the repository root; raises if check and it fails."""
    result = subprocess.run(
        [sys.executable, str(ROOT / script), *map(str, args)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
    )
    if check and result.returncode != 0:
        raise AssertionError(f"exit {result.returncode}: {result.stderr}")
    return result


def run_module(module: str, *args, check: bool = True) -> subprocess.CompletedProcess:
    """python -m module args..., from the repository root; raises if check and it fails."""
    result = subprocess.run(
        [sys.executable, "-m", module, *map(str, args)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
    )
    if check and result.returncode != 0:
        raise AssertionError(f"exit {result.returncode}: {result.stderr}")
    return result


def assert_one_line_error(result: subprocess.CompletedProcess, *fragments: str) -> str:
    """Exit status 2 and exactly one line on stderr, "error: ...", holding every fragment;
    returns that line."""
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2, (result.returncode, result.stderr)
    assert len(lines) == 1 and lines[0].startswith("error:"), result.stderr
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    return lines[0]


def read_rows(path: Path, drop=("wall_seconds",)) -> list[dict]:
    """A CSV file's rows as dicts, without the columns in `drop` (wall time differs)."""
    with open(path) as f:
        return [{k: v for k, v in row.items() if k not in drop} for row in csv.DictReader(f)]


def interrupted_after(episodes: int):
    """offpac_il.run_episode, raising as a kill would once `episodes` training episodes
    ran (training episodes are the ones given a replay buffer or rollout to fill)."""
    import offpac_il

    original, calls = offpac_il.run_episode, {"n": 0}

    def run_episode(*args, **kwargs):
        if len(args) >= 6 or kwargs.get("replay") is not None:
            calls["n"] += 1
            if calls["n"] > episodes:
                raise KeyboardInterrupt
        return original(*args, **kwargs)

    return run_episode
