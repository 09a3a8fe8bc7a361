"""The sweep (skip, resume, failures, needs, Dask), the figures, and experiments.ipynb in
quick mode. Real runs are tiny (a few seconds each); the whole file takes about two minutes
on 2 cores, most of it the notebook."""

import json
import os
import pickle
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from harness import UserError
from lab import experiments
from lab.experiments import ROOT, RunSpec
from lab.table import PAPER_TASKS

TINY = experiments.QUICK_ARGS["offpac_il.py"]


def tiny_spec(run_dir, *extra, seed=0) -> RunSpec:
    """A real learner run of a few seconds."""
    args = ("--env", "Hopper-v4", "--seed", seed, *TINY, *extra)
    return RunSpec("offpac_il.py", args, str(run_dir), {"method": "Ours", "seed": seed})


def script(tmp_path: Path, name: str, body: str) -> str:
    """A stand-in training script (absolute path) that parses --run-dir like the real ones."""
    path = tmp_path / name
    path.write_text(
        "import argparse, pathlib, sys\n"
        "parser = argparse.ArgumentParser()\n"
        "parser.add_argument('--run-dir', default='')\n"
        "parser.add_argument('--resume', default='')\n"
        "parser.add_argument('--init', default='')\n"
        "args = parser.parse_args()\n"
        "run_dir = pathlib.Path(args.run_dir or args.resume)\n" + textwrap.dedent(body)
    )
    return str(path)


def finishing_script(tmp_path: Path) -> str:
    return script(tmp_path, "finishes.py", "(run_dir / 'policy_final.npz').write_bytes(b'')\n")


# ----------------------------------------------------------------------------------------
# The sweep.
# ----------------------------------------------------------------------------------------


def test_sweep_runs_then_skips_finished_runs(tmp_path):
    specs = [tiny_spec(tmp_path / "a", seed=0), tiny_spec(tmp_path / "b", seed=1)]
    lines = []
    first = experiments.sweep(specs, echo=lines.append)
    assert [r.status for r in first] == ["completed", "completed"], [r.line() for r in first]
    assert [r.spec for r in first] == specs  # in the order of the specs
    assert len(lines) == 2
    progress = experiments.read_progress(tmp_path / "a")
    assert progress["interactions"][-1] >= 300
    saved = (tmp_path / "a" / "progress.csv").read_bytes()

    again = experiments.sweep(specs, echo=None)
    assert [r.status for r in again] == ["skipped", "skipped"]
    assert (tmp_path / "a" / "progress.csv").read_bytes() == saved
    # The run directory describes itself: the spec that made it and its log.
    run = experiments.load_run(tmp_path / "a")
    assert run.finished and run.labels["method"] == "Ours" and run.labels["env"] == "Hopper-v4"
    assert "--run-dir" in (tmp_path / "a" / experiments.LOG_FILE).read_text()


def test_sweep_resumes_an_interrupted_run(tmp_path):
    run_dir = tmp_path / "run"
    spec = tiny_spec(run_dir, "--total-steps", "1500", "--checkpoint-every", "0")
    process = subprocess.Popen(
        spec.command(),
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 120
        while not (run_dir / "checkpoint.npz").exists():
            assert process.poll() is None, "the run ended before its first checkpoint"
            assert time.monotonic() < deadline, "no checkpoint after 120 s"
            time.sleep(0.05)
        time.sleep(0.3)  # a few more episodes (one checkpoint after each)
    finally:
        os.killpg(process.pid, signal.SIGKILL)  # like a lost machine: no clean exit
        process.wait()
    assert not (run_dir / "policy_final.npz").exists(), "the run finished before it was killed"

    [result] = experiments.sweep([spec], echo=None)
    assert result.status == "resumed", result.line()
    assert f"--resume {run_dir}" in (run_dir / experiments.LOG_FILE).read_text()
    progress = experiments.read_progress(run_dir)
    assert progress["interactions"][0] == 0 and progress["interactions"][-1] >= 1500
    assert np.all(np.diff(progress["interactions"]) > 0)


def test_sweep_reports_failures_and_runs_the_rest(tmp_path):
    finishes = finishing_script(tmp_path)
    crashes = script(tmp_path, "crashes.py", "raise RuntimeError('boom in the learner')\n")
    quits = script(tmp_path, "quits.py", "print('nothing to do')\n")
    specs = [
        RunSpec(crashes, (), tmp_path / "crashed"),
        RunSpec(tmp_path / "no_such_script.py", (), tmp_path / "missing"),
        RunSpec(quits, (), tmp_path / "quit"),
        tiny_spec(tmp_path / "good"),  # a real run, after and between failures
        RunSpec(finishes, (), tmp_path / "after-crash", needs=[tmp_path / "crashed"]),
        RunSpec(finishes, (), tmp_path / "after-good", needs=[tmp_path / "good"]),
        RunSpec(finishes, (), tmp_path / "needs-nothing-there", needs=[tmp_path / "never-made"]),
    ]
    results = experiments.sweep(specs, workers=2, echo=None)
    status = {Path(r.spec.run_dir).name: r for r in results}
    assert status["crashed"].status == "failed" and status["crashed"].returncode == 1
    assert "boom in the learner" in status["crashed"].message
    assert status["missing"].status == "failed" and "no script" in status["missing"].message
    assert status["quit"].status == "failed" and "no policy_final.npz" in status["quit"].message
    assert status["good"].status == "completed"
    assert (
        status["after-crash"].status == "failed" and "which failed" in status["after-crash"].message
    )
    assert not (tmp_path / "after-crash").exists()  # never started
    assert status["after-good"].status == "completed"
    assert "needs the finished run" in status["needs-nothing-there"].message
    assert experiments.status_counts(results) == {"failed": 5, "completed": 2}


def test_sweep_rejects_two_specs_with_one_run_dir(tmp_path):
    spec = RunSpec("offpac_il.py", (), tmp_path / "same")
    with pytest.raises(ValueError, match="share the run directory"):
        experiments.sweep([spec, RunSpec("lab/baselines.py", ("bc",), tmp_path / "same")])


def test_sweep_on_a_dask_local_cluster(tmp_path):
    import distributed  # in the [lab] extra: missing is a failure, not a skip

    finishes = finishing_script(tmp_path)
    specs = [
        tiny_spec(tmp_path / "real"),
        RunSpec(finishes, (), tmp_path / "stand-in"),
        RunSpec(tmp_path / "absent.py", (), tmp_path / "fails"),
    ]
    # What Dask sends to its workers: the function by reference (the workers import it).
    assert len(pickle.dumps(experiments.run_one)) < 100
    assert pickle.loads(pickle.dumps(specs[0])) == specs[0]
    with (
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        results = experiments.sweep(specs, client.get_executor(), echo=None)
    assert [r.status for r in results] == ["completed", "completed", "failed"]
    assert (tmp_path / "real" / "policy_final.npz").exists()


def test_run_spec_command_line():
    spec = RunSpec("lab/baselines.py", ("bc-gail", "--seed", 3, "--bc-init", "x"), "runs/y")
    assert spec.args == ("bc-gail", "--seed", "3", "--bc-init", "x")
    assert spec.subcommand == ("bc-gail",)
    # A module of the lab package runs as `python -m lab.NAME` from the repository root.
    module = ["-m", "lab.baselines"]
    assert spec.command()[1:] == [*module, *spec.args, "--run-dir", "runs/y"]
    assert spec.command(resume=True)[1:] == [*module, "bc-gail", "--resume", "runs/y"]
    # A top-level script, or one given by its absolute path, runs as `python SCRIPT`.
    assert RunSpec("offpac_il.py", (), "r").command()[1:] == ["offpac_il.py", "--run-dir", "r"]
    assert RunSpec("/x/lab/a.py", (), "r").command()[1:] == ["/x/lab/a.py", "--run-dir", "r"]


# ----------------------------------------------------------------------------------------
# Plans and what exists yet.
# ----------------------------------------------------------------------------------------


def test_plan_covers_the_figures_once_each():
    quick = experiments.plan(True, "runs/q")
    full = experiments.plan(False, "runs/f")
    for specs in (quick, full):
        dirs = [s.run_dir for s in specs]
        assert len(dirs) == len(set(dirs))
        assert {s.labels["method"] for s in specs} == set(experiments.METHODS)
        for s in specs:
            if s.labels["method"] == "BC+GAIL":  # starts from the BC run of its setting
                [need] = s.needs
                assert need == str(experiments.run_dir_of(Path(s.run_dir).parents[3], "BC", **{
                    k: s.labels[k] for k in ("env", "sampling", "trajectories", "seed")
                }))  # fmt: skip
                assert need in s.args
    assert all("--total-steps" not in s.args for s in full)  # the scripts' own defaults
    assert {s.labels["trajectories"] for s in full} == {1, 4, 7, 10}
    assert {s.labels["seed"] for s in full} == {0, 1, 2}
    # The paper's five tasks, every one with its expert; Table 1's -v5 rows are not in it.
    assert {s.labels["env"] for s in full} == set(PAPER_TASKS)


def test_select_keeps_a_part_of_the_plan_and_what_it_starts_from():
    full = experiments.plan(False, "runs/f")
    bc = experiments.select(full, ["BC"], ["Hopper-v4"])
    assert bc and {(s.labels["method"], s.labels["env"]) for s in bc} == {("BC", "Hopper-v4")}
    both = experiments.select(full, ["BC+GAIL"], ["Hopper-v4"])
    assert {s.labels["method"] for s in both} == {"BC", "BC+GAIL"}
    assert all(n in {s.run_dir for s in both} for s in both for n in s.needs)
    assert [s.run_dir for s in both] == [s.run_dir for s in full if s in both]  # plan order
    assert experiments.select(full) == full


def test_missing_support_names_what_is_missing(tmp_path):
    cli = script(tmp_path, "cli.py", "")
    assert experiments.missing_support(RunSpec(cli, ("--init", "x"), "r")) is None
    reason = experiments.missing_support(RunSpec(cli, ("--on-policy",), "r"))
    assert reason == f"{cli} has no --on-policy yet"
    reason = experiments.missing_support(RunSpec(tmp_path / "nope.py", (), "r"))
    assert "does not exist yet" in reason
    runnable, skipped = experiments.split_runnable(
        [RunSpec(cli, (), "a", {"method": "A"}), RunSpec(cli, ("--x",), "b", {"method": "B"})]
    )
    assert [s.run_dir for s in runnable] == ["a"] and set(skipped) == {"B"}
    # A switch is listed as "[--on-policy | --no-on-policy]" and "--on-policy, --no-...".
    switch = tmp_path / "switch.py"
    switch.write_text(
        "import argparse\n"
        "parser = argparse.ArgumentParser()\n"
        "parser.add_argument('--on-policy', action=argparse.BooleanOptionalAction)\n"
        "parser.parse_args()\n"
    )
    assert experiments.missing_support(RunSpec(switch, ("--on-policy",), "r")) is None
    assert experiments.missing_support(RunSpec(switch, ("--on",), "r")) is not None


def test_every_method_is_supported_by_its_script():
    """METHODS and the scripts' flags agree: no method of Figures 2-4 would be skipped."""
    specs = [
        experiments.method_spec(
            m, "runs/x", env="Hopper-v4", seed=0, trajectories=4, sampling="sparse"
        )
        for m in experiments.METHODS
    ]
    assert experiments.split_runnable(specs)[1] == {}


# ----------------------------------------------------------------------------------------
# Figures.
# ----------------------------------------------------------------------------------------


def fake_run(root: Path, method: str, seed: int, trajectories: int, sampling: str, scale: float):
    """A finished run directory as a script would leave it (for the plots only)."""
    run_dir = experiments.run_dir_of(root, method, "Hopper-v4", sampling, trajectories, seed)
    run_dir.mkdir(parents=True)
    moves = method != "BC"  # BC never interacts: its interactions stay 0
    rows = ["interactions,wall_seconds,normalized_score"]
    for k in range(6):
        interactions = k * 1000 * (100 if method == "GAIL" else 1) if moves else 0
        score = scale * k / 5 + 0.05 * seed
        rows.append(f"{interactions},{10.0 * k + seed},{score}")
    (run_dir / "progress.csv").write_text("\n".join(rows) + "\n")
    labels = dict(method=method, env="Hopper-v4", sampling=sampling, trajectories=trajectories,
                  seed=seed)  # fmt: skip
    (run_dir / experiments.SPEC_FILE).write_text(json.dumps({"labels": labels}))
    (run_dir / "config.json").write_text(json.dumps({"env": "Hopper-v4", "seed": seed}))
    (run_dir / "policy_final.npz").write_bytes(b"")


def is_png(path) -> bool:
    return Path(path).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_legend_names_the_seed_counts_of_a_line():
    assert experiments._seeds(1) == "1 seed" and experiments._seeds(3, 3) == "3 seeds"
    assert experiments._seeds(1, 3) == "1-3 seeds"  # Figure 2: settings with fewer seeds


def test_figures_write_png_and_csv(tmp_path):
    runs_root, out = tmp_path / "runs", tmp_path / "figures"
    for seed in (0, 1):
        for method, scale in (("Ours", 0.9), ("BC", 0.3), ("GAIL", 0.8), ("Ours+OnP", 0.2)):
            for sampling in ("sparse", "dense"):
                for n in (1, 4):
                    if method != "Ours+OnP" or (sampling, n) == ("sparse", 4):
                        fake_run(runs_root, method, seed, n, sampling, scale * n / 4)
    unfinished = experiments.run_dir_of(runs_root, "Ours", "Hopper-v4", "sparse", 4, 7)
    fake_run(runs_root, "Ours", 7, 4, "sparse", 5.0)
    (unfinished / "policy_final.npz").unlink()  # stopped: a line of its own in Figure 3 only

    runs = experiments.load_runs(runs_root)
    assert len(runs) == 27
    # Several roots, one a run directory under another: each run is read once.
    assert [r.run_dir for r in experiments.load_runs(runs_root, unfinished)] == [
        r.run_dir for r in runs
    ]
    figures = experiments.draw_figures(runs_root, out)
    assert all(is_png(path) for path in figures.values())
    table = (out / "figure2.csv").read_text().splitlines()
    assert table[0].startswith("env,sampling,method,trajectories,n,final_score_mean")
    assert "Hopper-v4,sparse,Ours,4,2,0.925," in "\n".join(table)  # (0.9 + 0.95) / 2
    assert len((out / "figure2_runs.csv").read_text().splitlines()) == 1 + 26
    curves = (out / "figure3.csv").read_text()
    assert "Hopper-v4 interactions,BC,nan," in curves  # no interactions: a level line
    stopped = [line for line in curves.splitlines() if "Ours (stopped)" in line]
    assert stopped and all(line.endswith(",1") for line in stopped)
    assert {line.split(",")[0] for line in stopped} == {
        "Hopper-v4 wall_seconds",
        "Hopper-v4 interactions",
    }
    # its own scores (5 k / 5 + 0.35), not pooled with the finished seeds
    assert max(float(line.split(",")[3]) for line in stopped) == pytest.approx(5.35)
    assert "Ours+OnP" in (out / "figure4.csv").read_text()

    # Without ablation runs there is no Figure 4.
    only_ours = [r for r in runs if r.labels["method"] == "Ours"]
    assert experiments.figure4(only_ours, out / "none.png") is None
    assert not (out / "none.png").exists()

    experiments.main(["curves", str(out / "curves.png"), *map(str, (r.run_dir for r in runs[:2]))])
    assert is_png(out / "curves.png")

    # `figures ablations` draws Figure 4 alone.
    alone = tmp_path / "alone"
    experiments.main(["figures", "ablations", "--runs", str(runs_root), "--out", str(alone)])
    assert sorted(p.name for p in alone.iterdir()) == ["figure4.csv", "figure4.png"]


def test_interpolated_band_pools_runs_on_a_common_grid():
    a = {"t": np.array([0.0, 10.0]), "y": np.array([0.0, 1.0])}
    b = {"t": np.array([0.0, 4.0, 8.0]), "y": np.array([1.0, 1.0, 1.0])}
    xs, mean, low, high, n = experiments.interpolated_band([a, b], "t", "y", points=5)
    np.testing.assert_allclose(xs, [0, 2, 4, 6, 8])  # up to where both runs have data
    np.testing.assert_allclose(mean, (np.array([0, 0.2, 0.4, 0.6, 0.8]) + 1) / 2)
    np.testing.assert_allclose(low, [0, 0.2, 0.4, 0.6, 0.8])
    assert n == 2 and np.all(high == 1)
    flat = {"t": np.array([0.0, 0.0]), "y": np.array([0.2, 0.3])}
    assert experiments.interpolated_band([flat], "t", "y") is None


# ----------------------------------------------------------------------------------------
# The notebook, in quick mode, as CI runs it.
# ----------------------------------------------------------------------------------------


def execute_notebook(injected: str):
    """experiments.ipynb executed with `injected` run after its parameters cell, as
    papermill does; returns the executed notebook and the text of its outputs."""
    import nbclient
    import nbformat
    from jupyter_client.kernelspec import KernelSpecManager

    # The kernel must exist in a fresh virtual environment (ipykernel installs it).
    KernelSpecManager().get_kernel_spec("python3")
    notebook = nbformat.read(ROOT / "experiments.ipynb", as_version=4)
    [parameters] = [
        i for i, cell in enumerate(notebook.cells) if "parameters" in cell.metadata.get("tags", [])
    ]
    assert "QUICK = True" in notebook.cells[parameters].source
    assert "SWEEP = True" in notebook.cells[parameters].source
    notebook.cells.insert(parameters + 1, nbformat.v4.new_code_cell(injected))
    nbclient.NotebookClient(
        notebook, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(ROOT)}}
    ).execute()
    text = "\n".join(
        output.get("text", "")
        for cell in notebook.cells
        if cell.cell_type == "code"
        for output in cell.outputs
    )
    return notebook, text


def test_notebook_runs_in_quick_mode(tmp_path):
    readme_figures = {p: p.stat().st_mtime_ns for p in (ROOT / "figures").glob("*")}
    notebook, text = execute_notebook(
        f"QUICK = True\nRUNS = {str(tmp_path / 'runs')!r}\nFIGURES = {str(tmp_path / 'fig')!r}"
    )
    assert "quick mode" in text
    assert "'failed'" not in text  # the sweep's status counts
    assert is_png(tmp_path / "fig" / "figure2.png") and is_png(tmp_path / "fig" / "figure3.png")
    assert (tmp_path / "fig" / "figure2.csv").exists()
    # Figure 4 is drawn exactly when an ablation ran; otherwise the notebook says so.
    ablations_ran = any(
        (tmp_path / "runs" / "Hopper-v4" / experiments._slug(m)).exists()
        for m in experiments.ABLATIONS
    )
    assert (tmp_path / "fig" / "figure4.png").exists() == ablations_ran
    assert ablations_ran or "Figure 4 skipped" in text
    # Table 1 is rendered from experts/table.json.
    markdown = [
        output["data"].get("text/markdown", "")
        for cell in notebook.cells
        if cell.cell_type == "code"
        for output in cell.outputs
        if output.output_type == "display_data"
    ]
    assert any("| Hopper-v4 | 11 | 3 |" in m for m in markdown)
    # The README's figures are never touched by quick mode.
    assert {p: p.stat().st_mtime_ns for p in (ROOT / "figures").glob("*")} == readme_figures


def test_module_runs_as_a_script():
    done = subprocess.run(
        [sys.executable, "-m", "lab.experiments", "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0 and "sweep" in done.stdout and "figures" in done.stdout


def test_bc_final_score_is_the_early_stopped_policys(tmp_path):
    """BC's policy_final.npz is the policy of `best_update`, not the last evaluated one."""
    run_dir = tmp_path / "bc"
    run_dir.mkdir()
    (run_dir / "progress.csv").write_text(
        "interactions,wall_seconds,updates,normalized_score\n0,1,0,0.1\n0,2,250,0.9\n0,3,500,0.4\n"
    )
    (run_dir / "diagnostics.csv").write_text("updates,best_update\n250,250\n500,250\n")
    (run_dir / "policy_final.npz").write_bytes(b"")
    [row] = experiments.summarize([experiments.load_run(run_dir)])
    assert (row["final_score"], row["best_score"]) == (0.9, 0.9)
    (run_dir / "diagnostics.csv").unlink()  # any other method: the last evaluation
    [row] = experiments.summarize([experiments.load_run(run_dir)])
    assert row["final_score"] == 0.4


def test_a_runs_score_is_its_averaged_policys_where_it_keeps_one(tmp_path):
    """output_scores (which the figures plot) and summarize score the policy a run hands
    over: the averaged policy where progress.csv has its column filled, else PN."""
    run_dir = tmp_path / "ours"
    run_dir.mkdir()
    header = "interactions,wall_seconds,updates,normalized_score,average_score\n"
    (run_dir / "progress.csv").write_text(header + "0,1,0,0.0,0.1\n500,2,500,0.4,0.9\n")
    (run_dir / "policy_final.npz").write_bytes(b"")
    run = experiments.load_run(run_dir)
    [row] = experiments.summarize([run])
    assert (row["final_score"], row["best_score"], row["policy_final_score"]) == (0.9, 0.9, 0.4)
    np.testing.assert_array_equal(experiments.output_scores(run), [0.1, 0.9])
    (run_dir / "progress.csv").write_text(header + "0,1,0,0.0,\n500,2,500,0.4,\n")
    [row] = experiments.summarize([experiments.load_run(run_dir)])
    assert (row["final_score"], row["policy_final_score"]) == (0.4, 0.4)


def test_a_run_kept_without_its_policies_is_finished_once_it_reached_its_budget(tmp_path):
    run_dir = tmp_path / "gail"
    run_dir.mkdir()
    (run_dir / "config.json").write_text(json.dumps({"method": "gail", "total_steps": 1000}))
    header = "interactions,wall_seconds,updates,normalized_score\n"
    (run_dir / "progress.csv").write_text(header + "0,1,0,0.0\n999,2,5,0.5\n")
    assert not experiments.load_run(run_dir).finished
    (run_dir / "progress.csv").write_text(header + "0,1,0,0.0\n1003,2,5,0.5\n")
    assert experiments.load_run(run_dir).finished


def test_a_run_made_by_hand_is_named_by_its_config():
    """load_run names a run without sweep.json from config.json: every method of METHODS
    comes back as itself, and a mix of ablation switches is named by those switches."""
    for name, (script, selector) in experiments.METHODS.items():
        if script not in (experiments.BASELINES, experiments.PEERS):  # the learner's scripts
            config = experiments.selector_settings(selector)
        else:
            config = {"method": selector[0]}
        assert experiments.method_of(config) == name
    mixed = experiments.method_of({"on_policy": True, "policy_type": "gaussian"})
    assert mixed == "Ours+on_policy=True,policy_type=gaussian"


def test_curves_group_runs_by_method_and_settings_they_ran_with(tmp_path):
    """group_runs names each run's method, and fills a setting that a run's config.json
    predates with the value it ran with (GAIL's target_kl: 0 before it existed)."""
    configs = {
        "gail-old": {"method": "gail", "env": "Hopper-v4", "bc_init": ""},
        "gail-new": {"method": "gail", "env": "Hopper-v4", "bc_init": "", "target_kl": 0.01},
        "ours": {"env": "Hopper-v4"},
        "onp": {"env": "Hopper-v4", "on_policy": True},
    }
    for name, config in configs.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "config.json").write_text(json.dumps(config))
    groups = experiments.group_runs([tmp_path / name for name in configs], ["method", "target_kl"])
    assert {label: [p.name for p in paths] for label, paths in groups.items()} == {
        "method=GAIL, target_kl=0.0": ["gail-old"],
        "method=GAIL, target_kl=0.01": ["gail-new"],
        "method=Ours, target_kl=None": ["ours"],
        "method=Ours+OnP, target_kl=None": ["onp"],
    }


def test_curves_stop_at_x_max(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "progress.csv").write_text(
        "interactions,normalized_score\n0,0.0\n10,0.5\n20,0.9\n30,1.0\n"
    )
    plotted, original = [], experiments.mean_and_spread
    monkeypatch.setattr(
        experiments,
        "mean_and_spread",
        lambda runs, x, y: plotted.append(runs[0][x].tolist()) or original(runs, x, y),
    )
    experiments.plot_curves({"a": [run_dir]}, tmp_path / "all.png")
    experiments.plot_curves({"a": [run_dir]}, tmp_path / "cut.png", x_max=15)
    assert plotted == [[0, 10, 20, 30], [0, 10]]


def test_hold_stats_counts_the_dips_after_the_first_crossing():
    progress = {
        "interactions": np.array([0, 10_000, 20_000, 30_000, 40_000, 50_000, 60_000.0]),
        "normalized_score": np.array([0.0, 0.95, 0.5, 0.92, 0.85, 0.79, 1.0]),
    }
    h = experiments.hold_stats(progress, reach=0.9, floor=0.8, since=40_000)
    assert h["first_reach"] == 10_000
    assert (h["after"], h["below_floor"], h["lowest"]) == (5, 2, 0.5)
    assert (h["since_evaluations"], h["since_reach"]) == (3, 1)
    assert h["since_mean"] == pytest.approx((0.85 + 0.79 + 1.0) / 3)
    assert (h["since_lowest"], h["last"], h["last_interactions"]) == (0.79, 1.0, 60_000)
    h = experiments.hold_stats(progress, since=40_000, until=50_000)
    assert (h["after"], h["below_floor"], h["since_evaluations"]) == (4, 2, 2)
    assert (h["last"], h["last_interactions"]) == (0.79, 50_000)


def test_hold_stats_counts_falls_after_the_first_crossing_where_recorded():
    progress = {
        "interactions": np.array([0, 10_000, 20_000, 30_000, 40_000.0]),
        "normalized_score": np.array([0.0, 0.95, 0.8, 0.99, 0.7]),
        # 4 falls before the crossing do not count; the 20 k row predates the column
        "eval_falls": np.array([4, 0, np.nan, 0, 2]),
    }
    h = experiments.hold_stats(progress, eval_episodes=5)
    assert (h["falls_after"], h["fall_episodes"]) == (2, 10)
    h = experiments.hold_stats({k: v for k, v in progress.items() if k != "eval_falls"})
    assert (h["falls_after"], h["fall_episodes"]) == (0, 0)


def test_hold_stats_of_a_run_that_never_reaches():
    progress = {"interactions": np.array([0, 5_000.0]), "normalized_score": np.array([0.1, 0.3])}
    h = experiments.hold_stats(progress, since=0)
    assert np.isnan(h["first_reach"]) and h["after"] == 0 and h["below_floor"] == 0
    assert h["since_mean"] == pytest.approx(0.2)


def test_hold_command_prints_one_row_per_run(tmp_path, capsys):
    old, new = tmp_path / "old", tmp_path / "new"
    old.mkdir(), new.mkdir()
    (old / "progress.csv").write_text(
        "interactions,normalized_score\n0,0.0\n20000,0.95\n40000,0.7\n60000,0.97\n"
    )
    (new / "config.json").write_text('{"eval_episodes": 5}')
    (new / "progress.csv").write_text(
        "interactions,normalized_score,eval_falls\n0,0.0,5\n20000,0.95,0\n40000,0.7,1\n"
        "60000,0.97,0\n"
    )
    assert experiments.main(["hold", str(old), str(new), "--since", "40000"]) == 0
    rows = capsys.readouterr().out.strip().splitlines()[-2:]
    tail = "| 20.0 k | 1 of 2 | 0.70 | {} | 1 of 2 / 0.83 / 0.70 | 0.97 (60 k) |"
    assert rows == [f"| {old} {tail.format('-')}", f"| {new} {tail.format('1 of 10')}"]
    # --averaged reads the averaged PN's columns instead, and refuses a run without them.
    (new / "progress.csv").write_text(
        "interactions,normalized_score,eval_falls,average_score,average_falls\n"
        "0,0.0,5,0.0,5\n20000,0.95,0,0.5,3\n40000,0.7,1,0.92,0\n60000,0.97,0,0.98,0\n"
    )
    assert experiments.main(["hold", str(new), "--averaged"]) == 0
    row = capsys.readouterr().out.strip().splitlines()[-1]
    assert (
        row == f"| {new} | 40.0 k | 0 of 1 | 0.98 | 0 of 5 | 2 of 2 / 0.95 / 0.92 | 0.98 (60 k) |"
    )
    assert experiments.main(["hold", str(old), "--averaged"]) == 2
    assert "no averaged PN" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, says",
    [
        (["hold", "{absent}"], "no readable progress.csv"),
        (["curves", "{tmp}/c.png", "{absent}"], "config.json missing"),
        (["probe", "{absent}"], "holds no run"),
        (["gradient-noise", "{absent}"], "holds no run"),
        (["gradient-noise", "{run}"], "holds no checkpoint"),
        (["gradient-noise", "{run}", "--draws", "1"], "--draws"),
        (["probe", "{run}", "--steps", "0"], "--steps"),
        (["figures", "sideways"], "invalid choice"),
        (["figures", "quick", "--runs", "{absent}"], "no such directory"),
        (["figures", "quick", "--runs", "{tmp}/run"], "holds no runs"),
        (["sweep", "ablations", "--envs", "Hopper-v4", "Ant-v4"], "on one task"),
        (["evaluate", "{absent}"], "config.json missing"),
        (["evaluate", "{run}"], "policy_final.npz does not exist"),
        (["evaluate", "{run}", "--policy", "worst"], "--policy worst"),
        (["evaluate", "{run}", "--policy", "5000"], "0005000.npz does not exist"),
        (["evaluate", "{run}", "--policy", "snapshots"], "holds no policy snapshots"),
        (["along-expert", "{absent}"], "config.json missing"),
        (["along-expert", "{run}"], "policy_average.npz does not exist"),
        (["along-expert", "{run}", "--policy", "worst"], "--policy worst"),
        (["along-expert", "{run}", "--policy", "snapshots"], "give one policy"),
        (["average-snapshots", "{absent}"], "config.json missing"),
        (["average-snapshots", "{run}"], "fewer than two policy snapshots"),
        (["average-snapshots", "{run}", "--horizons", "0"], "--horizons"),
        (["average-snapshots", "{run}", "--horizons", "10000", "nan"], "--horizons"),
    ],
)
def test_bad_command_lines_end_in_one_line_and_status_2(tmp_path, capsys, argv, says):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    names = {"absent": tmp_path / "absent", "tmp": tmp_path, "run": run}
    with pytest.raises(SystemExit) as stop:
        sys.exit(experiments.main([a.format(**names) for a in argv]))
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1


def test_tables_and_curves_refuse_a_progress_csv_without_the_score(tmp_path, capsys):
    """An expert trainer's run (lab/sac.py's columns) given to hold or curves."""
    sac = tmp_path / "sac"
    sac.mkdir()
    (sac / "config.json").write_text('{"env": "Walker2d-v4"}')
    (sac / "progress.csv").write_text("env_steps,eval_return_mean\n5000,310.5\n10000,420.0\n")
    for argv in (["hold", str(sac)], ["curves", str(tmp_path / "c.png"), str(sac)]):
        assert experiments.main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"{sac / 'progress.csv'} has no column" in err
        assert "normalized_score" in err
    assert not (tmp_path / "c.png").exists()


def test_ablation_plan_runs_every_ablation_at_its_budget_seed_by_seed():
    specs = experiments.ablation_plan("runs/a")
    assert [s.labels["seed"] for s in specs] == [0] * 6 + [1] * 6 + [2] * 6
    assert {s.labels["method"] for s in specs} == {"Ours", *experiments.ABLATIONS}
    for s in specs:
        ours = s.labels["method"] == "Ours"
        assert s.script == (experiments.LEARNER if ours else experiments.ABLATIONS_SCRIPT)
        assert s.labels["env"] == "Hopper-v4"
        assert (s.labels["sampling"], s.labels["trajectories"]) == ("sparse", 4)
        assert s.args[-len(experiments.ABLATION_SWEEP_ARGS) :] == experiments.ABLATION_SWEEP_ARGS
    assert len({s.run_dir for s in specs}) == len(specs)
    assert {s.labels["env"] for s in experiments.ablation_plan("r", "Ant-v4")} == {"Ant-v4"}


def test_notebook_without_sweep_starts_nothing_and_draws_finished_runs(tmp_path):
    elsewhere = tmp_path / "elsewhere"
    fake_run(elsewhere, "BC", 0, 7, "dense", 0.9)
    runs = tmp_path / "runs"
    _, text = execute_notebook(
        f"QUICK = True\nSWEEP = False\nRUNS = {str(runs)!r}\n"
        f"MORE_RUNS = [{str(elsewhere)!r}]\nFIGURES = {str(tmp_path / 'fig')!r}"
    )
    assert not runs.exists()  # the plan's runs were listed, none was started
    assert "SWEEP = False: no run started" in text
    assert is_png(tmp_path / "fig" / "figure2.png")  # drawn from the finished run alone
    per_run = (tmp_path / "fig" / "figure2_runs.csv").read_text().splitlines()
    assert len(per_run) == 2 and per_run[1].startswith("BC,Hopper-v4,dense,7,0,")


def test_restore_arrays_turns_a_missing_key_or_wrong_shape_into_a_user_error(tmp_path):
    def missing():
        raise KeyError("policy/W0")

    def wrong_shape():
        np.zeros((2, 3))[...] = np.zeros((4, 3))

    for load in (missing, wrong_shape):
        with pytest.raises(UserError, match="policy.npz: does not fit this run"):
            experiments.restore_arrays(tmp_path / "policy.npz", load)


def test_a_bc_run_kept_without_its_policies_is_finished_once_it_stopped(tmp_path):
    """BC's budget counts updates and it stops early; a BC run whose policies left the
    tree is finished by its diagnostics.csv (results/sweep keeps such runs)."""
    config = {"method": "bc", "env": "Ant-v4", "total_steps": 20000, "eval_every": 250}
    progress = "interactions,normalized_score,updates\n0,0.1,0\n0,0.2,6500\n"
    for patience, last, finished in [(20, 6500, True), (21, 6500, False), (99, 20000, True)]:
        run_dir = tmp_path / f"p{patience}-{last}"
        run_dir.mkdir()
        (run_dir / "config.json").write_text(json.dumps({**config, "patience": patience}))
        (run_dir / "progress.csv").write_text(progress)
        (run_dir / "diagnostics.csv").write_text(f"updates,best_update\n{last},1500\n")
        assert experiments.load_run(run_dir).finished is finished, run_dir.name
    (run_dir / "diagnostics.csv").unlink()
    assert experiments.load_run(run_dir).finished is False
