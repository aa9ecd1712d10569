"""``streamcal report FLIGHT --cal CAL``: the residual-against-channels figure and the
held/re-estimated parameter table (issue #10)."""
from __future__ import annotations

import pytest

from streamcal.cli import main
from streamcal.inputs import autopilot_calibration, read_recording

from .conftest import REAL_FLIGHTS, real_path

LOG = REAL_FLIGHTS / "ardupilot_erle_15-12-2014_16.BIN"


@pytest.mark.slow
def test_report_against_a_calibration_file_shows_aux_figure_and_held_table(tmp_path, capsys):
    real_path(LOG)
    cal_path = tmp_path / "autopilot.json"
    autopilot_calibration(read_recording(LOG)).save(cal_path)
    out = tmp_path / "out.html"
    assert main(["report", str(LOG), "--cal", str(cal_path), "-o", str(out)]) == 0
    page = out.read_text()
    assert 'id="fig-aux_residuals"' in page
    assert 'id="held-parameters"' in page
    table = page[page.index('id="held-parameters"'):]
    table = table[:table.index("</table>")]
    for name in ("K_xx", "K_yy", "b_x", "b_z"):
        assert f"<td>{name}</td>" in table
    assert "held" in table and "re-estimated" in table
    assert "µT" in table and "Cramér–Rao" in table
    assert str(cal_path) in page          # the calibration's source is named
