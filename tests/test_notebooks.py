"""Every notebook in notebooks/ executes (they are stored without outputs)."""

from pathlib import Path

import nbclient
import nbformat
import pytest

from jaxnrsfm import datasets

NOTEBOOKS = sorted((Path(__file__).parents[1] / "notebooks").glob("*.ipynb"))
NEEDS_DATA = {"real_sequences"}


def _have_data() -> bool:
    try:
        datasets.data_dir()
    except FileNotFoundError:
        return False
    return True


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_executes(path, tmp_path):
    if path.stem in NEEDS_DATA and not _have_data():
        pytest.skip("real data absent: set $JAXNRSFM_DATA or provide ../shared/data next to the repository")
    nb = nbformat.read(path, as_version=4)
    assert all(not cell.get("outputs") for cell in nb.cells if cell.cell_type == "code"), "stored with outputs"
    nbclient.NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()
