"""The notebooks in notebooks/ are committed without outputs (``make test`` executes them
through nbmake; this file only checks what is stored in git)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parents[2] / "notebooks"
EXPECTED = ("01-quickstart.ipynb", "02-posterior-diagnostics.ipynb", "03-reproduce-deena2010.ipynb",
            "04-bring-your-own-corpus.ipynb")


def stored_outputs(nb: dict) -> list[str]:
    """Where a notebook (parsed JSON) holds outputs: cell outputs, execution counts, or
    per-cell execution metadata; [] when it is stripped."""
    found = []
    for i, cell in enumerate(nb.get("cells", [])):
        if cell.get("cell_type") != "code":
            continue
        if cell.get("outputs"):
            found.append(f"cell {i}: {len(cell['outputs'])} output(s)")
        if cell.get("execution_count") is not None:
            found.append(f"cell {i}: execution_count {cell['execution_count']}")
        if "execution" in cell.get("metadata", {}):
            found.append(f"cell {i}: execution timing metadata")
    return found


def test_every_listed_notebook_is_there():
    assert sorted(p.name for p in NOTEBOOKS.glob("*.ipynb")) == sorted(EXPECTED)


@pytest.mark.parametrize("name", EXPECTED)
def test_notebook_is_committed_without_outputs(name):
    nb = json.loads((NOTEBOOKS / name).read_text(encoding="utf-8"))
    assert nb.get("nbformat") == 4
    assert nb["metadata"]["kernelspec"]["name"] == "python3"
    found = stored_outputs(nb)
    assert not found, (f"notebooks/{name} holds outputs ({'; '.join(found[:5])}); clear them before "
                       "committing: `.venv/bin/python notebooks/clear_outputs.py notebooks/*.ipynb`")


def test_the_check_finds_outputs_in_an_executed_cell():
    executed = {"cells": [{"cell_type": "markdown", "source": "x", "metadata": {}},
                          {"cell_type": "code", "source": "1", "metadata": {}, "execution_count": 3,
                           "outputs": [{"output_type": "execute_result", "data": {"text/plain": "1"}}]}]}
    assert stored_outputs(executed) == ["cell 1: 1 output(s)", "cell 1: execution_count 3"]


def test_clear_outputs_strips_an_executed_notebook(tmp_path):
    import subprocess
    import sys

    import nbformat
    from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook, new_output

    nb = new_notebook(cells=[new_markdown_cell("# t"), new_code_cell("print(1)", execution_count=1,
                             outputs=[new_output("stream", name="stdout", text="1\n")])])
    nb.cells[1].metadata["execution"] = {"iopub.status.busy": "2026-01-01T00:00:00Z"}
    path = tmp_path / "x.ipynb"
    nbformat.write(nb, path)
    assert len(stored_outputs(json.loads(path.read_text()))) == 3
    script = NOTEBOOKS / "clear_outputs.py"
    run = subprocess.run([sys.executable, str(script), str(path)], capture_output=True, text=True, check=True)
    assert "cleared" in run.stdout
    cleaned = json.loads(path.read_text())
    assert stored_outputs(cleaned) == [] and nbformat.read(path, as_version=4).cells[1].source == "print(1)"
