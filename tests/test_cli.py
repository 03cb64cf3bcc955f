from typer.testing import CliRunner

from jaxnrsfm.cli import app


def test_demo_prints_table_and_writes_figure(tmp_path):
    out = tmp_path / "frames.png"
    result = CliRunner().invoke(app, ["demo", "--out", str(out)])
    assert result.exit_code == 0, result.output
    for text in ("registered rank 12", "augmented rank 13", "10% outliers", "20% missing", "e3D", "ok"):
        assert text in result.output
    assert out.stat().st_size > 10_000 and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
