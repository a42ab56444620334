"""report.html: self-contained, every section filled."""

import re

from click.testing import CliRunner

from recon3d.cli import cli


def test_report_is_self_contained_and_filled(delft_run):
    page = (delft_run.out_dir / "report.html").read_text(encoding="utf-8")
    assert "http://" not in page and "https://" not in page  # opens offline
    for section in ("Accuracy (metres)", "Surfaces", "Buildings", "Timings", "Parameters chosen"):
        assert section in page
    assert len(re.findall(r"data:image/png;base64,", page)) == 3  # DSM, DTM, model DSM hillshades
    assert page.count("aria-label=\"error histogram\"") >= 2
    assert page.count("<polygon") == len(delft_run.city)
    assert "provider ground points" in page


def test_report_command_regenerates(delft_run, tmp_path):
    result = CliRunner().invoke(cli, ["report", str(delft_run.out_dir)])
    assert result.exit_code == 0 and "report.html" in result.output
    bad = CliRunner().invoke(cli, ["report", str(tmp_path)])
    assert bad.exit_code == 1 and "not a recon3d output folder" in bad.output
