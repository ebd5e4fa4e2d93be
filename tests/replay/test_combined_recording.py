"""The README's combined recording ("When the model is off"): every lab condition at once on
a markers-only paper-protocol recording, evaluated as `cathtrack evaluate` does. The bands are
the issue's: no confidently wrong configuration, UKF RMS at most a third of per-frame Tip
Position's and within 1.2 times the grid filter's, 2-sigma coverage in [93 %, 97 %], mean
NEES in [0.7, 1.5]."""

from __future__ import annotations

import pytest

from replay import evaluation
from replay.protocol import ProtocolSettings, simulate_protocol
from replay.robustness import LabSessionSettings

# The lab sessions' conditions, as the README's `cathtrack simulate` command sets them.
CONDITIONS = LabSessionSettings().conditions


@pytest.fixture(scope="module")
def rows(tmp_path_factory):
    settings = ProtocolSettings(
        images=False, configurations=22, frames_per_configuration=50,
        noise_levels_mm=(0.11, 0.3), lab_conditions=CONDITIONS,
    )  # fmt: skip
    path = tmp_path_factory.mktemp("lab") / "lab.mcap"
    simulate_protocol(settings, path, workers=1, progress=False)
    result = evaluation.evaluate_recording(
        path, None, methods=["tip-position", "ukf", "ukf-position", "grid"], rrd=False, figures=False
    )
    return {row["method"]: row for row in result.tables["robustness"]}


def test_the_ukf_is_three_times_better_than_tip_position_and_within_the_grid(rows):
    ukf = rows["ukf"]["rms_deg"]
    assert ukf <= rows["tip-position"]["rms_deg"] / 3
    assert ukf <= 1.2 * rows["grid"]["rms_deg"]


def test_velocity_fusion_does_not_raise_the_error(rows):
    assert rows["ukf"]["rms_deg"] <= rows["ukf-position"]["rms_deg"] * 1.001
    assert rows["ukf"]["max_deg"] <= rows["ukf-position"]["max_deg"] * 1.001


def test_no_filter_is_confidently_wrong_and_the_ukf_uncertainty_is_calibrated(rows):
    for name in ("ukf", "grid"):
        assert rows[name]["confidently_wrong_configurations"] == 0, name
    ukf = rows["ukf"]
    assert 0.93 <= ukf["within_2sigma"] <= 0.97
    assert 0.7 <= ukf["mean_nees"] <= 1.5
