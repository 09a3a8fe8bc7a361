"""Test configuration: the repository root on sys.path and the Hypothesis profiles.

Profiles:
- "ci" (the default): derandomised, so every run draws the same examples, and small
  enough that `python -m pytest` finishes in seconds.
- "dev": many random examples, for hunting; select it with HYPOTHESIS_PROFILE=dev.
"""

import os
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

# `python -m pytest` puts the working directory on sys.path, the bare `pytest` script
# does not; make `import nets` work from either, and from any working directory.
ROOT = str(Path(__file__).resolve().parent.parent)
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

settings.register_profile(
    "ci",
    derandomize=True,
    database=None,
    max_examples=30,
    deadline=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile(
    "dev",
    max_examples=1000,
    deadline=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


@pytest.fixture(scope="session")
def hopper_demos(tmp_path_factory) -> Path:
    """One sparse Hopper-v4 trajectory from the shipped expert, for command-line tests."""
    import expert

    path = tmp_path_factory.mktemp("demos") / "hopper.npz"
    expert.write_demos(path, expert.make_demos("Hopper-v4", 1, "sparse", seed=0))
    return path


@pytest.fixture(autouse=True)
def release_run_dir_locks():
    """A run directory stays locked for the life of the process that opened it; the tests
    train many runs in one process, so each test gives its locks up at its end."""
    yield
    from helpers import release

    import harness

    for run_dir in list(harness._held_locks):
        release(run_dir)
    harness._checkpoint_files.clear()
