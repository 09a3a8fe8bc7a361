"""The installed package (`pip install .`, as .ci/run does) runs out of the box away from
the checkout: its modules, the shipped experts and Table 1 come with it. Skipped where
the project is not installed (running the tests from a checkout needs no install)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.helpers import ROOT


def isolated(*args: str, cwd) -> subprocess.CompletedProcess:
    """python -I ...: neither the working directory nor PYTHONPATH is on the path, so
    only an installed copy of the project can be imported."""
    return subprocess.run(
        [sys.executable, "-I", *args], capture_output=True, text=True, cwd=cwd, timeout=600
    )


def test_installed_package_finds_its_experts_and_trains(tmp_path):
    found = isolated("-c", "import expert; print(expert.__file__)", cwd=tmp_path)
    if found.returncode != 0:
        pytest.skip("the project is not installed (pip install . runs this test)")
    installed_from_checkout = found.stdout.strip().startswith(str(ROOT))  # pip install -e .
    table = isolated(
        "-c",
        "import expert; print(expert.load_expert('Hopper-v4').env_id,"
        " expert.reference_returns('Hopper-v4')[1] > 3000)",
        cwd=tmp_path,
    )
    assert table.stdout.split() == ["Hopper-v4", "True"], table.stderr
    run = isolated(
        "-m", "offpac_il", "--env", "Hopper-v4", "--total-steps", "200", "--eval-every", "200",
        "--eval-episodes", "1", "--noise-samples", "2", "--run-dir", "run", cwd=tmp_path,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "run" / "progress.csv").read_text().count("\n") == 3  # header, 0, 200
    if not installed_from_checkout:  # demonstrations are cached where the user works
        assert list((tmp_path / "demos").glob("Hopper-v4-sparse-4traj-seed0.npz"))
