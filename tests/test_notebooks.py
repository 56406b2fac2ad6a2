"""The notebooks run end to end in a Jupyter kernel: ``notebooks/sweep.ipynb`` at
``TTD3_NB_SIZE=tiny`` and ``notebooks/mujoco_results.ipynb`` on a small synthetic
``evals.csv``, figures to a temporary folder.  Needs the ``dev`` extra (nbclient,
nbformat, ipykernel)."""

from __future__ import annotations

import csv
import json
import os
import sys
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

REPO = Path(__file__).resolve().parent.parent
NOTEBOOKS = REPO / "notebooks"
PROBE = "import sys; print(sys.executable)"


@pytest.fixture(scope="module")
def jupyter_path(tmp_path_factory) -> str:
    """A ``python3`` kernel spec that runs this interpreter (the venv's), found first because
    JUPYTER_PATH comes before the user's and the system's Jupyter folders."""
    root = tmp_path_factory.mktemp("jupyter")
    spec = root / "kernels" / "python3"
    spec.mkdir(parents=True)
    argv = [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"]
    (spec / "kernel.json").write_text(
        json.dumps({"argv": argv, "display_name": "Python 3", "language": "python"})
    )
    return os.pathsep.join([str(root), *filter(None, [os.environ.get("JUPYTER_PATH")])])


def execute(name: str, env: dict, jupyter_path: str, monkeypatch):
    """Run notebook ``name`` in a fresh kernel with ``env`` set; fails on the first cell
    that raises (nbclient's CellExecutionError shows the cell and its traceback)."""
    for k, v in {**env, "JUPYTER_PATH": jupyter_path}.items():
        monkeypatch.setenv(k, v)
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    nb.cells.insert(0, nbformat.v4.new_code_cell(PROBE))
    client = nbclient.NotebookClient(
        nb, kernel_name="python3", timeout=600, resources={"metadata": {"path": str(NOTEBOOKS)}}
    )
    client.execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    assert not errors, errors
    probe = "".join(o.get("text", "") for o in nb.cells[0].outputs).strip()
    assert os.path.realpath(probe) == os.path.realpath(sys.executable), (probe, sys.executable)
    return nb


def test_notebooks_are_committed_without_outputs():
    for path in sorted(NOTEBOOKS.glob("*.ipynb")):
        nb = nbformat.read(path, as_version=4)
        nbformat.validate(nb)
        for cell in nb.cells:
            if cell.cell_type == "code":
                assert not cell.outputs and cell.execution_count is None, f"{path.name} has outputs"


@pytest.mark.slow  # .ci/run runs it (-m slow)
def test_sweep_notebook_tiny(tmp_path, jupyter_path, monkeypatch):
    out = tmp_path / "out"
    execute("sweep.ipynb", {"TTD3_NB_SIZE": "tiny", "TTD3_NB_OUT": str(out)}, jupyter_path, monkeypatch)
    for png in ("sweep_heatmap_sum", "sweep_heatmap_mean", "sweep_learning_curves"):
        assert (out / f"{png}.png").stat().st_size > 10_000, png
    with open(out / "sweep_results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 * 8  # delta_reduce x (2 seeds x 2 beta x 2 lambda)
    assert {r["delta_reduce"] for r in rows} == {"sum", "mean"}
    assert {(r["seed"], r["beta"], r["lam"]) for r in rows} == {
        (s, b, lam) for s in ("0", "1") for b in ("0.08", "0.25") for lam in ("0.01", "0.03")
    }


def write_evals(folder: Path) -> None:
    """A few evaluations per task, algorithm and seed, as experiments/mujoco_compare.py writes."""
    tasks = ("ant", "walker2d", "inverted_double_pendulum", "hopper")
    folder.mkdir(parents=True)
    with open(folder / "evals.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["task", "algo", "seed", "step", "eval_return"])
        for i, task in enumerate(tasks):
            for algo, gain in (("ttd3", 1.1), ("td3", 1.0)):
                for seed in range(2):
                    for step in (5000, 10000, 15000):
                        w.writerow([task, algo, seed, step, gain * (i + 1) * step / 100 + 7 * seed])


def test_mujoco_results_notebook(tmp_path, jupyter_path, monkeypatch):
    results, out = tmp_path / "mujoco", tmp_path / "out"
    write_evals(results)
    env = {"TTD3_MUJOCO_RESULTS": str(results), "TTD3_NB_OUT": str(out)}
    nb = execute("mujoco_results.ipynb", env, jupyter_path, monkeypatch)
    for png in ("mujoco_curves", "mujoco_gap"):
        assert (out / f"{png}.png").stat().st_size > 10_000, png
    shown = [
        o
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.outputs
        if "text/markdown" in o.get("data", {})
    ]
    table = "".join(o["data"]["text/markdown"] for o in shown)
    assert "| hopper | T-TD3 |" in table and "| ant | TD3 |" in table, table
