"""Command lines of the tracking studies: an --out that is not a writable directory."""

from __future__ import annotations

import pytest

from workbench.cli import main


@pytest.mark.parametrize("study", ["tracking-demo", "tracking"])
@pytest.mark.parametrize("where", ["file", "under_file", "unwritable"])
def test_class7_out_that_is_not_a_writable_directory_names_out(tmp_path, capsys, study, where):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    out = {"file": a_file, "under_file": a_file / "sub",
           "unwritable": "/proc/wbrel-no-such/out"}[where]
    assert main(["run", study, "--profile", "quick", "--out", str(out)]) == 2
    assert "error: --out = " in capsys.readouterr().err
