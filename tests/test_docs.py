"""The API reference site (mkdocs with mkdocstrings, as equinox and optimistix build theirs)
builds from the docstrings with every warning an error: a docstring, a cross-reference or
a page that mkdocstrings cannot render fails the suite."""

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_docs_build_strictly(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    page = (tmp_path / "site" / "api" / "stages" / "index.html").read_text()
    # the stages' docstrings and their fields' docstrings are on the page
    for text in ("OutlierStrategy", "The contract of the outlier stage", "Outlier threshold as a multiple"):
        assert text in page, text
    shutil.rmtree(tmp_path / "site")
