"""notebooks/*.ipynb: saved with their outputs (what a reader sees without running them), and
executed top to bottom here (small settings) with figures to show.

Refresh the saved outputs after changing a notebook or what it shows: ``make notebooks-run``
(with ``CI=1``, so the 3D views are saved as static images, not 2 MB viewers).
"""

import os
from pathlib import Path

import nbformat
import pytest

REPO = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((REPO / "notebooks").glob("*.ipynb"))


def images(nb) -> list:
    return [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if "image/png" in o.get("data", {})]


def test_notebooks_are_there():
    assert {p.name for p in NOTEBOOKS} >= {"explore_synthetic.ipynb", "explore_capture.ipynb"}


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_saved_with_their_outputs(path):
    nb = nbformat.read(path, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    counts = [c.execution_count for c in code]
    assert counts == list(range(1, len(code) + 1)), f"{path.name}: run it top to bottom and save (make notebooks-run)"
    errors = [o for c in code for o in c.outputs if o.output_type == "error"]
    assert not errors, f"{path.name}: saved with an error: {errors[0].get('ename')}"
    assert len(images(nb)) >= 6, f"{path.name}: saved without its figures"
    assert path.stat().st_size < 3_000_000, f"{path.name}: saved with interactive viewers; rerun with CI=1"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs(path, tmp_path, monkeypatch):
    from nbclient import NotebookClient

    monkeypatch.setenv("CI", "1")  # the 3D views as static images (no browser looks at them here)
    # the kernel runs in tmp_path: let it import this checkout's o3d_mvps (not another install's)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    nb = nbformat.read(path, as_version=4)
    # "python3" is the kernel of the running interpreter: jupyter_client launches it with sys.executable
    NotebookClient(nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    assert len(images(nb)) >= 6
