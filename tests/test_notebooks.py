"""Execute every `notebooks/*.ipynb` at small size (`LIEVI_NOTEBOOK_SMALL=1`): no cell may fail.

The notebooks contain their own assertions (conservation to round-off, fitted orders), so
a passing run also checks the numbers they show.
"""

import os
import sys
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")
pytest.importorskip("matplotlib")

NOTEBOOKS = sorted((Path(__file__).resolve().parent.parent / "notebooks").glob("*.ipynb"))
CELL_TIMEOUT = 300  # seconds per cell

# Appended to each notebook before running it: which Python the kernel runs.
_WHICH_PYTHON = "import sys; print(sys.prefix)"


# `-m extended` runs the introduction (19 s) and the heavy top (32 s); the others (each a
# minute or more of compiling) run with `-m slow`.
_EXTENDED = ("01_free_rigid_body.ipynb", "05_heavy_top.ipynb")


@pytest.mark.parametrize(
    "path",
    [
        pytest.param(p, marks=pytest.mark.extended if p.name in _EXTENDED else pytest.mark.slow)
        for p in NOTEBOOKS
    ],
    ids=[p.name for p in NOTEBOOKS],
)
def test_notebook_runs(path, monkeypatch):
    # The kernel inherits this process's environment.
    monkeypatch.setenv("LIEVI_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    # Make the "python3" kernelspec of this interpreter's prefix win over any user-wide
    # one (JUPYTER_PATH is searched first); jupyter_client then launches its
    # `python -m ipykernel_launcher` with `sys.executable`.
    monkeypatch.setenv(
        "JUPYTER_PATH",
        os.pathsep.join(
            [os.path.join(sys.prefix, "share", "jupyter")]
            + [p for p in os.environ.get("JUPYTER_PATH", "").split(os.pathsep) if p]
        ),
    )

    nb = nbformat.read(path, as_version=4)
    nb.cells.append(nbformat.v4.new_code_cell(_WHICH_PYTHON))
    client = nbclient.NotebookClient(
        nb,
        timeout=CELL_TIMEOUT,
        kernel_name="python3",
        resources={"metadata": {"path": str(path.parent)}},
    )
    client.execute()  # raises CellExecutionError, with the failing cell, on any error

    for cell in nb.cells:
        for output in cell.get("outputs", []):
            assert output.output_type != "error", f"{path.name}: {output.ename}: {output.evalue}"
    kernel_prefix = "".join(o.get("text", "") for o in nb.cells[-1].outputs).strip()
    assert os.path.realpath(kernel_prefix) == os.path.realpath(sys.prefix), (
        f"the notebook kernel ran in {kernel_prefix!r}, not in this environment ({sys.prefix!r})"
    )
