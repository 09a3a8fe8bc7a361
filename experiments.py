"""Reading finished runs and drawing the README's figures (used by experiments.ipynb).

Every run is a directory written by `offpac_il.py` (or a baseline) with `config.json` and
`progress.csv`; nothing here trains anything.

    python experiments.py curves OUT.png RUN_DIR [RUN_DIR ...] [--label-by termination]
"""

from __future__ import annotations

import argparse
import csv
import json
from collections import defaultdict
from pathlib import Path

import numpy as np


def read_progress(run_dir) -> dict[str, np.ndarray]:
    """progress.csv as {column: float array}; empty cells become NaN."""
    with open(Path(run_dir) / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return {}
    return {
        key: np.array([float(r[key]) if r[key] not in ("", None) else np.nan for r in rows])
        for key in rows[0]
    }


def read_config(run_dir) -> dict:
    return json.loads((Path(run_dir) / "config.json").read_text())


def group_runs(run_dirs, label_by: list[str]) -> dict[str, list[Path]]:
    """Runs grouped by the values of the config keys in `label_by` (seeds pooled)."""
    groups: dict[str, list[Path]] = defaultdict(list)
    for run_dir in map(Path, run_dirs):
        config = read_config(run_dir)
        label = ", ".join(f"{k}={config.get(k)}" for k in label_by) or config["env"]
        groups[label].append(run_dir)
    return dict(groups)


def mean_and_spread(runs: list[dict[str, np.ndarray]], x: str, y: str):
    """Mean, min and max of y over runs, on the x values the runs share."""
    length = min(len(r[x]) for r in runs)
    xs = runs[0][x][:length]
    ys = np.stack([r[y][:length] for r in runs])
    return xs, ys.mean(axis=0), ys.min(axis=0), ys.max(axis=0)


def plot_curves(
    groups: dict[str, list[Path]],
    out_png,
    x: str = "interactions",
    y: str = "normalized_score",
    title: str = "",
) -> None:
    """One line per group (mean over seeds) with the min-max band over seeds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for label, run_dirs in groups.items():
        runs = [read_progress(d) for d in run_dirs]
        runs = [r for r in runs if r]
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
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    Path(out_png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    curves = sub.add_parser("curves", help="normalised score vs interactions, PNG")
    curves.add_argument("out")
    curves.add_argument("run_dirs", nargs="+")
    curves.add_argument("--label-by", nargs="*", default=[])
    curves.add_argument("--x", default="interactions")
    curves.add_argument("--y", default="normalized_score")
    curves.add_argument("--title", default="")
    args = parser.parse_args(argv)
    plot_curves(group_runs(args.run_dirs, args.label_by), args.out, args.x, args.y, args.title)


if __name__ == "__main__":
    main()
