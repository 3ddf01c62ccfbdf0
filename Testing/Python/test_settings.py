"""Settings: one typed tree from case.toml; every table and key known or refused with one line."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys

import pytest

from EMRegModule.errors import EMRegError
from EMRegModule.settings import (
    CalibrationSettings,
    DetectionSettings,
    DwellSettings,
    EvaluationSettings,
    PairingSettings,
    RegistrationSettings,
    Settings,
    load_settings,
)
from EMRegModule.tables import defaults_of, table_keys


def _load(tmp_path, text: str) -> Settings:
    path = tmp_path / "case.toml"
    path.write_text(text)
    return load_settings(path)


def _refused(tmp_path, text: str) -> str:
    with pytest.raises(EMRegError) as info:
        _load(tmp_path, text)
    message = str(info.value)
    assert "\n" not in message and str(tmp_path / "case.toml") in message
    return message


def test_defaults_without_a_file(tmp_path):
    settings = load_settings(tmp_path / "absent.toml")
    assert settings == Settings()
    assert (settings.sensors.reference, settings.sensors.probe) == (1, 2)
    assert settings.registration.max_fre_mm == 2.0 and settings.registration.pairing.min_pairs == 4
    assert settings.evaluation.still_radius_mm == 1.0 and settings.calibration.still_radius_mm == 0.5
    assert settings.calibration.revisit_tolerance_mm == 1.0 and settings.report.iso_value is None
    with pytest.raises(EMRegError, match="settings file not found"):
        load_settings(tmp_path / "absent.toml", required=True)


def test_a_misspelt_table_is_refused_and_names_the_known_ones(tmp_path):
    message = _refused(tmp_path, "[registraton]\nmax_fre_mm = 0.1\n")
    assert "unknown table [registraton]" in message and "[registration]" in message and "[evaluation]" in message


def test_a_table_that_is_a_value_is_refused(tmp_path):
    assert "detection must be a table" in _refused(tmp_path, "detection = 5\n")


@pytest.mark.parametrize(("text", "table", "key"), [
    ("[sensors]\nrefrence = 1\n", "sensors", "refrence"),
    ("[evaluation]\nmax_target_distance = 3\n", "evaluation", "max_target_distance"),
    ("[report]\niso = 300\n", "report", "iso"),
    ("[registration]\nmax_fre = 0.5\n", "registration", "max_fre"),
    ("[calibration]\nrevisit_tolerance = 0.5\n", "calibration", "revisit_tolerance"),
    ("[marker]\nheight = 3\n", "marker", "height"),
    ("[board]\nedges = [1, 2, 3]\n", "board", "edges"),
    ("[detection]\nlow_hue = 500\n", "detection", "low_hue"),
])
def test_an_unknown_key_is_refused_in_every_table(tmp_path, text, table, key):
    message = _refused(tmp_path, text)
    known = ", ".join(sorted(table_keys(type(getattr(Settings(), table)))))
    assert re.search(rf"\[{table}\] unknown key {key}; known: {re.escape(known)}$", message), message


@pytest.mark.parametrize(("text", "expected"), [
    ("[registration]\nmax_fre_mm = true\n", r"\[registration\] max_fre_mm must be a number, got True"),
    ("[registration]\nmax_fre_mm = '0.5'\n", r"max_fre_mm must be a number, got '0.5'"),
    ("[registration]\nmax_fre_mm = -1\n", r"max_fre_mm must be a positive number, got -1"),
    ("[registration]\nmax_fre_mm = nan\n", r"max_fre_mm must be a finite number"),
    ("[registration]\nmin_pairs = 3.5\n", r"min_pairs must be a whole number, got 3.5"),
    ("[registration]\nexclude_outliers = 1\n", r"exclude_outliers must be true or false"),
    ("[calibration]\nrevisit_tolerance_mm = 0\n", r"revisit_tolerance_mm must be a positive number"),
    ("[evaluation]\nmax_target_distance_mm = -3\n", r"\[evaluation\] max_target_distance_mm must be a positive"),
    ("[evaluation]\nmin_samples = 'many'\n", r"min_samples must be a whole number"),
    ("[report]\niso_value = 'auto'\n", r"\[report\] iso_value must be a number, got 'auto'"),
    ("[sensors]\nreference = 2\n", r"\[sensors\] reference and probe are both port 2"),
    ("[sensors]\nprobe = 0\n", r"probe must be a port number \(1 or more.*got 0"),
    ("[board]\nedges_mm = [75, 'x', 60]\n", r"\[board\] edges_mm must be a list of numbers"),
    ("[board]\nedges_mm = [75, 60]\n", r"edges_mm must be three or more positive lengths"),
    ("[detection]\nlow_hu = 2000\n", r"\[detection\] need low_hu < high_hu <= metal_hu"),
    ("[detection]\nmin_inlier_fraction = 1.5\n", r"min_inlier_fraction must lie in \(0, 1\]"),
    ("[marker]\ntop_diameter_mm = 20\n", r"\[marker\] marker model: the top cylinder"),
    ("[ct]\nseries = 1.5\n", r"\[ct\] series must be a string or a whole number"),
])
def test_values_are_type_and_range_checked(tmp_path, text, expected):
    assert re.search(expected, _refused(tmp_path, text))


def test_a_tightened_safety_limit_is_applied(tmp_path):
    settings = _load(tmp_path, "[registration]\nmax_fre_mm = 0.1\nmin_pairs = 6\n"
                               "[evaluation]\nmin_duration_s = 0.3\nmax_target_distance_mm = 5\n"
                               "[report]\niso_value = 300\n[ct]\nseries = 3\n")
    assert settings.registration.max_fre_mm == 0.1 and settings.registration.pairing.min_pairs == 6
    assert isinstance(settings.registration.pairing.min_pairs, int)
    assert settings.evaluation.min_duration_s == 0.3 and settings.evaluation.max_target_distance_mm == 5.0
    assert settings.evaluation.still_radius_mm == 1.0  # the evaluation's own default stays
    assert settings.report.iso_value == 300.0 and settings.ct.series == 3
    assert settings.source == str(tmp_path / "case.toml")


def test_detection_defaults_follow_the_marker(tmp_path):
    settings = _load(tmp_path, "[marker]\ntop_diameter_mm = 4.5\n")
    assert settings.detection.coarse_step_mm == pytest.approx(1.5)
    settings = _load(tmp_path, "[marker]\ntop_diameter_mm = 4.5\n[detection]\ncoarse_step_mm = 1.0\n")
    assert settings.detection.coarse_step_mm == 1.0


def test_command_line_ports_are_checked_like_the_table():
    settings = Settings()
    assert settings.with_sensors(3, None).sensors.reference == 3
    assert settings.with_sensors(2, 1).sensors == dataclasses.replace(settings.sensors, reference=2, probe=1)
    with pytest.raises(EMRegError, match=r"command line: \[sensors\] reference and probe are both port 1"):
        settings.with_sensors(None, 1)
    with pytest.raises(EMRegError, match="port number"):
        settings.with_sensors(-1, None)


def test_the_tree_is_frozen_and_its_digest_tracks_values(tmp_path):
    settings = _load(tmp_path, "[registration]\nmax_fre_mm = 1.5\n")
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.registration.max_fre_mm = 5.0  # type: ignore[misc]
    assert settings.digest() != Settings().digest()
    assert settings.digest() == _load(tmp_path, "[registration]\nmax_fre_mm = 1.50\n").digest()
    assert settings.to_json()["registration"]["pairing"]["min_pairs"] == 4


def test_the_stage_tables_are_the_settings_classes():
    """One class per table: the stage modules re-export the settings' classes, with one set of defaults."""
    from EMRegModule.core import calibration, detection, dwell, pairing, registration

    assert registration.RegistrationSettings is RegistrationSettings and pairing.PairingSettings is PairingSettings
    assert dwell.DwellSettings is DwellSettings and detection.DetectionSettings is DetectionSettings
    assert calibration.CalibrationSettings is CalibrationSettings
    assert issubclass(CalibrationSettings, DwellSettings) and issubclass(EvaluationSettings, DwellSettings)
    assert defaults_of(RegistrationSettings)["min_pairs"] == PairingSettings().min_pairs


def test_docs_settings_table_lists_every_key():
    """The manual's settings table (``docs/guide/settings.md``) names every key of every optional table, and no
    other."""
    from pathlib import Path

    page = (Path(__file__).resolve().parents[2] / "docs" / "guide" / "settings.md").read_text(encoding="utf-8")
    rows = {m.group(1): m.group(2) for m in re.finditer(r"^ *\| `\[(\w+)\]` \| (.*) \|$", page, re.M)}
    for table in ("detection", "calibration", "registration", "evaluation", "navigation", "report", "handeye", "robot"):
        documented = set(re.findall(r"`(\w+)`", rows[table]))
        keys = set(table_keys(type(getattr(Settings(), table))))
        if table in ("evaluation", "navigation"):  # "the dwell keys of [calibration]", "the dwell keys (...)"
            documented |= set(table_keys(DwellSettings))
        assert keys <= documented, (table, sorted(keys - documented))
        assert documented <= keys, (table, sorted(documented - keys))


def test_the_robots_tables_stay_out_of_a_runs_settings_until_given(tmp_path):
    """[handeye] and [robot], which no registration stage reads, are in a run's settings JSON (and its digest, the
    provenance of every output) only when the file gives them: runs made before they existed keep their digest."""
    defaults = Settings().to_json()
    assert "handeye" not in defaults and "robot" not in defaults and "navigation" in defaults
    (tmp_path / "case.toml").write_text("[robot]\nstandoff_mm = 5.0\n")
    given = load_settings(tmp_path / "case.toml")
    assert given.to_json()["robot"]["standoff_mm"] == 5.0 and "handeye" not in given.to_json()
    assert given.digest() != Settings().digest()


def test_emreg_refuses_a_typo_with_one_line(tmp_path):
    (tmp_path / "case.toml").write_text("[registraton]\nmax_fre_mm = 0.1\n")
    done = subprocess.run([sys.executable, "-m", "EMRegModule.cli.main", "calibrate", str(tmp_path / "x.csv"),
                           "--out", str(tmp_path / "out"), "--settings", str(tmp_path / "case.toml")],
                          capture_output=True, text=True, check=False)
    assert done.returncode == 2
    assert done.stderr.strip().count("\n") == 0 and "unknown table [registraton]" in done.stderr
    assert not (tmp_path / "out" / "frame_calibration.json").exists()
