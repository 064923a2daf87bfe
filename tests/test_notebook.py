"""The notebooks run from top to bottom (the pipeline on its tiny settings, the results on the cells in docs/)."""

from __future__ import annotations

from pathlib import Path

import nbformat
from nbclient import NotebookClient

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"


def _execute(name: str, directory: Path) -> tuple[str, int]:
    """Run a notebook in ``directory``; its printed text and how many images it displayed."""
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    client = NotebookClient(notebook, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(directory)}})
    client.execute()
    outputs = [output for cell in notebook.cells if cell.cell_type == "code" for output in cell.get("outputs", [])]
    assert not [output for output in outputs if output.get("output_type") == "error"]
    images = sum("image/png" in output.get("data", {}) for output in outputs)
    return "".join(output.get("text", "") for output in outputs), images


def test_pipeline_notebook_executes(tmp_path):
    text, _ = _execute("d2a_pipeline.ipynb", tmp_path)
    assert "success" in text and "progress of the imagined cloud" in text


def test_results_notebook_reads_the_shipped_cells():
    text, images = _execute("results.ipynb", NOTEBOOKS)
    assert "paper protocol" in text and "very_hard" in text and "pairs of" in text
    assert text.count("of `d2a` and `d2a-present`") >= 2 and "(Wilson, " in text  # every pair, then Push at 2
    assert images == 3  # Table I, Table IV, the paired differences
