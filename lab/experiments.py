"""The sweep behind experiments.ipynb, and the figures it draws from finished runs.

A run is a command line: a script, its arguments and a run directory (`RunSpec`). Every
training script of the project (`offpac_il.py`, `lab/ablations.py`, `lab/baselines.py`)
writes the same run directory (harness.py): `config.json`, `progress.csv` (one row per
evaluation), `checkpoint.npz` while it runs and `policy_final.npz` once it has finished.
So a sweep is only bookkeeping:

- a run whose `policy_final.npz` exists is finished and skipped;
- a run with a `checkpoint.npz` but no `policy_final.npz` was interrupted, and continues
  with `SCRIPT [SUBCOMMAND] --resume RUN_DIR`;
- any other run starts with `SCRIPT ARGS --run-dir RUN_DIR`.

`sweep(specs, executor)` hands each spec to `run_one` through any
`concurrent.futures.Executor`: by default a local thread pool whose threads only wait for
their run's subprocess, or a Dask cluster's `Client(...).get_executor()`. A run that fails
is reported in the returned statuses (with the tail of its log), never raised mid-sweep.

Relative paths (scripts, run directories, sweep roots) are relative to the repository root,
the folder above this file, on whichever machine runs them; a script of this package runs
as `python -m lab.NAME` from there. A Dask cluster therefore needs the
repository (and its requirements) on every worker, importable (start the workers from it
with `PYTHONPATH=$PWD dask worker tcp://SCHEDULER:8786 --nthreads 1`: one run per worker
thread, a learner run keeps two cores busy), and the run directories on a file system
that the workers and the notebook share.

Figures (matplotlib, Agg), each written as a PNG with the CSV of what it plots beside it;
seeds are pooled into their mean with a min-max band:

- Figure 2: final normalised score vs number of trajectories, sparse and dense;
- Figure 3: normalised score vs wall time and vs interactions (one setting);
- Figure 4: normalised score vs interactions for the ablations.

Command line, from the repository root:

    python -m lab.experiments sweep quick|full|ablations [--runs DIR] [--workers N]
                        [--scheduler ADDRESS] [--methods BC GAIL ...] [--envs Hopper-v4 ...]
    python -m lab.experiments figures quick|full [--runs DIR [DIR ...]] [--out DIR]
    python -m lab.experiments curves OUT.png RUN_DIR [RUN_DIR ...] [--label-by termination]
                        [--x-max N]
    python -m lab.experiments hold RUN_DIR [RUN_DIR ...] [--since N] [--until N]
    python -m lab.experiments probe RUN_DIR [--episodes 3] [--steps 300]
    python -m lab.experiments evaluate RUN_DIR [--policy final|best|checkpoint|average|N|snapshots]
                        [--episodes 20]
    python -m lab.experiments gradient-noise RUN_DIR [--samples 8 128] [--draws 30]
    python -m lab.experiments average-snapshots RUN_DIR [--horizons 10000 30000] [--episodes 5]
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import re
import subprocess
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import FIRST_COMPLETED, Executor, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

import harness
from harness import UserError

ROOT = Path(__file__).resolve().parent.parent  # the repository root
FINISHED = "policy_final.npz"  # written by a script only when its run has finished
CHECKPOINT = "checkpoint.npz"  # present while a run can be resumed
SPEC_FILE = "sweep.json"  # the spec that made the run, written by run_one
LOG_FILE = "sweep.log"  # the run's stdout and stderr, one block per attempt

# ----------------------------------------------------------------------------------------
# Methods: how each compared method and ablation is launched.
# ----------------------------------------------------------------------------------------

# name -> (script, the arguments that select the method). The ablations are switches of
# lab/ablations.py (its AblationConfig: on_policy, reward_learning, policy_type; Sec. 5.3,
# Figure 4), whose other flags are offpac_il.py's. `missing_support` checks each against
# the script's --help, so a method whose script or flag does not exist is reported and
# skipped, never faked.
LEARNER, ABLATIONS_SCRIPT, BASELINES = "offpac_il.py", "lab/ablations.py", "lab/baselines.py"
PEERS = "lab/peers.py"  # the off-policy peers on SAC (not in the paper)
METHODS: dict[str, tuple[str, tuple[str, ...]]] = {
    "Ours": (LEARNER, ()),
    "BC": (BASELINES, ("bc",)),
    "GAIL": (BASELINES, ("gail",)),
    "BC+GAIL": (BASELINES, ("bc-gail",)),
    "SQIL": (PEERS, ("sqil",)),
    "IQ-Learn": (PEERS, ("iq-learn",)),
    "Ours+OnP": (ABLATIONS_SCRIPT, ("--on-policy",)),
    "Ours+IRL(D)": (ABLATIONS_SCRIPT, ("--reward-learning", "discriminator")),
    "Ours+IRL(E)": (ABLATIONS_SCRIPT, ("--reward-learning", "entropy")),
    "Ours+GP": (ABLATIONS_SCRIPT, ("--policy-type", "gaussian")),
    "Ours+DP": (ABLATIONS_SCRIPT, ("--policy-type", "deterministic")),
}
# A method that starts from another's finished run of the same setting:
# name -> (that method, the flag that names its run directory).
STARTS_FROM = {"BC+GAIL": ("BC", "--bc-init")}
# Figures 2 and 3: the paper's (Sec. 5.2), then the off-policy peers.
COMPARED = ("Ours", "BC", "GAIL", "BC+GAIL", "SQIL", "IQ-Learn")
ABLATIONS = ("Ours+OnP", "Ours+IRL(D)", "Ours+IRL(E)", "Ours+GP", "Ours+DP")  # Figure 4

# Quick mode: configurations that train in a few seconds each on 2 cores. They show that
# the pipeline works end to end, not how the methods compare.
QUICK_ARGS: dict[str, tuple[str, ...]] = {
    LEARNER: (
        *("--total-steps", "300", "--eval-every", "100", "--eval-episodes", "1"),
        *("--policy-hidden", "8", "8", "--critic-hidden", "16", "16"),
        *("--noise-samples", "4", "--target-samples", "2", "--batch-size", "8"),
    ),
    BASELINES: ("--total-steps", "300", "--eval-every", "100", "--eval-episodes", "1"),
}
QUICK_ARGS[ABLATIONS_SCRIPT] = QUICK_ARGS[LEARNER]
QUICK_ARGS[PEERS] = (
    *QUICK_ARGS[BASELINES],
    *("--hidden", "16", "16", "--batch-size", "16", "--learning-starts", "100"),
)


def resolve(path) -> Path:
    """A path relative to the repository root (absolute paths stay as they are)."""
    return ROOT / path


def launcher(script: str) -> list[str]:
    """How a script starts, from the repository root: `python -m lab.NAME` for a module
    of a package there (so that it imports the core), `python SCRIPT` for any other."""
    path = Path(script)
    if not path.is_absolute() and len(path.parts) > 1 and path.suffix == ".py":
        return [sys.executable, "-m", ".".join(path.with_suffix("").parts)]
    return [sys.executable, script]


# ----------------------------------------------------------------------------------------
# One run.
# ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunSpec:
    """One run: `python SCRIPT ARGS --run-dir RUN_DIR` (`launcher`).

    `labels` (method, env, sampling, trajectories, seed, ...) do not change the command;
    they are saved in the run directory's sweep.json and group runs in the figures.
    `needs`: run directories that must hold finished runs before this one starts (BC+GAIL
    starts from a BC run); a sweep that holds them runs them first.
    """

    script: str
    args: tuple[str, ...]
    run_dir: str
    labels: dict = field(default_factory=dict, compare=False, hash=False)
    needs: tuple[str, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "args", tuple(str(a) for a in self.args))
        object.__setattr__(self, "needs", tuple(str(n) for n in self.needs))
        object.__setattr__(self, "script", str(self.script))
        object.__setattr__(self, "run_dir", str(self.run_dir))

    @property
    def subcommand(self) -> tuple[str, ...]:
        """The leading positional arguments (`bc` in `lab/baselines.py bc --seed 0`)."""
        leading = []
        for arg in self.args:
            if arg.startswith("-"):
                break
            leading.append(arg)
        return tuple(leading)

    def command(self, resume: bool = False) -> list[str]:
        if resume:  # the run's saved config.json holds every other setting
            return [*launcher(self.script), *self.subcommand, "--resume", self.run_dir]
        return [*launcher(self.script), *self.args, "--run-dir", self.run_dir]


@dataclass
class RunResult:
    """What happened to one spec in a sweep.

    status: "skipped" (finished before), "completed" (ran from the start to the end now),
    "resumed" (continued from a checkpoint to the end now) or "failed" (message says why).
    """

    spec: RunSpec
    status: str
    returncode: int | None = None
    seconds: float = 0.0
    message: str = ""

    @property
    def ok(self) -> bool:
        return self.status != "failed"

    def line(self) -> str:
        text = f"{self.status:9s} {self.seconds:7.1f} s  {self.spec.run_dir}"
        return f"{text}\n          {self.message}" if self.message else text


def run_one(spec: RunSpec) -> RunResult:
    """Run, resume or skip one spec; never raises for a failed run.

    Module-level and free of closures so that any executor can pickle it (Dask sends it
    by reference: the workers import this module).
    """
    started = time.perf_counter()
    run_dir, script = resolve(spec.run_dir), resolve(spec.script)

    def result(status: str, returncode=None, message="") -> RunResult:
        return RunResult(spec, status, returncode, time.perf_counter() - started, message)

    if (run_dir / FINISHED).exists():
        return result("skipped")
    if not script.is_file():
        return result("failed", message=f"no script {script}")
    unfinished = [need for need in spec.needs if not (resolve(need) / FINISHED).exists()]
    if unfinished:
        return result("failed", message=f"needs the finished run {unfinished[0]}")
    resume = (run_dir / CHECKPOINT).exists()
    command = spec.command(resume)
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / SPEC_FILE).write_text(
            json.dumps({**asdict(spec), "command": command[1:]}, indent=2) + "\n"
        )
        with open(run_dir / LOG_FILE, "a") as log:
            log.write(f"\n# {time.strftime('%Y-%m-%d %H:%M:%S')} {' '.join(command[1:])}\n")
            log.flush()
            start_of_attempt = log.tell()
            returncode = subprocess.call(
                command, cwd=ROOT, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT
            )
    except OSError as error:
        return result("failed", message=f"could not launch: {error}")
    if returncode != 0:
        return result(
            "failed", returncode, f"exit {returncode}: {_log_tail(run_dir, start_of_attempt)}"
        )
    if not (run_dir / FINISHED).exists():
        return result("failed", returncode, f"exit 0 but no {FINISHED} in {run_dir}")
    return result("resumed" if resume else "completed", returncode)


def _log_tail(run_dir: Path, offset: int, lines: int = 3) -> str:
    with open(run_dir / LOG_FILE, errors="replace") as log:
        log.seek(offset)
        text = [line.strip() for line in log.read().splitlines() if line.strip()]
    return " | ".join(text[-lines:]) or "no output"


# ----------------------------------------------------------------------------------------
# The sweep.
# ----------------------------------------------------------------------------------------


def default_workers() -> int:
    """Runs at a time in the default pool: one per two cores (a learner run keeps two
    cores busy with its own row chunks, harness.map_row_chunks)."""
    return max(1, (os.cpu_count() or 1) // 2)


def sweep(
    specs: Iterable[RunSpec],
    executor: Executor | None = None,
    *,
    workers: int | None = None,
    echo: Callable[[str], None] | None = print,
) -> list[RunResult]:
    """Run every spec through `executor`; results in the order of `specs`.

    executor: any concurrent.futures.Executor, e.g. `distributed.Client(...).get_executor()`.
    None: a ThreadPoolExecutor of `workers` threads (default `default_workers()`), shut
    down at the end. Threads rather than processes because each run is a subprocess
    anyway: a thread only waits for it, nothing needs pickling, and nothing forks a
    process that holds threads (a Jupyter kernel does). Ctrl-C (or a kernel interrupt)
    reaches the runs through the process group: they stop, and the next sweep resumes
    them from their last checkpoint.

    A spec starts once the specs it needs (RunSpec.needs) in the same sweep have ended;
    if one of them failed, it fails without starting.

    echo: called with one line per run as it ends (None: quiet).
    """
    specs = list(specs)
    index: dict[Path, int] = {}
    for i, spec in enumerate(specs):
        run_dir = resolve(spec.run_dir).resolve()
        if run_dir in index:
            raise ValueError(f"two specs share the run directory {spec.run_dir}")
        index[run_dir] = i
    # The specs each spec waits for (needs outside the sweep are run_one's to check).
    waits_for = {
        i: {index[d] for d in (resolve(n).resolve() for n in spec.needs) if d in index}
        for i, spec in enumerate(specs)
    }
    own_executor = executor is None
    if own_executor:
        executor = ThreadPoolExecutor(max_workers=workers or default_workers())
    results: list[RunResult | None] = [None] * len(specs)
    running: dict = {}

    def record(i: int, result: RunResult) -> None:
        results[i] = result
        if echo is not None:
            echo(result.line())

    def start_ready() -> None:
        for i, deps in list(waits_for.items()):
            if any(results[d] is None for d in deps):
                continue
            del waits_for[i]
            failed = [specs[d].run_dir for d in deps if not results[d].ok]
            if failed:
                record(i, RunResult(specs[i], "failed", message=f"needs {failed[0]}, which failed"))
            else:
                running[executor.submit(run_one, specs[i])] = i

    try:
        start_ready()
        while running:
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                i = running.pop(future)
                try:
                    record(i, future.result())
                except Exception as error:  # the executor itself failed (e.g. a lost worker)
                    record(
                        i, RunResult(specs[i], "failed", message=f"{type(error).__name__}: {error}")
                    )
            start_ready()
        for i in waits_for:  # only a cycle of needs leaves specs waiting
            record(i, RunResult(specs[i], "failed", message="its needs form a cycle"))
    finally:
        if own_executor:
            executor.shutdown(wait=True, cancel_futures=True)
    return results


def status_counts(results: Iterable[RunResult]) -> dict[str, int]:
    counts: dict[str, int] = defaultdict(int)
    for r in results:
        counts[r.status] += 1
    return dict(counts)


# ----------------------------------------------------------------------------------------
# Building specs.
# ----------------------------------------------------------------------------------------


def run_dir_of(root, method: str, env: str, sampling: str, trajectories: int, seed: int) -> Path:
    """The layout of a sweep: ROOT/ENV/METHOD/SAMPLING-Ntraj/seedS."""
    return Path(root) / env / _slug(method) / f"{sampling}-{trajectories}traj" / f"seed{seed}"


def method_spec(
    method: str,
    root,
    *,
    env: str,
    seed: int,
    trajectories: int,
    sampling: str,
    extra_args: Sequence[str] = (),
) -> RunSpec:
    """The spec of one method (a name in METHODS) on one setting, in the layout of
    `run_dir_of`. A method of STARTS_FROM names (and needs) the run it starts from: the
    run of its base method with the same setting under the same root."""
    script, selector = METHODS[method]
    setting = dict(env=env, sampling=sampling, trajectories=trajectories, seed=seed)
    args = [
        *selector,
        *("--env", env, "--seed", seed, "--trajectories", trajectories, "--sampling", sampling),
        *extra_args,
    ]
    needs = []
    if method in STARTS_FROM:
        base, flag = STARTS_FROM[method]
        needs.append(run_dir_of(root, base, **setting))
        args += [flag, needs[-1]]
    return RunSpec(
        script, args, run_dir_of(root, method, **setting), dict(method=method, **setting), needs
    )


def grid(
    root,
    methods: Sequence[str],
    *,
    envs: Sequence[str] = ("Hopper-v4",),
    seeds: Sequence[int] = (0,),
    trajectories: Sequence[int] = (4,),
    samplings: Sequence[str] = ("sparse",),
    extra_args: dict[str, Sequence[str]] | None = None,
) -> list[RunSpec]:
    """Every combination of methods x envs x samplings x trajectories x seeds, in the
    layout of `run_dir_of`. extra_args maps a script (e.g. "offpac_il.py") to
    arguments added to each of its runs."""
    extra_args = extra_args or {}
    return [
        method_spec(
            method, root, env=env, seed=seed, trajectories=n, sampling=sampling,
            extra_args=extra_args.get(METHODS[method][0], ()),
        )
        for method in methods
        for env in envs
        for sampling in samplings
        for n in trajectories
        for seed in seeds
    ]  # fmt: skip


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in name).strip("-").lower()


def envs_with_experts(table_path=ROOT / "experts" / "table.json") -> list[str]:
    """The paper's tasks (-v4) whose expert exists (the only ones with a normalised score);
    Table 1's -v5 rows serve runs on those tasks, not the figures."""
    from lab.table import PAPER_TASKS

    table = json.loads(Path(table_path).read_text())
    return [env for env in PAPER_TASKS if (table.get(env) or {}).get("expert_mean") is not None]


def plan(quick: bool, root) -> list[RunSpec]:
    """The runs behind Figures 2-4.

    quick: Hopper-v4, seeds 0 and 1, 1 and 4 trajectories, sparse and dense, every method
    at QUICK_ARGS (seconds per run), and the ablations at 4 sparse trajectories.
    full: each script's defaults (offpac_il.py's: Appendix B with the README's two
    measured deviations): every task with an expert, 3 seeds (Sec. 5.1: "three
    experiments on each task"), 1, 4, 7 and 10 trajectories (the paper does not list its
    counts), sparse and dense; the ablations at 4 sparse
    trajectories on Ant-v4 (the paper's Figure 4) once its expert exists, else Hopper-v4.
    Figures 3 and 4 reuse the Figure 2 runs of their setting (Ours at 4 sparse
    trajectories): no run is made twice.
    """
    envs = ["Hopper-v4"] if quick else envs_with_experts()
    seeds = (0, 1) if quick else (0, 1, 2)
    counts = (1, 4) if quick else (1, 4, 7, 10)
    extra = QUICK_ARGS if quick else {}
    ablation_env = "Ant-v4" if "Ant-v4" in envs else "Hopper-v4"
    return grid(
        root, COMPARED, envs=envs, seeds=seeds, trajectories=counts,
        samplings=("sparse", "dense"), extra_args=extra,
    ) + grid(
        root, ABLATIONS, envs=[ablation_env], seeds=seeds, trajectories=(4,),
        samplings=("sparse",), extra_args=extra,
    )  # fmt: skip


# Figure 4 within a 2-core machine's means: the "full" plan's ablations run each script's
# defaults (128 noise samples, 300 000 interactions: about 10 hours a run here). This plan
# runs Ours and the five ablations with 8 noise samples and PN's learning rate at 3e-5
# (README, Results point 7: 8x cheaper, and it held the expert on Hopper-v4 in 3 of 3
# seeds, as the 128-sample default at 2.3e-5 has so far) over 60 000 interactions, the
# span in which Ours reaches and holds the expert there: 18 runs of about 28 minutes each
# on one core (measured beside a 128-sample run on the other).
ABLATION_SWEEP_ARGS = ("--total-steps", "60000", "--noise-samples", "8", "--policy-lr", "3e-5")


def ablation_plan(root, env: str = "Hopper-v4", seeds: Sequence[int] = (0, 1, 2)) -> list[RunSpec]:
    """The runs behind Figure 4 at ABLATION_SWEEP_ARGS: Ours and ABLATIONS, 4 sparse
    trajectories, on one task; seed by seed, so a sweep cut short has every method."""
    specs = grid(
        root, ("Ours", *ABLATIONS), envs=[env], seeds=seeds,
        extra_args={LEARNER: ABLATION_SWEEP_ARGS, ABLATIONS_SCRIPT: ABLATION_SWEEP_ARGS},
    )  # fmt: skip
    return sorted(specs, key=lambda spec: spec.labels["seed"])


# ----------------------------------------------------------------------------------------
# What exists yet.
# ----------------------------------------------------------------------------------------


def _help_text(script: str, subcommand: tuple[str, ...]) -> str | None:
    """`python SCRIPT [SUBCOMMAND] --help`, or None when that fails (not cached: scripts
    change while a notebook's kernel lives)."""
    path = resolve(script)
    if not path.is_file():
        return None
    done = subprocess.run(
        [*launcher(script), *subcommand, "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
    )
    return done.stdout if done.returncode == 0 else None


def missing_support(spec: RunSpec, _helps: dict | None = None) -> str | None:
    """Why `spec` cannot run with the scripts as they are (None: it can).

    Checks that the script exists, that `SCRIPT [SUBCOMMAND] --help` works and that it
    lists every --flag of the spec; not that the flags' values are accepted.
    """
    if not resolve(spec.script).is_file():
        return f"{spec.script} does not exist yet"
    helps = {} if _helps is None else _helps
    key = (spec.script, spec.subcommand)
    if key not in helps:
        helps[key] = _help_text(*key)
    help_text = helps[key]
    shown = " ".join([spec.script, *spec.subcommand])
    if help_text is None:
        return f"`{shown} --help` fails"
    if not help_text.strip():
        return f"`{shown} --help` lists no options yet"
    flags = {arg.split("=")[0] for arg in spec.args if arg.startswith("--")}
    # Every --word of the help text: a switch is listed as "[--on-policy | --no-on-policy]"
    # and "--on-policy, --no-on-policy", so split words would carry brackets and commas.
    listed = set(re.findall(r"--[\w-]+", help_text))
    unknown = sorted(flag for flag in flags if flag not in listed)
    if unknown:
        return f"{spec.script} has no {', '.join(unknown)} yet"
    return None


def select(
    specs: Sequence[RunSpec], methods: Iterable[str] = (), envs: Iterable[str] = ()
) -> list[RunSpec]:
    """The specs of the given methods and environments (empty: all), with the runs they
    start from (BC+GAIL keeps its BC run), in plan order: one part of a plan, run alone."""
    methods, envs = set(methods), set(envs)
    chosen = {
        spec.run_dir
        for spec in specs
        if (not methods or spec.labels.get("method") in methods)
        and (not envs or spec.labels.get("env") in envs)
    }
    chosen |= {need for spec in specs if spec.run_dir in chosen for need in spec.needs}
    return [spec for spec in specs if spec.run_dir in chosen]


def split_runnable(specs: Iterable[RunSpec]) -> tuple[list[RunSpec], dict[str, list[str]]]:
    """(specs that can run, {method: reason} for the methods that cannot)."""
    runnable, skipped, helps = [], {}, {}
    for spec in specs:
        reason = missing_support(spec, helps)
        if reason is None:
            runnable.append(spec)
        else:
            skipped.setdefault(spec.labels.get("method", spec.script), reason)
    return runnable, skipped


# ----------------------------------------------------------------------------------------
# Reading runs.
# ----------------------------------------------------------------------------------------


TEXT_COLUMNS = ("handover",)


def read_progress(run_dir) -> dict[str, np.ndarray]:
    """progress.csv as {column: float array}, empty cells NaN; TEXT_COLUMNS (the file a
    run hands over) as arrays of strings."""
    try:
        with open(Path(run_dir) / "progress.csv") as f:
            rows = list(csv.DictReader(f))
    except OSError as error:
        raise UserError(f"{run_dir}: no readable progress.csv ({error.strerror})") from None
    if not rows:
        return {}

    def column(key: str) -> np.ndarray:
        if key in TEXT_COLUMNS:
            return np.array([r[key] for r in rows])
        return np.array([float(r[key]) if r[key] not in ("", None) else np.nan for r in rows])

    return {key: column(key) for key in rows[0]}


def need_columns(progress: dict[str, np.ndarray], run_dir, *columns: str) -> None:
    """Refuse a progress.csv without the columns a table or a figure reads, such as an
    expert trainer's (lab/sac.py, lab/ars.py), which has no normalized_score."""
    missing = [column for column in columns if column not in progress]
    if missing:
        what = "no rows" if not progress else f"no column {', '.join(missing)}"
        raise UserError(
            f"{Path(run_dir) / 'progress.csv'} has {what}; give runs of offpac_il.py, "
            f"lab/ablations.py or lab/baselines.py"
        )


def read_config(run_dir) -> dict:
    return harness.read_config(run_dir)


@dataclass
class Run:
    """A run directory as the figures see it."""

    run_dir: Path
    labels: dict  # method, env, sampling, trajectories, seed
    progress: dict[str, np.ndarray]
    finished: bool


LABEL_KEYS = ("method", "env", "sampling", "trajectories", "seed")


# The switches of lab/ablations.py's AblationConfig that turn Ours into an ablation.
ABLATION_SWITCHES = ("on_policy", "reward_learning", "policy_type")


def learner_config(config: dict):
    """The AblationConfig of a learner run's config.json (offpac_il.py's or
    lab/ablations.py's): settings it lacks are the ones the run had."""
    import offpac_il
    from lab import ablations

    return harness.saved_config(ablations.AblationConfig, config, offpac_il.PAPER_SETTINGS)


def selector_settings(selector: Sequence[str]) -> dict:
    """The settings that a learner method's flags (its METHODS selector) give, the
    others at their defaults: the switches of lab/ablations.py's AblationConfig."""
    from lab import ablations

    parser = argparse.ArgumentParser()
    harness.add_dataclass_flags(parser, ablations.AblationConfig)
    return vars(parser.parse_args(list(selector)))


def method_of(config: dict) -> str:
    """The METHODS name of a run made by hand, from its config.json: lab/baselines.py and
    lab/peers.py save their subcommand as "method"; a learner run is Ours or the ablation
    whose switches it has (a mix of switches is named by them)."""
    if "method" in config:
        for name, (script, selector) in METHODS.items():
            if script in (BASELINES, PEERS) and selector == (config["method"],):
                return name
        return str(config["method"])
    config = asdict(learner_config(config))  # older runs lack newer switches
    for name, (script, selector) in METHODS.items():
        if script in (LEARNER, ABLATIONS_SCRIPT):
            flags = selector_settings(selector)
            if all(flags[k] == config[k] for k in ABLATION_SWITCHES):
                return name
    ours = selector_settings(())
    return "Ours+" + ",".join(f"{k}={config[k]}" for k in ABLATION_SWITCHES if config[k] != ours[k])


def run_settings(run_dir) -> dict:
    """A run's config.json with its METHODS name as "method", and the settings added
    since the run started filled in with the values it ran with."""
    from lab import baselines, peers

    config = read_config(run_dir)
    if config.get("method") in peers.METHODS:
        settings = peers.saved_settings(config)
    elif "method" in config:
        settings = baselines.saved_settings(config)
    else:
        settings = learner_config(config)
    return {**asdict(settings), "method": method_of(config)}


def load_run(run_dir) -> Run:
    """Labels from sweep.json, else from config.json (a run made by hand). A run is
    finished when its policy_final.npz exists or, for a run kept without its policies,
    when its progress.csv reaches the interaction budget of its config.json (BC: when it
    stopped, `bc_stopped`)."""
    run_dir = Path(run_dir)
    labels = {"method": "Ours"}
    config = {}
    if (run_dir / "config.json").exists():
        config = read_config(run_dir)
        labels.update({k: config[k] for k in LABEL_KEYS if k in config})
        labels["method"] = method_of(config)
    if (run_dir / SPEC_FILE).exists():
        labels.update(json.loads((run_dir / SPEC_FILE).read_text())["labels"])
    progress = read_progress(run_dir)
    budget = config.get("total_steps")
    reached = bool(progress) and budget is not None and progress["interactions"][-1] >= budget
    reached = reached or bc_stopped(run_dir, config)
    return Run(run_dir, labels, progress, (run_dir / FINISHED).exists() or reached)


def bc_stopped(run_dir: Path, config: dict) -> bool:
    """Has a BC run (whose budget counts updates, not interactions) ended, by its
    diagnostics.csv's last evaluation and lab/baselines.bc_finished?"""
    diagnostics = run_dir / "diagnostics.csv"
    if config.get("method") != "bc" or not diagnostics.exists():
        return False
    with open(diagnostics) as f:
        rows = list(csv.DictReader(f))
    if not rows or not rows[-1].get("best_update"):
        return False
    from lab import baselines

    settings = baselines.saved_settings(config)
    updates, best = int(float(rows[-1]["updates"])), int(float(rows[-1]["best_update"]))
    # Evaluations come every eval_every updates, so those since the best one:
    return baselines.bc_finished(settings, updates, (updates - best) // settings.eval_every)


def load_runs(*roots) -> list[Run]:
    """Every run directory (one with a progress.csv) under any of the roots (a root may
    be a run directory itself), each once, sorted by path."""
    found = {p.parent for root in roots for p in resolve(root).rglob("progress.csv")}
    return [load_run(run_dir) for run_dir in sorted(found)]


def final_row(run: Run) -> int:
    """The progress row that evaluated policy_final.npz: the last one, except for BC,
    whose final policy is the early-stopped one of `best_update` (diagnostics.csv)."""
    diagnostics = run.run_dir / "diagnostics.csv"
    if run.finished and diagnostics.exists() and "updates" in run.progress:
        with open(diagnostics) as f:
            rows = list(csv.DictReader(f))
        if rows and rows[-1].get("best_update"):
            chosen = np.flatnonzero(run.progress["updates"] == float(rows[-1]["best_update"]))
            if chosen.size:
                return int(chosen[-1])
    return -1


def output_scores(run: Run) -> np.ndarray:
    """The normalised score, at each evaluation, of the policy the run hands over: the
    averaged policy's (`average_score`, policy_average.npz) where the run keeps one, as
    offpac_il.py does by default, else the policy's own (`normalized_score`)."""
    p = run.progress
    averaged = p.get("average_score")
    if averaged is not None and not np.all(np.isnan(averaged)):
        return averaged
    return p.get("normalized_score", np.array([]))


def summarize(runs: Iterable[Run]) -> list[dict]:
    """One row per run: its labels, how far it got, and the normalised score of the
    policy it hands over (`output_scores`): final, the evaluation of the final policy
    (`final_row`), and best, the highest; policy_final_score is the last evaluation of
    the policy itself (PN), which differs from final_score where a run keeps an
    averaged policy."""
    rows = []
    for run in runs:
        p = run.progress
        scores = output_scores(run)
        has_score = scores.size and not np.all(np.isnan(scores))
        own = p.get("normalized_score", np.array([]))
        rows.append(
            {
                **{k: run.labels.get(k, "") for k in LABEL_KEYS},
                "finished": run.finished,
                "interactions": int(p["interactions"][-1]) if p else 0,
                "wall_seconds": float(p["wall_seconds"][-1]) if p else 0.0,
                "evaluations": len(scores),
                "final_score": float(scores[final_row(run)]) if has_score else np.nan,
                "best_score": float(np.nanmax(scores)) if has_score else np.nan,
                "policy_final_score": float(own[final_row(run)]) if own.size else np.nan,
                "run_dir": str(run.run_dir),
            }
        )
    return rows


def aggregate(rows: Iterable[dict], by: Sequence[str], values: Sequence[str]) -> list[dict]:
    """Seeds pooled: for each group of `by`, n and the mean, std, min, max of each value."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for row in rows:
        groups[tuple(row[k] for k in by)].append(row)
    out = []
    for key, members in sorted(groups.items(), key=lambda item: tuple(map(str, item[0]))):
        entry = {**dict(zip(by, key, strict=True)), "n": len(members)}
        for value in values:
            v = np.array([m[value] for m in members], dtype=float)
            entry |= {
                f"{value}_mean": float(v.mean()),
                f"{value}_std": float(v.std()),
                f"{value}_min": float(v.min()),
                f"{value}_max": float(v.max()),
            }
        out.append(entry)
    return out


def write_csv(rows: Sequence[dict], path) -> Path:
    """rows (dicts with the same keys) as a CSV file, written atomically; floats to 5
    significant digits (progress.csv's precision)."""
    buffer = io.StringIO()
    if rows:
        writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(
            {k: f"{v:.5g}" if isinstance(v, float) else v for k, v in row.items()} for row in rows
        )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    harness.write_text(path, buffer.getvalue())
    return path


# ----------------------------------------------------------------------------------------
# Figures.
# ----------------------------------------------------------------------------------------


def mean_and_spread(runs: list[dict[str, np.ndarray]], x: str, y: str):
    """Mean, min and max of y over runs, on the x values the runs share."""
    length = min(len(r[x]) for r in runs)
    xs = runs[0][x][:length]
    ys = np.stack([r[y][:length] for r in runs])
    return xs, ys.mean(axis=0), ys.min(axis=0), ys.max(axis=0)


def interpolated_band(runs: list[dict[str, np.ndarray]], x: str, y: str, points: int = 200):
    """Mean, min and max of y over runs, each run interpolated linearly onto a common
    grid of x from the smallest first x to the smallest last x (where every run has
    data). Runs evaluate at slightly different interactions and at different wall times,
    so the rows cannot be paired by index. None if the runs share no span of x."""
    curves = []
    for r in runs:
        keep = ~np.isnan(r[y]) & ~np.isnan(r[x])
        if keep.sum() >= 2:
            curves.append((r[x][keep], r[y][keep]))
    if not curves:
        return None
    low_x = max(cx[0] for cx, _ in curves)
    high_x = min(cx[-1] for cx, _ in curves)
    if not high_x > low_x:
        return None
    xs = np.linspace(low_x, high_x, points)
    ys = np.stack([np.interp(xs, cx, cy) for cx, cy in curves])
    return xs, ys.mean(axis=0), ys.min(axis=0), ys.max(axis=0), len(curves)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _reference_lines(ax) -> None:
    ax.axhline(1.0, color="gray", lw=0.8, ls="--")  # the expert
    ax.axhline(0.0, color="gray", lw=0.8, ls=":")  # the random policy
    ax.grid(alpha=0.3)


def _save(fig, out_png) -> Path:
    plt = _pyplot()
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out_png, dpi=110, bbox_inches="tight")  # legends may sit outside the axes
    plt.close(fig)
    return out_png


def _seeds(n: int, most: int | None = None) -> str:
    """Legend text: 3 seeds, or 1-3 seeds where a line's points have different counts."""
    if most is not None and most != n:
        return f"{n}-{most} seeds"
    return f"{n} seed{'s' * (n != 1)}"


def _select(runs: Iterable[Run], finished_only: bool = True, **labels) -> list[Run]:
    return [
        r
        for r in runs
        if (r.finished or not finished_only)
        and all(str(r.labels.get(k)) == str(v) for k, v in labels.items())
    ]


def figure2(runs: Sequence[Run], out_png, score: str = "final_score") -> Path | None:
    """Figure 2: normalised score vs number of trajectories, one column per task, sparse
    on top and dense below, one line per method (mean over seeds, band min-max).

    Writes out_png, STEM.csv (per setting over seeds) and STEM_runs.csv (per run) from
    finished runs only; None when there is none.
    """
    rows = summarize(_select(runs))
    if not rows:
        return None
    table = aggregate(
        rows, ("env", "sampling", "method", "trajectories"), ("final_score", "best_score")
    )
    out_png = Path(out_png)
    write_csv(rows, out_png.with_name(f"{out_png.stem}_runs.csv"))
    write_csv(table, out_png.with_suffix(".csv"))
    envs = sorted({r["env"] for r in table})
    samplings = [s for s in ("sparse", "dense") if any(r["sampling"] == s for r in table)]
    plt = _pyplot()
    fig, axes = plt.subplots(
        len(samplings), len(envs), figsize=(4.5 * len(envs), 3.2 * len(samplings)),
        squeeze=False, sharey=True,
    )  # fmt: skip
    for i, sampling in enumerate(samplings):
        for j, env in enumerate(envs):
            ax = axes[i][j]
            for method in [m for m in METHODS if any(r["method"] == m for r in table)]:
                setting = (env, sampling, method)
                points = sorted(
                    (r for r in table if (r["env"], r["sampling"], r["method"]) == setting),
                    key=lambda r: int(r["trajectories"]),
                )
                if not points:
                    continue
                xs = [int(r["trajectories"]) for r in points]
                seeds = [r["n"] for r in points]
                ax.plot(
                    xs, [r[f"{score}_mean"] for r in points], marker="o", color=_color(method),
                    label=f"{method} ({_seeds(min(seeds), max(seeds))})",
                )  # fmt: skip
                ax.fill_between(
                    xs, [r[f"{score}_min"] for r in points], [r[f"{score}_max"] for r in points],
                    color=_color(method), alpha=0.2,
                )  # fmt: skip
            in_panel = [r for r in table if (r["env"], r["sampling"]) == (env, sampling)]
            ax.set_xticks(sorted({int(r["trajectories"]) for r in in_panel}))
            _reference_lines(ax)
            ax.set_title(f"{env}, {sampling}")
            ax.set_xlabel("trajectories in the dataset")
            ax.set_ylabel(f"normalised score ({score.split('_')[0]})")
            ax.legend(fontsize=7)
    return _save(fig, out_png)


def _color(method: str) -> str:
    """One colour per method in every figure."""
    return f"C{list(METHODS).index(method) % 10}" if method in METHODS else "k"


def _curve_panel(ax, runs: Sequence[Run], methods: Sequence[str], x: str, csv_rows, panel: str):
    """One line per method: mean score (`output_scores`) over its finished seeds vs x, band
    min-max; a run stopped short of its budget as a dotted line of its own. A method whose
    runs do not move along x (BC: no interactions) is drawn as a level line at its mean
    final score. Wall time is shown in hours past two hours; x is logarithmic when the
    methods' budgets differ a hundredfold (GAIL's millions of interactions)."""
    in_methods = [r for r in runs if r.labels.get("method") in methods and r.progress]
    stopped = [r for r in in_methods if not r.finished]
    runs = [r for r in runs if r.finished]
    bands, levels = {}, {}
    for method in methods:
        chosen = [r for r in runs if r.labels.get("method") == method and r.progress]
        group = [{**r.progress, "output_score": output_scores(r)} for r in chosen]
        if group:
            band = interpolated_band(group, x, "output_score")
            if band is None:
                finals = [output_scores(r)[final_row(r)] for r in chosen]
                levels[method] = (np.mean(finals), len(group))
            else:
                bands[method] = band
    ends = [band[0][-1] for band in bands.values()] + [r.progress[x][-1] for r in stopped]
    scale, unit = (3600.0, "h") if x == "wall_seconds" and max(ends, default=0) > 7200 else (1, "s")
    for run in stopped:
        method, xs, scores = run.labels.get("method"), run.progress[x], output_scores(run)
        stop = f"{run.progress['interactions'][-1] / 1000:,.0f} k"
        ax.plot(
            xs / scale, scores, ls=":", color=_color(method), label=f"{method}, stopped at {stop}"
        )
        csv_rows.extend(
            dict(panel=panel, method=f"{method} (stopped)", x=float(a), mean=float(b),
                 min=float(b), max=float(b), n=1)
            for a, b in zip(xs, scores, strict=True)
        )  # fmt: skip
    for method, (xs, mean, low, high, n) in bands.items():
        ax.plot(xs / scale, mean, color=_color(method), label=f"{method} ({_seeds(n)})")
        ax.fill_between(xs / scale, low, high, color=_color(method), alpha=0.2)
        csv_rows.extend(
            dict(panel=panel, method=method, x=float(a), mean=float(b), min=float(c),
                 max=float(d), n=n)
            for a, b, c, d in zip(xs, mean, low, high, strict=True)
        )  # fmt: skip
    for method, (level, n) in levels.items():
        ax.axhline(level, ls="-.", color=_color(method), label=f"{method} ({_seeds(n)}, final)")
        csv_rows.append(
            dict(panel=panel, method=method, x=np.nan, mean=level, min=np.nan, max=np.nan, n=n)
        )
    if ends and max(ends) > 100 * min(ends):
        ax.set_xscale("log")
    _reference_lines(ax)
    ax.set_xlabel(f"wall time ({unit})" if x == "wall_seconds" else x.replace("_", " "))
    ax.set_ylabel("normalised score")
    ax.legend(fontsize=7)


def figure3(
    runs: Sequence[Run],
    out_png,
    sampling: str = "sparse",
    trajectories: int = 4,
    methods: Sequence[str] = COMPARED,
) -> Path | None:
    """Figure 3: normalised score vs wall time (top) and vs interactions (bottom), one
    column per task, at one setting (the paper: sparse). Finished runs as bands; a run
    stopped short of its budget as a dotted line of its own, labelled with where it
    stopped, so that a task whose runs could not finish still shows how far they got.
    Writes STEM.csv with the plotted lines (a stopped run's method as "M (stopped)").
    None when there is no run."""
    chosen = [
        r
        for r in _select(runs, finished_only=False, sampling=sampling, trajectories=trajectories)
        if r.labels.get("method") in methods and r.progress
    ]
    if not chosen:
        return None
    envs = sorted({r.labels["env"] for r in chosen})
    plt = _pyplot()
    fig, axes = plt.subplots(2, len(envs), figsize=(5 * len(envs), 6.4), squeeze=False)
    csv_rows: list[dict] = []
    for j, env in enumerate(envs):
        in_env = [r for r in chosen if r.labels["env"] == env]
        for i, x in enumerate(("wall_seconds", "interactions")):
            _curve_panel(axes[i][j], in_env, methods, x, csv_rows, f"{env} {x}")
            axes[i][j].set_title(f"{env}, {trajectories} {sampling} trajectories")
    write_csv(csv_rows, Path(out_png).with_suffix(".csv"))
    return _save(fig, out_png)


def figure4(
    runs: Sequence[Run],
    out_png,
    env: str | None = None,
    sampling: str = "sparse",
    trajectories: int = 4,
    methods: Sequence[str] = ("Ours", *ABLATIONS),
) -> Path | None:
    """Figure 4: normalised score vs interactions for Ours and its ablations on one task
    (default: the task of the ablation runs). Finished runs only; writes STEM.csv. None
    when no ablation run has finished (Ours alone is no ablation)."""
    chosen = [
        r
        for r in _select(runs, sampling=sampling, trajectories=trajectories)
        if r.labels.get("method") in methods and (env is None or r.labels.get("env") == env)
    ]
    ablated = [r for r in chosen if r.labels.get("method") != "Ours"]
    if not ablated:
        return None
    env = env or ablated[0].labels["env"]
    chosen = [r for r in chosen if r.labels.get("env") == env]
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4))
    csv_rows: list[dict] = []
    _curve_panel(ax, chosen, methods, "interactions", csv_rows, env)
    ax.set_title(f"Ablations: {env}, {trajectories} {sampling} trajectories")
    write_csv(csv_rows, Path(out_png).with_suffix(".csv"))
    return _save(fig, out_png)


def hold_stats(
    progress: dict[str, np.ndarray],
    reach: float = 0.9,
    floor: float = 0.8,
    since: float = 40_000,
    until: float = np.inf,
    eval_episodes: int = 5,
) -> dict:
    """Does a run reach the expert and stay there (the README's reach-and-hold target)?

    Only evaluations at or before `until` interactions count (so that runs of different
    lengths compare over one span). first_reach: interactions of the first evaluation
    with score >= reach (NaN: never); after: evaluations after that one, below_floor:
    how many of them scored < floor, lowest: the lowest of them; from `since` on:
    evaluations, how many >= reach, their mean and lowest; last: the last evaluation's
    score and interactions. falls_after / fall_episodes: evaluation episodes after the
    first reach that fell, out of how many (counting only rows that record eval_falls;
    runs started before that column existed record none), given `eval_episodes` per row.
    """
    kept = progress["interactions"] <= until
    x, score = progress["interactions"][kept], progress["normalized_score"][kept]
    reached = np.flatnonzero(score >= reach)
    stats = {"first_reach": float(x[reached[0]]) if reached.size else np.nan}
    later = score[reached[0] + 1 :] if reached.size else np.array([])
    falls = progress.get("eval_falls", np.full(len(kept), np.nan))[kept]
    later_falls = falls[reached[0] + 1 :] if reached.size else np.array([])
    recorded = ~np.isnan(later_falls)
    stats.update(
        after=len(later),
        below_floor=int((later < floor).sum()),
        lowest=float(later.min()) if later.size else np.nan,
        falls_after=int(later_falls[recorded].sum()),
        fall_episodes=int(recorded.sum()) * eval_episodes,
    )
    tail = score[x >= since]
    stats.update(
        since=since,
        since_evaluations=len(tail),
        since_reach=int((tail >= reach).sum()),
        since_mean=float(tail.mean()) if tail.size else np.nan,
        since_lowest=float(tail.min()) if tail.size else np.nan,
        last_interactions=float(x[-1]),
        last=float(score[-1]),
    )
    return stats


def hold_table(
    run_dirs,
    reach: float = 0.9,
    floor: float = 0.8,
    since: float = 40_000,
    until: float = np.inf,
    averaged: bool = False,
) -> str:
    """`hold_stats` of each run as a Markdown table (the README's Hopper and HalfCheetah
    tables); with `averaged`, of the averaged PN's evaluations (--policy-average runs)."""
    lines = [
        f"| Run | first >= {reach} | evaluations after it < {floor} | lowest after it "
        f"| episodes after it that fell "
        f"| from {since / 1000:g} k on: >= {reach} / mean / lowest | last |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for run_dir in run_dirs:
        has_config = (Path(run_dir) / "config.json").exists()
        episodes = read_config(run_dir).get("eval_episodes", 0) if has_config else 0
        progress = read_progress(run_dir)
        if averaged:
            if "average_score" not in progress:
                raise UserError(f"{run_dir}: no averaged PN's evaluations (--policy-average)")
            progress |= {
                "normalized_score": progress["average_score"],
                "eval_falls": progress["average_falls"],
            }
        need_columns(progress, run_dir, "interactions", "normalized_score")
        h = hold_stats(progress, reach, floor, since, until, episodes)
        first = "never" if np.isnan(h["first_reach"]) else f"{h['first_reach'] / 1000:.1f} k"
        fell = f"{h['falls_after']} of {h['fall_episodes']}" if h["fall_episodes"] else "-"
        lines.append(
            f"| {run_dir} | {first} | {h['below_floor']} of {h['after']} | {h['lowest']:.2f} "
            f"| {fell} "
            f"| {h['since_reach']} of {h['since_evaluations']} / {h['since_mean']:.2f} / "
            f"{h['since_lowest']:.2f} | {h['last']:.2f} ({h['last_interactions'] / 1000:g} k) |"
        )
    return "\n".join(lines)


def group_runs(run_dirs, label_by: list[str]) -> dict[str, list[Path]]:
    """Runs grouped by the values of the config keys in `label_by` (seeds pooled);
    "method" is the METHODS name of each run."""
    configs = {run_dir: run_settings(run_dir) for run_dir in map(Path, run_dirs)}
    # Only the keys whose values differ between the runs tell the groups apart.
    varying = [k for k in label_by if len({str(c.get(k)) for c in configs.values()}) > 1]
    groups: dict[str, list[Path]] = defaultdict(list)
    for run_dir, config in configs.items():
        label = ", ".join(f"{k}={config.get(k)}" for k in varying) or config["env"]
        groups[label].append(run_dir)
    return dict(groups)


def plot_curves(
    groups: dict[str, list[Path]],
    out_png,
    x: str = "interactions",
    y: str = "normalized_score",
    title: str = "",
    x_max: float | None = None,
) -> None:
    """One line per group (mean over seeds) with the min-max band over seeds, up to
    x_max when given (so that runs of different lengths compare on a common span)."""
    plt = _pyplot()
    # The legend goes below the axes, one line per group, so long labels never cover it.
    fig, ax = plt.subplots(figsize=(8, 4 + 0.22 * len(groups)))
    for label, run_dirs in groups.items():
        runs = [read_progress(d) for d in run_dirs]
        for run_dir, run in zip(run_dirs, runs, strict=True):
            if run:  # a run without evaluations yet draws nothing
                need_columns(run, run_dir, x, y)
        if x_max is not None:
            runs = [{k: v[r[x] <= x_max] for k, v in r.items()} if r else r for r in runs]
        runs = [r for r in runs if r and len(r[x])]
        if not runs:
            continue
        xs, mean, low, high = mean_and_spread(runs, x, y)
        (line,) = ax.plot(xs, mean, label=f"{label} ({len(runs)} seed{'s' * (len(runs) > 1)})")
        ax.fill_between(xs, low, high, color=line.get_color(), alpha=0.2)
    if y == "normalized_score":
        ax.axhline(1.0, color="gray", lw=0.8, ls="--")
    ax.set_xlabel(x.replace("_", " "))
    ax.set_ylabel(y.replace("_", " "))
    ax.set_title(title)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(0.0, -0.15))
    ax.grid(alpha=0.3)
    _save(fig, out_png)


# ----------------------------------------------------------------------------------------
# Command line.
# ----------------------------------------------------------------------------------------

DEFAULT_RUNS = {"quick": "runs/quick", "full": "runs/sweep", "ablations": "runs/ablations"}
DEFAULT_FIGURES = {"quick": "runs/quick/figures", "full": "figures", "ablations": "figures"}
FIGURES = {"figure2": figure2, "figure3": figure3, "figure4": figure4}


def draw_figures(runs_roots, out_dir, names=tuple(FIGURES)) -> dict[str, Path | None]:
    """The figures `names` (of FIGURES) from the runs under runs_roots (one root or
    several) into out_dir as NAME.png (None: nothing to draw)."""
    runs = load_runs(*([runs_roots] if isinstance(runs_roots, str | Path) else runs_roots))
    out_dir = resolve(out_dir)
    return {name: FIGURES[name](runs, out_dir / f"{name}.png") for name in names}


def restored(run_dir):
    """A learner run as its last checkpoint left it, with the run's own variant (an
    ablation's, for a run of lab/ablations.py), for looking into it, not for training:
    (config, spaces, expert_buffer, learner, replay, progress)."""
    import expert
    import offpac_il
    from lab import ablations

    config = learner_config({**read_config(run_dir), "run_dir": str(run_dir)})
    if not (Path(run_dir) / harness.CHECKPOINT).exists():
        raise UserError(f"{run_dir} holds no checkpoint")
    rng = np.random.default_rng(config.seed)
    env, variant = expert.make_env(config.env), ablations.variant_of(config)
    spaces, expert_buffer, learner, replay, _ = offpac_il.prepare(config, env, rng, variant)
    progress = offpac_il.load_checkpoint(run_dir, learner, replay, rng)
    return config, spaces, expert_buffer, learner, replay, progress


def fell(env, length: int) -> bool:
    """Did an episode of `length` steps end by termination, before the time limit?
    (Without a time limit nothing counts as a fall.)"""
    time_limit = env.spec.max_episode_steps if env.spec is not None else None
    return time_limit is not None and length < time_limit


class _Recording:
    """An environment that keeps the observations it returns, so that an episode run by
    `offpac_il.run_episode` can be looked at afterwards."""

    def __init__(self, env):
        self.env, self.observations = env, []

    def reset(self, **kwargs):
        observation, info = self.env.reset(**kwargs)
        self.observations = [observation]
        return observation, info

    def step(self, action):
        result = self.env.step(action)
        self.observations.append(result[0])
        return result


def probe_critic(run_dir, episodes: int = 3, steps: int = 300, seed: int = 2_000_000) -> list[dict]:
    """How the critic of a run's checkpoint sees the learner's own states.

    Runs episodes of the stochastic policy from reset seeds seed, seed + 1, ... and, at
    each of the first `steps` states s of each, compares the shipped expert's action
    a_E(s) (in [-1, 1] units) with the policy's pi(s, 0): q(s, a_E) against q(s, pi), and
    the cosine between the direction gradient (6) moves the action, d log q / da at pi,
    and a_E - pi; squared_distance is ||a_E - pi||^2. One row per episode (its return is
    the whole episode's): where the critic would lead the policy back to the expert, the
    fraction is high and the cosine positive.
    """
    import expert
    import nets
    import offpac_il

    config, spaces, _, learner, _, _ = restored(run_dir)
    env, policy_of_expert = _Recording(expert.make_env(config.env)), expert.load_expert(config.env)
    rng = np.random.default_rng(seed)
    rows = []
    for episode in range(episodes):
        total, length = offpac_il.run_episode(env, learner, spaces, rng, seed + episode)
        observations = env.observations[: min(length, steps)]  # those acted upon
        s = spaces.state(np.array(observations))  # (T, dim s)
        a_expert = np.clip(
            np.array([spaces.from_env_action(policy_of_expert.act(o)) for o in observations]),
            -1.0,
            1.0,
        ).astype(np.float32)  # (T, dim A)
        noise = np.zeros((len(s), learner.policy.noise_dim), np.float32)
        a_policy = learner.policy.act(s, noise)  # pi(s, 0): (T, dim A)
        q_expert = learner.critic.forward((s, a_expert))[0][:, 0]
        _, cache = learner.critic.forward((s, a_policy))  # logits (T, 1)
        # d(-log q)/da at pi, row by row: the critic's part of gradient (6), Eq. (10).
        (_, d_actions), _ = learner.critic.backward(
            -nets.log_sigmoid_grad(cache.logits),
            cache,
            through_head=False,
            param_grads=False,
            input_grads=(False, True),
        )
        q_policy = cache.output[:, 0]
        towards = a_expert - a_policy
        # The step of gradient (6) moves the action along -d_actions = d log q / da.
        cosine = -(d_actions * towards).sum(axis=1) / (
            np.linalg.norm(d_actions, axis=1) * np.linalg.norm(towards, axis=1) + 1e-12
        )
        rows.append(
            {
                "episode": episode,
                "steps": len(s),
                "return": round(total, 1),
                "q_at_expert_action": float(q_expert.mean()),
                "q_at_policy_action": float(q_policy.mean()),
                "expert_action_preferred": float((q_expert > q_policy).mean()),
                "squared_distance": float((towards**2).sum(axis=1).mean()),
                "gradient_cosine": float(cosine.mean()),
            }
        )
    return rows


def gradient_noise(
    run_dir, samples: Sequence[int] = (8, 128), draws: int = 30, seed: int = 0
) -> list[dict]:
    """How much of gradient (6)'s randomness comes from the noise z, at a run's checkpoint.

    For each count Z of noise samples per state, `draws` policy steps' gradients are
    computed as `offpac_il.update` would (fresh states and noise each time), and `draws`
    more on one fixed batch of states with fresh noise only. Per row: the norm of their
    mean, the total variance (summed over PN's parameters), the part of it left with the
    states fixed (the noise's part; it shrinks as 1/Z), and mean_step_fraction, the
    mean over parameters of |E g| / sqrt(E g^2): how far along the mean gradient an
    RMSProp step goes, as a fraction of the learning rate. Nothing is updated.
    """
    import offpac_il

    config, _, expert_buffer, learner, replay, _ = restored(run_dir)
    rng = np.random.default_rng(seed)

    def flat_gradient(states: np.ndarray, z: int) -> np.ndarray:
        rows = len(states) * learner.policy.samples_per_state(z)  # as offpac_il.policy_step
        noise = rng.standard_normal((rows, learner.policy.noise_dim), np.float32)
        _, grads, _ = offpac_il.policy_loss_and_grads(learner, states, noise)
        return np.concatenate([g.ravel() for g in grads.values()]).astype(np.float64)

    rows = []
    for z in samples:
        full = np.array(
            [
                flat_gradient(offpac_il.policy_states(expert_buffer, replay, config, rng), z)
                for _ in range(draws)
            ]
        )
        fixed = offpac_il.policy_states(expert_buffer, replay, config, rng)
        noise_only = np.array([flat_gradient(fixed, z) for _ in range(draws)])
        mean, total = full.mean(axis=0), full.var(axis=0, ddof=1).sum()
        noise_variance = noise_only.var(axis=0, ddof=1).sum()
        rows.append(
            {
                "noise_samples": z,
                "mean_gradient_norm": float(np.linalg.norm(mean)),
                "total_variance": float(total),
                "noise_variance": float(noise_variance),
                "noise_share": float(noise_variance / total) if total > 0 else 0.0,
                "mean_step_fraction": float(
                    np.mean(np.abs(mean) / (np.sqrt((full**2).mean(axis=0)) + 1e-30))
                ),
            }
        )
    return rows


POLICY_FILES = {
    "final": "policy_final.npz",
    "best": "policy_best.npz",
    "checkpoint": "checkpoint.npz",
    "average": "policy_average.npz",  # the averaged PN (--policy-average)
}


def policy_file(run_dir, policy: str) -> Path:
    """final, best, checkpoint (the policy in checkpoint.npz), average (the averaged PN of
    a run with --policy-average), or a number: the policy snapshot taken at the evaluation
    after that many interactions."""
    import offpac_il

    if policy in POLICY_FILES:
        return Path(run_dir) / POLICY_FILES[policy]
    if policy.isdigit():
        return offpac_il.snapshot_path(run_dir, int(policy))
    raise UserError(
        f"--policy {policy}: not final, best, checkpoint, average, snapshots or a snapshot's "
        "interactions"
    )


def existing_policy_file(run_dir, policy: str) -> Path:
    """`policy_file`, once the run's config.json and that file are known to exist."""
    read_config(run_dir)  # a run at all, before its files
    path = policy_file(run_dir, policy)
    if not path.exists():
        raise UserError(f"{path} does not exist")
    return path


def restore_arrays(path, load: Callable[[], None]) -> None:
    """Run `load()` (copying a file's arrays into networks); a missing key or a wrong
    shape means the file is from another version or another run."""
    try:
        load()
    except (KeyError, ValueError) as error:
        raise UserError(f"{path}: does not fit this run ({error})") from None


def learner_of_run(run_dir, env=None):
    """A learner run's config, env (default: a new one of its task), spaces, expert
    buffer, demonstrations and a new learner, as its training started them."""
    import expert
    import offpac_il
    from lab import ablations

    run_dir = Path(run_dir)
    saved = read_config(run_dir)
    if "method" in saved:
        raise UserError(f"{run_dir} is a {saved['method']} run, not a learner run")
    config = learner_config({**saved, "run_dir": str(run_dir)})
    env = env if env is not None else expert.make_env(config.env)
    rng = np.random.default_rng(config.seed)
    spaces, expert_buffer, learner, _, demos = offpac_il.prepare(
        config, env, rng, ablations.variant_of(config)
    )
    return config, env, spaces, expert_buffer, demos, learner


def load_policy(learner, policy: Path | dict) -> None:
    """Copy a policy file's arrays (or the arrays themselves) into learner.policy."""
    if isinstance(policy, dict):
        learner.policy.load_state(policy, "policy")
    else:
        arrays = harness.load_arrays(policy)
        restore_arrays(policy, lambda: learner.policy.load_state(arrays, "policy"))


def policy_player(run_dir, env=None):
    """play(policy, episodes, seed): rows of a learner run's saved policy (see
    evaluate_policy), on `env` (default: a new one of the run's task)."""
    import expert
    import offpac_il

    config, env, spaces, _, demos, learner = learner_of_run(run_dir, env)
    references = expert.references_or_nan(config.env, demos)

    def play(policy: Path | dict, episodes: int, seed: int) -> list[dict]:
        """policy: a policy file, or the arrays it holds."""
        load_policy(learner, policy)
        rng = np.random.default_rng(seed)
        rows = []
        for episode in range(episodes):
            total, length = offpac_il.run_episode(env, learner, spaces, rng, seed + episode)
            rows.append(
                {
                    "seed": seed + episode,
                    "return": round(total, 1),
                    "length": length,
                    "fell": fell(env, length),
                    "normalized_score": expert.normalized_score(total, references),
                }
            )
        return rows

    return play


def evaluate_policy(run_dir, policy: str = "final", episodes: int = 20, seed: int = 3_000_000):
    """A learner run's saved policy (`policy_file`) over `episodes` episodes, one row each.

    Episodes start from reset seeds seed, seed + 1, ..., which a run's own evaluations
    (10**6 + ...) never use, with the policy's noise z drawn from a Generator seeded by
    `seed`. Each row: return, length, fell (ended before the time limit) and normalised
    score. A run evaluates 5 episodes from the same starts every time; this estimates
    how often the policy falls from starts it was never scored on.
    """

    return policy_player(run_dir)(existing_policy_file(run_dir, policy), episodes, seed)


def action_error_along_expert(
    run_dir,
    policy: str = "average",
    episodes: int = 5,
    seed: int = 3_000_000,
    edges: Sequence[int] = (0, 10, 40, 100, 300, 1000),
    noise_samples: int = 16,
) -> list[dict]:
    """Where along an episode a run's saved policy (`policy_file`) is wrong.

    The shipped expert plays `episodes` episodes from reset seeds seed, seed + 1, ...;
    at each of its states s, the policy's squared action error per component, the mean
    over `noise_samples` noise vectors z of (pi(s, z) - a_E(s))^2 in [-1, 1] units, is
    pooled into the time-step bins [edges[i], edges[i+1]). A last row gives the same
    error at the demonstrated states (the run logs it as expert_action_error, with one z
    per state). An episode start the demonstrations rarely hold shows as a first bin well
    above the rest.
    """
    import expert

    if policy == "snapshots":
        raise UserError("--policy snapshots: give one policy (a snapshot's interactions)")
    path = existing_policy_file(run_dir, policy)
    config, env, spaces, expert_buffer, _, learner = learner_of_run(run_dir)
    load_policy(learner, path)
    policy_of_expert = expert.load_expert(config.env)
    rng = np.random.default_rng(seed)
    errors = [[] for _ in edges[1:]]

    samples = learner.policy.samples_per_state(noise_samples)  # 1 for a deterministic one

    def squared_error(states, actions):  # (N, dim s), (N, dim A) -> (N,)
        # each state shared by `samples` consecutive noise rows, as in the policy step
        noise = rng.standard_normal((len(states) * samples, learner.policy.noise_dim))
        chosen = learner.policy.act(states, noise.astype(states.dtype))  # (N * Z, dim A)
        wrong = (chosen.reshape(len(states), samples, -1) - actions[:, None, :]) ** 2
        return wrong.mean(axis=(1, 2))

    for episode in range(episodes):
        states, actions, _, _ = expert.expert_episode(
            env, policy_of_expert, seed + episode, edges[-1]
        )
        # the states acted upon, and the actions in [-1, 1] units (clipped at the bounds)
        error = squared_error(spaces.state(states[:-1]), spaces.from_env_action(actions))
        for i, (start, stop) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
            errors[i].extend(error[start:stop])
    rows = [
        {"steps": f"{start}-{stop}", "states": len(e), "squared_error": float(np.mean(e))}
        for start, stop, e in zip(edges[:-1], edges[1:], errors, strict=True)
        if e
    ]
    at_demos = squared_error(expert_buffer.states, expert_buffer.actions)
    rows.append(
        {"steps": "demonstrated", "states": len(at_demos), "squared_error": float(at_demos.mean())}
    )
    return rows


def evaluate_snapshots(run_dir, episodes: int = 20, seed: int = 3_000_000) -> list[dict]:
    """Every policy snapshot of a run (one per evaluation), each over the same
    `episodes` new starts as evaluate_policy: one row per snapshot with its mean and
    lowest normalised score and how many episodes fell. Set beside progress.csv, it
    tells an unlucky evaluation (five starts) from a policy that got worse."""
    import offpac_il

    read_config(run_dir)  # a run at all, before its files
    paths = sorted((Path(run_dir) / offpac_il.SNAPSHOTS).glob("*.npz"))
    if not paths:
        raise UserError(f"{run_dir} holds no policy snapshots")
    play = policy_player(run_dir)
    return [
        {"interactions": int(path.stem), **played_summary(play(path, episodes, seed))}
        for path in paths
    ]


def exponential_averages(snapshots: Sequence[tuple[int, dict]], horizon: float) -> list[dict]:
    """Polyak averages of a run's policy snapshots, one per snapshot: after snapshot k at
    t_k interactions, avg <- avg + (1 - exp(-(t_k - t_{k-1}) / horizon)) (snapshot - avg),
    from avg = the first snapshot (the initial PN, as --policy-average starts). With one
    update per interaction this is --policy-average 1/horizon seen only at the snapshots.
    Arrays that are not PN's weights (the fixed z_0) are the latest snapshot's."""
    averages, average, last = [], None, None
    for interactions, arrays in snapshots:
        if average is None:
            average = {k: v.astype(np.float64) for k, v in arrays.items()}
        else:
            rate = 1.0 - np.exp(-(interactions - last) / horizon)
            for key, value in arrays.items():
                if key == "policy/fixed_noise":
                    average[key] = value.astype(np.float64)
                else:
                    average[key] += rate * (value - average[key])
        last = interactions
        averages.append({k: v.astype(arrays[k].dtype) for k, v in average.items()})
    return averages


def averaged_snapshots(
    run_dir, horizons: Sequence[float], episodes: int = 5, seed: int = 3_000_000
) -> list[dict]:
    """What a longer or shorter --policy-average would have scored, after the fact: at
    each snapshot, the exponential average of PN's snapshots so far (`exponential_averages`)
    for each horizon, played over the same `episodes` new starts. One row per snapshot:
    each horizon's mean normalised score and falls, and PN's own."""
    import offpac_il

    read_config(run_dir)
    paths = sorted((Path(run_dir) / offpac_il.SNAPSHOTS).glob("*.npz"))
    if len(paths) < 2:
        raise UserError(f"{run_dir} holds fewer than two policy snapshots")
    snapshots = [(int(path.stem), harness.load_arrays(path)) for path in paths]
    play = policy_player(run_dir)
    rows = [{"interactions": t} for t, _ in snapshots]
    for name, horizon in [("pn", None), *((f"h{h:g}", h) for h in horizons)]:
        weights = (
            [arrays for _, arrays in snapshots]
            if horizon is None
            else exponential_averages(snapshots, horizon)
        )
        for row, arrays in zip(rows, weights, strict=True):
            summary = played_summary(play(arrays, episodes, seed))
            row[f"{name}_score"] = summary["normalized_score"]
            row[f"{name}_fell"] = summary["fell"]
    return rows


def played_summary(rows: list[dict]) -> dict:
    """Mean, std and lowest normalised score of played episodes, and how many fell."""
    scores = np.array([row["normalized_score"] for row in rows])
    return {
        "normalized_score": float(scores.mean()),
        "std": float(scores.std()),
        "lowest": float(scores.min()),
        "fell": sum(row["fell"] for row in rows),
        "episodes": len(rows),
    }


def positive_number(text: str) -> float:
    """A finite number above 0, such as a time constant ``1e4`` (NaN and inf refused)."""
    value = float(text)
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {text}")
    return value


def print_rows(rows: list[dict]) -> None:
    """A list of dicts as a ` | `-separated table on stdout."""
    print(" | ".join(rows[0]))
    for row in rows:
        print(" | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row.values()))


def main(argv=None) -> int:
    try:
        return run_command(argv)
    except UserError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except SystemExit as exit:  # --help, or a bad flag's one line (CommandLineParser)
        return exit.code


def run_command(argv) -> int:
    """main's work; a user's mistake raises UserError."""
    from harness import positive_int

    parser = harness.CommandLineParser(
        prog="python -m lab.experiments", description=__doc__.splitlines()[0]
    )
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("sweep", help="run (or resume, or skip) every run of a plan")
    run.add_argument(
        "mode",
        choices=("quick", "full", "ablations"),
        help="ablations: Figure 4's runs at 8 noise samples and 60 000 interactions,"
        " on the task of --envs (default Hopper-v4)",
    )
    run.add_argument("--runs", help="root of the run directories (default: runs/MODE...)")
    run.add_argument("--workers", type=positive_int, help="runs at a time in the local pool")
    run.add_argument("--scheduler", help="address of a Dask scheduler to run on instead")
    run.add_argument(
        "--methods",
        nargs="+",
        default=[],
        choices=list(METHODS),
        metavar="METHOD",
        help="only these methods (default: all)",
    )
    run.add_argument("--envs", nargs="+", default=[], help="only these tasks (default: all)")
    figures = sub.add_parser("figures", help="Figures 2-4 (PNG and CSV) from the runs")
    figures.add_argument(
        "mode",
        choices=("quick", "full", "ablations"),
        help="ablations: Figure 4 alone, from the runs of `sweep ablations`",
    )
    figures.add_argument(
        "--runs", nargs="+", help="roots of the run directories, or run directories"
    )
    figures.add_argument("--out", help="folder of the figures (full: figures/)")
    curves = sub.add_parser("curves", help="normalised score vs interactions, PNG")
    curves.add_argument("out")
    curves.add_argument("run_dirs", nargs="+")
    curves.add_argument("--label-by", nargs="*", default=[])
    curves.add_argument("--x", default="interactions")
    curves.add_argument("--y", default="normalized_score")
    curves.add_argument("--title", default="")
    curves.add_argument("--x-max", type=float, help="only the rows up to this x")
    hold = sub.add_parser("hold", help="reaching and holding the expert's score, a table")
    hold.add_argument("run_dirs", nargs="+")
    hold.add_argument("--reach", type=float, default=0.9, help="score that counts as reached")
    hold.add_argument("--floor", type=float, default=0.8, help="score it must stay above")
    hold.add_argument("--since", type=float, default=40_000, help="interactions of the tail")
    hold.add_argument("--until", type=float, default=np.inf, help="ignore evaluations after")
    hold.add_argument(
        "--averaged", action="store_true", help="the averaged PN's evaluations (--policy-average)"
    )
    probe = sub.add_parser("probe", help="the critic at the learner's own states, a table")
    probe.add_argument("run_dir")
    probe.add_argument("--episodes", type=positive_int, default=3)
    probe.add_argument("--steps", type=positive_int, default=300, help="steps per episode")
    probe.add_argument(
        "--seed", type=harness.seed_number, default=2_000_000, help="reset seed of the first"
    )
    evaluation = sub.add_parser(
        "evaluate", help="a run's saved policy over many episodes: returns and falls, a table"
    )
    evaluation.add_argument("run_dir")
    evaluation.add_argument(
        "--policy",
        default="final",
        help="final, best, checkpoint, average, a snapshot's interactions, or snapshots "
        "(each in turn)",
    )
    evaluation.add_argument("--episodes", type=positive_int, default=20)
    evaluation.add_argument(
        "--seed", type=harness.seed_number, default=3_000_000, help="reset seed of the first"
    )
    along = sub.add_parser(
        "along-expert",
        help="a run's saved policy's action error along the expert's own episodes, by time step",
    )
    along.add_argument("run_dir")
    along.add_argument("--policy", default="average", help="as for evaluate")
    along.add_argument("--episodes", type=positive_int, default=5)
    along.add_argument(
        "--seed", type=harness.seed_number, default=3_000_000, help="reset seed of the first"
    )
    averaging = sub.add_parser(
        "average-snapshots",
        help="what other --policy-average horizons would have scored, from the snapshots",
    )
    averaging.add_argument("run_dir")
    averaging.add_argument(
        "--horizons",
        type=positive_number,
        nargs="+",
        default=[10_000, 30_000],
        metavar="INTERACTIONS",
    )
    averaging.add_argument("--episodes", type=positive_int, default=5)
    averaging.add_argument(
        "--seed", type=harness.seed_number, default=3_000_000, help="reset seed of the first"
    )
    noise = sub.add_parser(
        "gradient-noise", help="the noise z's share of gradient (6)'s variance, a table"
    )
    noise.add_argument("run_dir")
    noise.add_argument("--samples", type=positive_int, nargs="+", default=[8, 128], metavar="Z")
    noise.add_argument("--draws", type=positive_int, default=30, help="gradients per estimate")
    noise.add_argument("--seed", type=harness.seed_number, default=0)
    args = parser.parse_args(argv)

    if args.command == "probe":
        print_rows(probe_critic(args.run_dir, args.episodes, args.steps, args.seed))
        return 0
    if args.command == "evaluate" and args.policy == "snapshots":
        print_rows(evaluate_snapshots(args.run_dir, args.episodes, args.seed))
        return 0
    if args.command == "evaluate":
        rows = evaluate_policy(args.run_dir, args.policy, args.episodes, args.seed)
        print_rows(rows)
        summary = played_summary(rows)
        print(
            f"normalised score {summary['normalized_score']:.3f} ± {summary['std']:.3f};"
            f" {summary['fell']} of {summary['episodes']} episodes fell"
        )
        return 0
    if args.command == "along-expert":
        print_rows(action_error_along_expert(args.run_dir, args.policy, args.episodes, args.seed))
        return 0
    if args.command == "average-snapshots":
        print_rows(averaged_snapshots(args.run_dir, args.horizons, args.episodes, args.seed))
        return 0
    if args.command == "gradient-noise":
        if args.draws < 2:
            raise UserError("--draws must be at least 2: a variance needs two gradients")
        print_rows(gradient_noise(args.run_dir, args.samples, args.draws, args.seed))
        return 0
    if args.command == "hold":
        if args.since < 0 or args.until < args.since:
            raise UserError(
                f"hold: --since {args.since:g} and --until {args.until:g} must satisfy"
                " 0 <= since <= until"
            )
        print(
            hold_table(args.run_dirs, args.reach, args.floor, args.since, args.until, args.averaged)
        )
        return 0

    if args.command == "curves":
        out = Path(args.out)
        if out.is_dir():
            raise UserError(f"curves: {out} is a directory; give the .png file to write")
        if out.suffix.lower() not in ("", ".png"):
            raise UserError(f"curves: {out} must be a .png file")
        groups = group_runs(args.run_dirs, args.label_by)
        plot_curves(groups, args.out, args.x, args.y, args.title, args.x_max)
        return 0
    runs_root = args.runs or DEFAULT_RUNS[args.mode]
    if args.command == "figures":
        for root in args.runs or [runs_root]:  # a typo must not draw nothing, silently
            where = f"--runs {root}" if args.runs else f"{root} (the default --runs)"
            if not resolve(root).is_dir():
                raise UserError(f"{where}: no such directory")
            if not any(resolve(root).rglob("progress.csv")):
                raise UserError(f"{where} holds no runs (no progress.csv under it)")
        names = ("figure4",) if args.mode == "ablations" else tuple(FIGURES)
        out = args.out or DEFAULT_FIGURES[args.mode]
        for name, path in draw_figures(runs_root, out, names).items():
            print(f"{name}: {path or 'skipped (no finished runs for it)'}")
        return 0
    if args.mode == "ablations":
        if len(args.envs) > 1:
            raise UserError("sweep ablations runs on one task: give --envs at most one")
        chosen = select(ablation_plan(runs_root, *args.envs), args.methods)
    else:
        full_plan = plan(args.mode == "quick", runs_root)
        chosen = select(full_plan, args.methods, args.envs)
        if not chosen:  # a typo in --envs must not run nothing, silently
            tasks = sorted({spec.labels.get("env") for spec in full_plan} - {None})
            raise UserError(
                f"--envs {' '.join(args.envs)}: the plan's tasks are {', '.join(tasks)}"
            )
    specs, skipped = split_runnable(chosen)
    for method, reason in skipped.items():
        print(f"skipping {method}: {reason}")
    if args.scheduler:
        from distributed import Client

        with Client(args.scheduler) as client:
            results = sweep(specs, client.get_executor())
    else:
        results = sweep(specs, workers=args.workers)
    print(", ".join(f"{n} {status}" for status, n in status_counts(results).items()))
    return 0 if all(r.ok for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
