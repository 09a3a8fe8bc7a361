"""docs/walkthrough.ipynb executed headless, as CI runs it, and its finite-difference
checks shown to fail on a wrong gradient.

The notebook is committed with its outputs stripped, as experiments.ipynb is: executed,
it holds two PNGs and about a hundred lines of numbers (about 65 KB beside the 33 KB of
source) that change with the BLAS kernel and with every edit, which would bloat the clone
(kept under 50 MB) and bury each change's diff in output noise.
`test_committed_notebook_is_stripped` keeps it so; the executed copy lives only in memory
here, and in Jupyter for whoever opens it.

Its wall time is printed, not asserted (under a minute on 2 cores when written): a
timing belongs in a benchmark, not in a test that a busy machine would fail. The
execution timeout only stops a hung kernel.
"""

from __future__ import annotations

import time

import pytest
from helpers import ROOT

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOK = ROOT / "docs" / "walkthrough.ipynb"
TIMEOUT = 600  # seconds per cell: a hung kernel, not a timing


def execute(notebook) -> float:
    """Run `notebook` in place with the python3 kernel from docs/, where Jupyter opens it
    (the notebook puts the repository first on sys.path); returns the wall seconds."""
    from jupyter_client.kernelspec import KernelSpecManager

    KernelSpecManager().get_kernel_spec("python3")  # ipykernel installs it
    client = nbclient.NotebookClient(
        notebook,
        timeout=TIMEOUT,
        kernel_name="python3",
        resources={"metadata": {"path": str(NOTEBOOK.parent)}},
    )
    started = time.perf_counter()
    client.execute()
    return time.perf_counter() - started


def outputs(notebook, kind: str) -> list:
    """Every code cell's outputs: "text" joins the streams; else the outputs holding `kind`."""
    found = [o for cell in notebook.cells if cell.cell_type == "code" for o in cell.outputs]
    if kind == "text":
        return [o.get("text", "") for o in found]
    return [o for o in found if kind in o.get("data", {})]


def with_cell_after_imports(source: str):
    """The committed notebook with a code cell run right after its imports."""
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    [imports] = [i for i, cell in enumerate(notebook.cells) if "import offpac_il" in cell.source]
    notebook.cells.insert(imports + 1, nbformat.v4.new_code_cell(source))
    return notebook


def test_committed_notebook_is_stripped():
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(notebook)
    for cell in notebook.cells:
        if cell.cell_type == "code":
            assert cell.outputs == [] and cell.execution_count is None, cell.source[:60]


def test_walkthrough_runs_and_its_checks_pass(capsys):
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    seconds = execute(notebook)
    with capsys.disabled():
        print(f"\ndocs/walkthrough.ipynb executed in {seconds:.1f} s")
    text = "".join(outputs(notebook, "text"))
    # The kernel imported this checkout's modules, not another copy's.
    assert f"offpac_il from {ROOT / 'offpac_il.py'}" in text
    for check in (
        "dD_JS/dx on the 128 rows",
        "objective (18) in QN's 6 parameter arrays",
        "gradient (6) in PN's 6 parameter arrays",
        "the action gradient on the 512 rows",
    ):
        assert f"{check}: worst relative error" in text
    assert "arrays identical to offpac_il.update's" in text
    assert "normalized_score: first >= 0.9" in text and "average_score: first >= 0.9" in text
    assert len(outputs(notebook, "image/png")) == 2  # q at s_E; the finished run's curve


# Each planted slip must stop the notebook at the finite-difference check named, before
# any other cell notices it: the checks, not the by-hand recomputations, catch it.
WRONG_GRADIENTS = {
    "the JS gradient doubled": (
        "_right = nets.js_divergence_grad\n"
        "nets.js_divergence_grad = lambda x, t: 2.0 * _right(x, t)",
        "dD_JS/dx, Eq. (18)",
    ),
    "gradient (6) without the tanh derivative": (
        "offpac_il.BoundedPolicy.backward = lambda self, d_actions, cache: self.net.backward(\n"
        "    d_actions, cache, through_head=False, input_grads=False\n"
        ")[1]",
        "gradient (6) in PN's parameters",
    ),
}


@pytest.mark.parametrize("slip", WRONG_GRADIENTS)
def test_the_notebooks_finite_difference_checks_catch_a_wrong_gradient(slip):
    patch, check = WRONG_GRADIENTS[slip]
    notebook = with_cell_after_imports(patch)
    with pytest.raises(nbclient.exceptions.CellExecutionError) as failure:
        execute(notebook)
    assert failure.value.ename == "AssertionError"
    assert failure.value.evalue.startswith(f"{check}: relative error"), failure.value.evalue
