"""The run harness every trainer shares (the learner, the baselines, the expert trainers).

A trainer writes its method; this module owns everything around it, once:
- one-line errors: `UserError`, and `run_cli`, which turns it (and a full disk) into one
  line on stderr and exit status 2, and Ctrl-C or `kill` into "continue with --resume";
- the command line made from a hyperparameter dataclass (`add_dataclass_flags`,
  `config_from_args`), every number checked before anything is written (`check_numbers`);
- the run directory (`open_run_dir`): config.json, progress.csv, one atomic
  checkpoint.npz with the Generator's state, exact resume, and an exclusive lock so that
  two processes never write one run;
- the progress rows, the wall clock and ETA, stopping at the next checkpoint on a signal;
- `map_row_chunks`, the thread pool that runs a big pass's row chunks on both cores.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import csv
import dataclasses
import errno
import fcntl
import functools
import inspect
import io
import json
import math
import os
import signal
import sys
import tempfile
import threading
import time
import zipfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


class UserError(Exception):
    """An error the user caused (bad flag, bad file, wrong environment): one line, exit 2."""


# === Files, written atomically: a killed run keeps the previous file, never half a new one ===


def write_atomically(path, write) -> None:
    """Call write(file) on a temporary file beside `path`, then rename it to `path`."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{path} is a directory; give a file name")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except (FileExistsError, NotADirectoryError):
        raise UserError(f"cannot write {path}: a parent of it is a file") from None
    except PermissionError:
        raise UserError(f"cannot write {path}: permission denied") from None
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # mkstemp makes files private; results are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def save_arrays(path, arrays: dict[str, np.ndarray]) -> None:
    write_atomically(path, lambda f: np.savez(f, **arrays))


def write_text(path, text: str) -> None:
    write_atomically(path, lambda f: f.write(text.encode()))


def load_arrays(path) -> dict[str, np.ndarray]:
    """Every array of an .npz; a missing, truncated or corrupted file is a UserError."""
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError("a single array, not an .npz archive")
        with data:  # every member read now: a truncated file may fail on first access
            return {key: data[key] for key in data.files}
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        raise UserError(f"{path}: not a readable .npz file ({error})") from None


# === The command line, made from a hyperparameter dataclass (docstrings are the help) ===


@functools.cache  # parsed once: CPython 3.11's ast.parse may fail beside other threads
def field_docstrings(cls) -> dict[str, str]:
    """The string literal under each dataclass field."""
    body = ast.parse(inspect.getsource(cls)).body[0].body
    return {
        annotated.target.id: doc.value.value
        for annotated, doc in zip(body, body[1:], strict=False)
        if isinstance(annotated, ast.AnnAssign)
        and isinstance(doc, ast.Expr)
        and isinstance(doc.value, ast.Constant)
        and isinstance(doc.value.value, str)
    }


def add_dataclass_flags(parser: argparse.ArgumentParser, cls) -> None:
    """One --flag per dataclass field (inherited fields too), its help the docstring."""
    docs = {}
    for klass in reversed(cls.__mro__):
        if dataclasses.is_dataclass(klass):
            docs.update(field_docstrings(klass))
    for f in dataclasses.fields(cls):
        name, default = flag(f.name), f.default
        if isinstance(default, bool):
            parser.add_argument(
                name, action=argparse.BooleanOptionalAction, default=default, help=docs[f.name]
            )
        elif isinstance(default, tuple):
            parser.add_argument(name, type=int, nargs="+", default=default, help=docs[f.name])
        else:
            kind = whole_number if type(default) is int else type(default)
            parser.add_argument(name, type=kind, default=default, help=docs[f.name])


def whole_number(text: str) -> int:
    """An int flag's value; budgets may be written as 3e5."""
    value = float(text)
    if not value.is_integer():
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text}")
    return int(value)


def config_from_args(cls, args: argparse.Namespace):
    """The dataclass `cls` with the parsed flags' values (lists become tuples)."""
    return saved_config(cls, vars(args), {})


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def check_numbers(config, ranges: dict[str, tuple[float, float, str]]) -> None:
    """Refuse non-finite numbers anywhere in `config` (each element of a tuple field), and
    numbers outside `ranges`: field -> (low, high, kind), kind "[]" (both ends allowed),
    "(]", "[)" or "()"."""
    for f in dataclasses.fields(config):
        values = getattr(config, f.name)
        for value in values if isinstance(values, tuple) else (values,):
            if isinstance(value, bool) or not isinstance(value, int | float):
                continue
            if not math.isfinite(value):
                raise UserError(f"{flag(f.name)} must be a finite number, got {value}")
            if f.name not in ranges:
                continue
            low, high, kind = ranges[f.name]
            above = value >= low if kind[0] == "[" else value > low
            below = value <= high if kind[1] == "]" else value < high
            if not (above and below):
                raise UserError(f"{flag(f.name)} must lie in {kind[0]}{low:g}, {high:g}{kind[1]}")


def check_choices(config, choices: dict[str, tuple[str, ...]]) -> None:
    for name, allowed in choices.items():
        if getattr(config, name) not in allowed:
            raise UserError(f"{flag(name)} must be one of {', '.join(allowed)}")


def check_finite(arrays: dict[str, np.ndarray], when: str) -> None:
    """Stop a run whose numbers went non-finite; its last checkpoint holds finite ones."""
    for name, values in arrays.items():
        if not np.isfinite(values).all():
            raise UserError(f"{name} became non-finite {when}; the last checkpoint is kept")


def shown(value, spec: str) -> str:
    """A measurement for a log line, or "-" where none exists yet."""
    return "-" if value is None or value == "" else format(value, spec)


class CommandLineParser(argparse.ArgumentParser):
    """argparse, but a bad flag ends in one line on stderr and exit status 2 (no usage dump)."""

    def error(self, message: str):
        print(f"error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def config_from_command_line(argv, config_class, description, paper: dict, may_change, prog=None):
    """(config, resume) from a trainer's command line: one flag per `config_class` field,
    `--paper` (the `paper` values become the defaults; flags given still win) and
    `--resume RUN_DIR` (the saved settings, with only the flags in `may_change` given
    anew; any other flag given must agree with the saved run). prog: the command as typed
    (`python -m lab.peers sqil`), for the usage line and errors; default: the script."""
    parser = CommandLineParser(
        prog=prog, description=description, formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    add_dataclass_flags(parser, config_class)
    if paper:
        settings = ", ".join(f"{flag(k)} {v:g}" for k, v in paper.items())
        explained = f"the paper's values where the defaults deviate ({settings}); flags given win"
        parser.add_argument("--paper", action="store_true", help=explained)
    explained = "continue the run in RUN_DIR from its last checkpoint with its saved settings;"
    explained += f" only {', '.join(map(flag, may_change)) or 'no flag'} may be given anew"
    parser.add_argument("--resume", metavar="RUN_DIR", help=explained)
    args = parser.parse_args(argv)
    if getattr(args, "paper", False):
        parser.set_defaults(**paper)
        args = parser.parse_args(argv)
    if args.resume is None:
        return config_from_args(config_class, args), False
    if not args.resume:  # `--resume ""`, e.g. an unset shell variable: not a fresh run
        raise UserError("--resume needs a run directory")
    for action in parser._actions:  # parse again, keeping only the flags given
        action.default = argparse.SUPPRESS
    given = vars(parser.parse_args(argv))
    given.pop("resume")
    if given.pop("paper", False):
        raise UserError("--paper cannot be combined with --resume (the saved settings hold)")
    saved = read_config(args.resume)
    check_program(args.resume, saved, getattr(config_class, "program", None))
    check_removed_settings(args.resume, saved, getattr(config_class, "removed_settings", {}))
    saved = {**saved, "run_dir": args.resume}
    settings = resumed_settings(saved, given, may_change)
    try:
        return saved_config(config_class, settings, paper), True
    except UserError as error:
        raise UserError(f"{Path(args.resume) / str(error)}") from None


# config.json's key naming the command that made the run (its config class's `program`)
PROGRAM = "program"
BASELINES = ("bc", "gail", "bc-gail")  # lab/baselines.py's subcommands, for older runs


def program_of(saved: dict) -> str | None:
    """The command that made a run, from its config.json: its "program"; for a run made
    before that key was written, what the keys its program wrote say (None: unknown)."""
    if PROGRAM in saved:
        return str(saved[PROGRAM])
    method = saved.get("method")
    if method is not None:
        return f"python -m lab.{'baselines' if method in BASELINES else 'peers'} {method}"
    ablation_switches = {"on_policy": False, "reward_learning": "none", "policy_type": "bounded"}
    if any(saved.get(name, off) != off for name, off in ablation_switches.items()):
        return "python -m lab.ablations"
    if {"steps", "out"} <= saved.keys():  # lab/sac.py's budget and expert file
        return "python -m lab.sac"
    return "python offpac_il.py" if "termination" in saved else None


def check_program(run_dir, saved: dict, program: str | None) -> None:
    """Refuse to resume a run made by another command: that command's settings and
    networks would be dropped, and its config.json rewritten without them."""
    made_by = program_of(saved)
    if program is not None and made_by is not None and made_by != program:
        raise UserError(
            f"{run_dir} is a run of `{made_by}`, not of `{program}`;"
            f" resume it with `{made_by} --resume {run_dir}`"
        )


def check_removed_settings(run_dir, saved: dict, removed: dict) -> None:
    """Refuse to resume a run that used a setting the code no longer has: dropping it would
    silently change the run. `removed`: name -> (its "off" value, the last commit with it)."""
    for name, (off, commit) in removed.items():
        if name in saved and saved[name] != off:
            where = f"; resume it with the code of commit {commit}" if commit else ""
            raise UserError(
                f"{run_dir} was made with {flag(name)} {saved[name]}, a setting this code"
                f" no longer has{where}"
            )


def saved_config(config_class, saved: dict, paper: dict):
    """The config of a run's config.json. A setting the file lacks did not exist when
    the run was made, so the run had the behaviour of before it existed: the class's
    `settings_before_they_existed` where that differs from today's default, else the
    paper's (`paper`). Settings the code no longer has are dropped (a resume refuses a
    run that had one on: check_removed_settings)."""
    fields = {f.name: f for f in dataclasses.fields(config_class)}
    values = {**paper, **getattr(config_class, "settings_before_they_existed", {}), **saved}
    return config_class(
        **{name: saved_value(f, values[name]) for name, f in fields.items() if name in values}
    )


def saved_value(f: dataclasses.Field, value):
    """A config.json value as the command line would give it for field `f` (its default's
    type), so that a hand-edited file is refused in one line instead of crashing later."""
    default = f.default
    if default is None or default is dataclasses.MISSING:
        return value
    if isinstance(default, bool):
        ok = isinstance(value, bool)
    elif isinstance(default, tuple):
        ok = isinstance(value, list | tuple) and all(whole(v) for v in value)
        value = tuple(int(v) for v in value) if ok else value
    elif type(default) is int:
        ok = whole(value)
        value = int(value) if ok else value
    elif isinstance(default, float):
        ok = isinstance(value, int | float) and not isinstance(value, bool)
    else:
        ok = isinstance(value, type(default))
    if not ok:
        kind = {bool: "true or false", int: "a whole number", float: "a number", str: "a string"}
        wanted = "a list of whole numbers" if isinstance(default, tuple) else kind[type(default)]
        raise UserError(f"{CONFIG}: {f.name} must be {wanted}, got {json.dumps(value)}")
    return value


def whole(value) -> bool:
    return (
        isinstance(value, int | float) and not isinstance(value, bool) and float(value).is_integer()
    )


# === The run directory: config.json, progress.csv and checkpoint.npz, under a lock ===

CONFIG, PROGRESS, CHECKPOINT, LOCK = "config.json", "progress.csv", "checkpoint.npz", ".lock"
_held_locks: dict[Path, int] = {}
# The checkpoint files this process's runs write: run_cli's last line says whether there
# is anything to resume.
_checkpoint_files: set[Path] = set()


def will_checkpoint(path) -> None:
    """Record that this process's run keeps its checkpoint at `path` (open_run_dir does)."""
    _checkpoint_files.add(Path(path).resolve())


def _lock(run_dir: Path) -> None:
    """An exclusive lock on run_dir for the rest of this process's life (flock: the kernel
    drops it when the process dies, so a killed run never blocks its own resume)."""
    key = run_dir.resolve()
    if key in _held_locks:
        return
    try:
        fd = os.open(run_dir / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as error:
        raise UserError(f"cannot use run directory {run_dir}: {error.strerror}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise UserError(f"{run_dir} is in use by another running process") from None
    _held_locks[key] = fd


def open_run_dir(run_dir, resume: bool) -> Path:
    """Check, create and lock a run directory: a fresh run refuses one with a checkpoint, a
    resume needs all three files. The lock comes first, so a second process (started at the
    same instant, or a --resume of a live run) stops here with one line, before any write."""
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise UserError(f"--run-dir {run_dir} is a file, not a directory")
    if resume and not run_dir.is_dir():
        raise UserError(f"{run_dir} holds no run")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise UserError(f"--run-dir {run_dir} lies under a file") from None
    except PermissionError:
        raise UserError(f"--run-dir {run_dir}: permission denied") from None
    if not os.access(run_dir, os.W_OK):
        raise UserError(f"--run-dir {run_dir} is not writable")
    _lock(run_dir)
    will_checkpoint(run_dir / CHECKPOINT)
    if resume:
        if not (run_dir / CHECKPOINT).is_file():
            raise UserError(
                f"{run_dir} cannot be resumed: its {CHECKPOINT} is missing (a run stopped"
                " before its first checkpoint starts afresh with the same flags)"
            )
        for name in (CONFIG, PROGRESS):
            if not (run_dir / name).is_file():
                raise UserError(f"{run_dir} cannot be resumed: its {name} is missing")
    elif (run_dir / CHECKPOINT).exists():
        raise UserError(
            f"{run_dir} already holds a run; continue it with --resume {run_dir}"
            " or choose another --run-dir"
        )
    return run_dir


# The config.json text of each run directory this process wrote or read: save_checkpoint
# writes it again should the file have gone (deleted by hand mid-run), so that the run
# stays resumable.
_configs: dict[Path, str] = {}


def write_config(run_dir, settings: dict) -> None:
    text = json.dumps(settings, indent=2) + "\n"
    write_text(Path(run_dir) / CONFIG, text)
    _configs[Path(run_dir).resolve()] = text


def read_config(run_dir) -> dict:
    """A run's settings; a missing, unreadable or hand-broken config.json is a UserError
    that says which (the values themselves are checked by saved_config)."""
    path = Path(run_dir) / CONFIG
    try:
        text = path.read_text()
        settings = json.loads(text)
    except FileNotFoundError:
        if (Path(run_dir) / CHECKPOINT).is_file():
            raise UserError(f"{run_dir} cannot be resumed: its {CONFIG} is missing") from None
        raise UserError(f"{run_dir} holds no run ({CONFIG} missing)") from None
    except (OSError, ValueError) as error:
        raise UserError(f"{path} is unreadable ({error})") from None
    if not isinstance(settings, dict):
        raise UserError(f"{path} does not hold settings (a JSON object)")
    _configs.setdefault(Path(run_dir).resolve(), text)
    return settings


def resumed_settings(saved: dict, given: dict, may_change: tuple[str, ...]) -> dict:
    """A resumed run's settings: the saved ones, with the given flags that a resume may
    change (`may_change`, such as the budget). Any other flag given with a value other than
    the saved one is refused: ignoring it would run something the user did not ask for."""
    for name, value in given.items():
        value = list(value) if isinstance(value, tuple) else value
        if name in may_change or saved.get(name) == value:
            continue
        allowed = ", ".join(flag(n) for n in may_change) or "none"
        raise UserError(
            f"{flag(name)} conflicts with the saved run ({saved.get(name)!r});"
            f" a resume may change only: {allowed}"
        )
    return {**saved, **{k: v for k, v in given.items() if k in may_change}}


def save_checkpoint(run_dir, arrays: dict[str, np.ndarray], rng, progress, fields) -> None:
    """progress.csv (`fields` first), then checkpoint.npz (the arrays, the Generator's
    state, the counters and rows of the `progress` dataclass), each written atomically.
    The checkpoint holds everything: a kill between the two writes leaves a progress.csv
    a row ahead, which the resumed run rewrites from the checkpoint's rows."""
    write_text(Path(run_dir) / PROGRESS, progress_csv(progress.rows, fields))
    config_text = _configs.get(Path(run_dir).resolve())
    if config_text is not None and not (Path(run_dir) / CONFIG).exists():
        write_text(Path(run_dir) / CONFIG, config_text)
    counters = {k: v for k, v in dataclasses.asdict(progress).items() if k != "rows"}
    records = {"rng": rng.bit_generator.state, "counters": counters, "rows": progress.rows}
    records = {name: np.array(json.dumps(value)) for name, value in records.items()}
    save_arrays(Path(run_dir) / CHECKPOINT, arrays | records)


def load_checkpoint(run_dir, rng, load: Callable[[dict], None], progress_class=None):
    """Restore `rng` in place, call load(arrays) to fill the networks and buffers, and
    return the progress (`progress_class`, by default Progress) with the checkpoint's rows,
    which a resumed run's progress.csv is rewritten from. A bad file is a UserError."""
    path = Path(run_dir) / CHECKPOINT
    arrays = load_arrays(path)
    try:
        state = json.loads(str(arrays.pop("rng")))
        counters = json.loads(str(arrays.pop("counters")))
        rows = json.loads(str(arrays.pop("rows")))
        load(arrays)
        rng.bit_generator.state = state
        return (progress_class or Progress)(**counters, rows=rows)
    except (KeyError, ValueError, TypeError) as error:
        raise UserError(f"{path}: not a checkpoint of this run or version ({error})") from None


def rounded(value):
    """Counts as they are, measurements to 5 significant digits."""
    return value if isinstance(value, int | str) else float(f"{value:.5g}")


def progress_csv(rows: list[dict], fields) -> str:
    """`fields`, then any other column the rows hold, in their order."""
    fields = list(fields)
    fields += [name for name in (rows[0] if rows else {}) if name not in fields]
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


@dataclass
class Progress:
    """A run's counters and progress rows, restored exactly by its checkpoint."""

    interactions: int = 0
    updates: int = 0
    episodes: int = 0
    eval_rounds: int = 0
    wall_seconds: float = 0.0
    best_eval_return: float = -math.inf
    recent_returns: list[float] = field(default_factory=list)  # since the last evaluation
    last_stats: dict[str, float] = field(default_factory=dict)  # of the latest update
    rows: list[dict] = field(default_factory=list)

    def evaluation_due(self, every: int, total: int, counter: str = "interactions") -> bool:
        """At 0, at the first episode end past each `every`, and at the end, once: a
        finished run that is resumed adds no second final row."""
        count = getattr(self, counter)
        if self.rows and self.rows[-1][counter] == count:
            return False
        return count >= self.eval_rounds * every or count >= total

    def record(self, returns: np.ndarray, score: float, measured: dict, fields) -> dict:
        """Append an evaluation's row: the counters, the evaluation's statistics, the mean
        training return since the last row and `measured`'s values of `fields` ("": none)."""
        self.eval_rounds += 1
        recent = self.recent_returns
        row = {
            "interactions": self.interactions,
            "wall_seconds": round(self.wall_seconds, 1),
            "updates": self.updates,
            "episodes": self.episodes,
            "eval_return_mean": round(float(returns.mean()), 2),
            "eval_return_std": round(float(returns.std()), 2),
            "normalized_score": round(score, 4),
            "train_return": round(float(np.mean(recent)), 2) if recent else "",
        }
        row |= {k: rounded(measured[k]) if k in measured else "" for k in fields if k not in row}
        self.rows.append(row)
        recent.clear()
        return row


class Clock:
    """A run's wall time (carried over a resume), when to log and when to checkpoint, and
    the pace since this process started: a resumed run's earlier sessions may have run
    on a faster or slower machine, so their pace is not used for the ETA."""

    def __init__(self, progress: Progress, checkpoint_every: float, log_every: float):
        self.progress, self.checkpoint_every, self.log_every = progress, checkpoint_every, log_every
        self.start = self.last_log = self.last_checkpoint = time.perf_counter()
        self.start_interactions = progress.interactions
        self.started = self.start - progress.wall_seconds

    def tick(self) -> None:
        self.progress.wall_seconds = time.perf_counter() - self.started

    def log_due(self) -> bool:
        due = time.perf_counter() - self.last_log >= self.log_every
        if due:
            self.last_log = time.perf_counter()
        return due

    def checkpoint_due(self) -> bool:
        """A periodic checkpoint is due, or a signal asked the run to stop (then the loop
        checkpoints and calls stop_if_requested)."""
        return time.perf_counter() - self.last_checkpoint >= self.checkpoint_every or _stop.is_set()

    def checkpointed(self) -> None:
        self.last_checkpoint = time.perf_counter()

    def eta_minutes(self, total: int) -> float:
        """Minutes left until `total` interactions; never negative (the last episode may
        run past the budget), NaN before this process has done any."""
        done = self.progress.interactions - self.start_interactions
        if done <= 0:
            return float("nan")
        left = max(total - self.progress.interactions, 0)
        return left * (time.perf_counter() - self.start) / done / 60


# === Stopping a run at its next checkpoint ===

_stop = threading.Event()
_interrupted = threading.Event()  # a signal stopped the run at once (read after the `with`)


@contextlib.contextmanager
def stop_at_next_checkpoint(at_once: bool = False):
    """While active, SIGINT (Ctrl-C) and SIGTERM (`kill`) ask the training loop to stop at
    its next checkpoint point: the loop sees `Clock.checkpoint_due`, writes its checkpoint and
    raises KeyboardInterrupt (`stop_if_requested`), so nothing since the last periodic
    checkpoint is lost. A second signal stops at once, as does the first one with `at_once`
    (a command without checkpoints). A signal the process was started to ignore stays
    ignored (a shell's `cmd &` ignores SIGINT); outside the main thread nothing is installed."""
    _stop.clear()
    _interrupted.clear()
    installed = {}

    def request(signum, frame):
        if _stop.is_set() or at_once:
            _interrupted.set()
            raise KeyboardInterrupt
        _stop.set()
        print("stopping at the next checkpoint (signal again to stop at once)", file=sys.stderr)

    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):
            if signal.getsignal(signum) is not signal.SIG_IGN:
                installed[signum] = signal.signal(signum, request)
    try:
        yield
    finally:
        for signum, handler in installed.items():
            signal.signal(signum, handler)
        _stop.clear()


class StopRequested(KeyboardInterrupt):
    """A first signal honoured at a point where stopping loses nothing: after a
    checkpoint, or between the episodes of an evaluation or the trajectories of
    demonstrations being made (redone in full by the next start)."""


class StoppedBeforeStart(StopRequested):
    """A first signal honoured before the run wrote anything (making its demonstrations)."""


def stop_if_requested(started: bool = True) -> None:
    """End the run (StopRequested) if a signal asked for it: after a checkpoint, and
    between the steps of long passes that a resume redoes exactly (a signal would
    otherwise wait for the whole pass, minutes for a long evaluation); `started` False:
    before the run has written anything."""
    if _stop.is_set():
        raise StopRequested if started else StoppedBeforeStart


def interrupted_line(interrupt: KeyboardInterrupt, at_once: bool) -> str:
    """The last line of a stopped run: "continue with --resume" only where a resume can
    continue it: every checkpoint this process's runs keep (will_checkpoint) exists."""
    if at_once:
        return "interrupted"
    if isinstance(interrupt, StoppedBeforeStart) or not _checkpoint_files:
        return "interrupted before the run started, nothing written; run the same command again"
    unresumable = sorted(path for path in _checkpoint_files if not path.is_file())
    if unresumable:
        return (
            f"interrupted before the first checkpoint ({unresumable[0]}): nothing to resume;"
            " run the same command again to start afresh"
        )
    return "interrupted; continue with --resume"


def run_cli(body: Callable[[], object], at_once: bool = False) -> int:
    """A trainer's main: body() with BLAS on one thread (the threads come from
    map_row_chunks) and signals stopping at the next checkpoint (`at_once`: at once); errors
    a user can cause become one line on stderr and exit status 2."""
    from threadpoolctl import threadpool_limits

    reuse_freed_memory()
    try:
        with threadpool_limits(limits=1, user_api="blas"), stop_at_next_checkpoint(at_once):
            body()
    except UserError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as interrupt:
        print(interrupted_line(interrupt, at_once), file=sys.stderr)
        return 130
    except Exception as error:
        if _interrupted.is_set():
            # The stop-at-once interrupt was raised inside a C extension's call, which
            # reports it as an error of its own: ctypes.ArgumentError from MuJoCo's first
            # import of its GL bindings, ImportError from a module being imported.
            print(interrupted_line(KeyboardInterrupt(), at_once), file=sys.stderr)
            return 130
        if not isinstance(error, OSError) or error.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        where = f" writing {error.filename}" if error.filename else ""
        message = f"disk full{where}; the last checkpoint is kept, free space and --resume"
        print(f"error: {message}", file=sys.stderr)
        return 2
    return 0


# === The big passes: row chunks on both cores, and malloc that reuses memory ===

_POOL: ThreadPoolExecutor | None = None
# Rows per chunk of the big passes. For the policy step's 8 192 rows on 2 cores: 167,
# 140, 109 and 98 ms at 128, 256, 512 and 1024 rows per chunk, 158 ms unchunked with
# BLAS on both cores (small chunks stay in cache, large ones pay less Python overhead).
CHUNK_ROWS = 1024


def map_row_chunks(fn, n_states: int, rows_per_state: int) -> list:
    """[fn(chunk) for chunk in slices of states], on a thread pool with one thread per
    core; each chunk's rows (states x rows_per_state) fill about CHUNK_ROWS, and there is
    at least one chunk per core. NumPy releases the GIL inside matrix products and large
    ufuncs, so threads run chunks in parallel; `run_cli` limits BLAS to one thread."""
    global _POOL
    cores = os.cpu_count() or 1
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=cores)
    per_chunk = max(1, min(CHUNK_ROWS // rows_per_state, -(-n_states // cores)))
    chunks = [slice(lo, min(n_states, lo + per_chunk)) for lo in range(0, n_states, per_chunk)]
    return list(_POOL.map(fn, chunks))


def reuse_freed_memory() -> None:
    """Ask glibc's malloc to keep freed memory for reuse instead of returning it.

    By default, arrays above 128 KB-32 MB are mapped fresh from the kernel and unmapped
    when freed, so every (1024, 500) float32 temporary of the policy step starts with
    500 page faults: about 12 000 per update, 10-20 % of its time on 2 cores. With these
    settings the same memory is reused. Linux/glibc only; elsewhere this does nothing.
    """
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    if not name:
        return
    try:
        libc = ctypes.CDLL(name)
        m_trim_threshold, m_mmap_threshold = -1, -3
        libc.mallopt(m_mmap_threshold, 512 * 2**20)  # allocations below 512 MB: heap
        libc.mallopt(m_trim_threshold, 1024 * 2**20)  # keep up to 1 GB of freed heap
    except (OSError, AttributeError):
        pass


# === One main for every command, and count flags ===


def cli_main(argv, parse: Callable, run: Callable, checkpoints: bool = True) -> int:
    """A command's main: run(parse(argv), argv) under run_cli; parse's SystemExit (--help:
    0, a bad flag: 2) becomes the status. A command without checkpoints (checkpoints=False:
    expert.py's, lab.table) stops at once on Ctrl-C or `kill`, saying "interrupted" (130):
    it writes its one file atomically at its end, so there is nothing to resume."""
    argv = sys.argv[1:] if argv is None else argv
    try:
        return run_cli(lambda: run(parse(argv), argv), at_once=not checkpoints)
    except SystemExit as exit:
        return exit.code


# numpy's Generator takes seeds of any size, but files store them as int64 (expert.py's
# demonstrations): a larger seed would be written as an object array no one can read.
MAX_SEED = 2**63 - 1


def seed_number(text: str) -> int:
    """A --seed flag's value: a whole number in [0, 2**63 - 1]."""
    value = whole_number(text)
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must lie in [0, 2**63 - 1], got {text}")
    return value


def memory_bytes() -> int:
    """This machine's physical memory."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_fits_in_memory(arrays: dict[str, float]) -> None:
    """Refuse settings whose largest arrays (estimated bytes, named by the flags that size
    them) cannot fit in memory, before anything is allocated or written."""
    name, size = max(arrays.items(), key=lambda item: item[1])
    total = sum(arrays.values())
    if total > memory_bytes():
        raise UserError(
            f"these settings need about {total / 2**30:.3g} GiB of memory ({size / 2**30:.3g}"
            f" GiB for {name}); this machine has {memory_bytes() / 2**30:.3g} GiB"
        )


def positive_int(text: str) -> int:
    """A count flag's value: a whole number of at least 1, such as 8 or 7e6."""
    value = whole_number(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value
