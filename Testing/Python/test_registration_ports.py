"""The ports a registration was made with travel with it, and what the pairing left out is said.

- ``registration.json`` records ``reference_sensor`` / ``probe_sensor`` (the calibration's ports); ``emreg
  navigate`` and ``emreg evaluate`` use them when the user gives no ports (flag > case.toml ``[sensors]`` >
  the registration's > 1 / 2) and warn, in one line naming both, when the ports given differ from them.
- A calibration point (or a CT marker) left unpaired is named in one warning line with the likely reason.

Small simulated cases (1 mm voxels, 8 markers) made here, run at the command line.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest

from EMRegModule.cli.main import main
from EMRegModule.simulation.case import simulate_case

SMALL = {"frame_size_mm": (200.0, 200.0, 110.0), "n_markers": 8, "navigation_rounds": 2, "board_rounds": 3,
         "n_targets": 3}
RECORDINGS = ("calibration.csv", "navigation.csv", "board.csv")


def _remap_ports(path: Path, ports: dict[int, int]) -> None:
    """Rewrite a tracking CSV with its sensors moved to other ports (a tracker cabled otherwise)."""
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
        fields = list(rows[0])
    for row in rows:
        row["sensor"] = str(ports[int(row["sensor"])])
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fields)
        writer.writeheader()
        writer.writerows(rows)


@pytest.fixture(scope="module")
def cases(tmp_path_factory) -> Path:
    """``plain`` (ports 1 / 2) and ``cabled`` (the same recordings on ports 3 / 4, no [sensors]), the detection
    of the CT, and a calibration + registration of ``cabled`` made with ``--reference-sensor 3 --probe-sensor 4``."""
    root = tmp_path_factory.mktemp("ports")
    simulate_case(root / "plain", seed=5, spacing_mm=1.0, **SMALL)
    shutil.copytree(root / "plain", root / "cabled")
    for name in RECORDINGS:
        _remap_ports(root / "cabled" / name, {1: 3, 2: 4})
    toml = root / "cabled" / "case.toml"  # its [sensors] table left out: the case names no ports
    toml.write_text(toml.read_text().replace("[sensors]\nreference = 1\nprobe = 2\n", ""))
    assert "[sensors]" not in toml.read_text() and "[marker]" in toml.read_text()
    assert main(["detect", str(root / "plain"), "--out", str(root / "det"), "--quiet"]) == 0
    assert main(["calibrate", str(root / "cabled" / "calibration.csv"), "--out", str(root / "reg"),
                 "--reference-sensor", "3", "--probe-sensor", "4", "--quiet"]) == 0
    assert main(["register", "--markers", str(root / "det" / "markers.json"), "--calibration",
                 str(root / "reg" / "frame_calibration.json"), "--out", str(root / "reg"), "--quiet"]) == 0
    return root


def _json(path: Path) -> dict:
    return json.loads(path.read_text())


def _navigate(registration: Path, recording: Path, out: Path, *extra: str) -> int:
    return main(["navigate", "--registration", str(registration), "--source", f"replay:{recording}",
                 "--out", str(out), "--quiet", *extra])


def test_registration_json_records_the_calibration_ports(cases):
    registration = _json(cases / "reg" / "registration.json")
    assert (registration["reference_sensor"], registration["probe_sensor"]) == (3, 4)
    for key in ("ReferenceToImage", "sensor_offset_l_mm", "fre_mm", "pairs", "unpaired_image_markers",
                "unpaired_calibration_points"):
        assert key in registration


def test_navigate_and_evaluate_use_the_registration_ports(cases, tmp_path, capsys):
    registration = cases / "reg" / "registration.json"
    capsys.readouterr()
    assert _navigate(registration, cases / "cabled" / "navigation.csv", tmp_path / "nav") == 0
    assert "warning" not in capsys.readouterr().err
    # the same samples as the plain case navigated on ports 1 / 2 with an equal registration
    plain = tmp_path / "plain_reg"
    shutil.copytree(cases / "reg", plain)
    document = _json(plain / "registration.json")
    del document["reference_sensor"], document["probe_sensor"]  # an older file: the spec's defaults
    document.pop("provenance", None)
    (plain / "registration.json").write_text(json.dumps(document))
    (plain / "run.json").unlink(missing_ok=True)
    assert _navigate(plain / "registration.json", cases / "plain" / "navigation.csv", tmp_path / "nav_plain") == 0
    assert (tmp_path / "nav" / "navigation.csv").read_text() == (tmp_path / "nav_plain" / "navigation.csv").read_text()
    # the older file (no ports) on the re-cabled recording: ports 1 / 2 are absent, a clear refusal
    assert _navigate(plain / "registration.json", cases / "cabled" / "navigation.csv", tmp_path / "nav_old") == 2
    assert "port" in capsys.readouterr().err

    capsys.readouterr()
    case = tmp_path / "case"
    shutil.copytree(cases / "cabled", case)
    assert main(["evaluate", str(case), "--registration", str(registration), "--out", str(tmp_path / "ev"),
                 "--quiet"]) == 0
    assert "warning: the ports" not in capsys.readouterr().err
    evaluation = _json(tmp_path / "ev" / "evaluation.json")
    assert evaluation["tre"]["mean_mm"] < 5 and evaluation["board"]["edges"]


def test_ports_given_win_over_the_registration_with_a_warning(cases, tmp_path, capsys):
    """A tracker re-cabled after the registration: the ports given are used, and the difference is said."""
    registration = cases / "reg" / "registration.json"
    capsys.readouterr()
    assert _navigate(registration, cases / "plain" / "navigation.csv", tmp_path / "nav",
                     "--reference-sensor", "1", "--probe-sensor", "2") == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "reference 1, probe 2" in err[0] and "reference 3, probe 4" in err[0], err

    case = tmp_path / "case"  # calibrated on ports 3 / 4, then re-cabled to 1 / 2 for navigation
    shutil.copytree(cases / "cabled", case)
    for name in ("navigation.csv", "board.csv"):
        shutil.copy2(cases / "plain" / name, case / name)
    (case / "case.toml").write_text("[sensors]\nreference = 1\nprobe = 2\n")
    assert main(["evaluate", str(case), "--registration", str(registration), "--out", str(tmp_path / "ev"),
                 "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "reference 1, probe 2" in err and "reference 3, probe 4" in err
    # case.toml names one port only: the other comes from the registration (here: an absent port, refused)
    (case / "case.toml").write_text("[sensors]\nreference = 3\n")
    assert main(["evaluate", str(case), "--registration", str(registration), "--out", str(tmp_path / "ev2"),
                 "--quiet"]) == 2
    # the flag beats case.toml
    assert main(["evaluate", str(case), "--registration", str(registration), "--out", str(tmp_path / "ev3"),
                 "--reference-sensor", "1", "--probe-sensor", "2", "--quiet"]) == 0
    # the existing checks still hold: the same port twice is refused, a swapped pair too
    capsys.readouterr()
    assert _navigate(registration, cases / "cabled" / "navigation.csv", tmp_path / "same",
                     "--reference-sensor", "4") == 2
    assert "port 4" in capsys.readouterr().err
    assert _navigate(registration, cases / "cabled" / "navigation.csv", tmp_path / "swapped",
                     "--reference-sensor", "4", "--probe-sensor", "3") != 0


def _relabel_rows(path: Path, keep) -> None:
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
        fields = list(rows[0])
    rows = [r for r in (keep(r) for r in rows) if r is not None]
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fields)
        writer.writeheader()
        writer.writerows(rows)


def test_unpaired_points_are_named_in_a_warning(cases, tmp_path, capsys):
    """A pinhole dwell moved 40 mm off every marker (the probe not in a pinhole) and another marker's dwell
    left out of the calibration: each is named on stderr with its likely reason; exit 0."""
    recording = tmp_path / "calibration.csv"
    shutil.copy2(cases / "plain" / "calibration.csv", recording)
    with recording.open(newline="") as f:
        labels = sorted({r["label"] for r in csv.DictReader(f) if r["label"]})
    moved, dropped = labels[0], labels[1]

    def change(row: dict) -> dict | None:
        if row["label"] == dropped:
            return None
        if row["label"] == moved and row["sensor"] == "2":
            row["x_mm"] = f"{float(row['x_mm']) + 40.0:.4f}"
        return row

    _relabel_rows(recording, change)
    out = tmp_path / "out"
    assert main(["calibrate", str(recording), "--out", str(out), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["register", "--markers", str(cases / "det" / "markers.json"), "--calibration",
                 str(out / "frame_calibration.json"), "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err.splitlines()
    registration = _json(out / "registration.json")
    assert registration["unpaired_calibration_points"] == [moved]
    assert len(registration["unpaired_image_markers"]) == 2  # the moved one's and the dropped one's markers
    cal_lines = [line for line in err if "calibration point(s)" in line]
    assert len(cal_lines) == 1 and moved in cal_lines[0] and "not in a pinhole" in cal_lines[0]
    marker_lines = [line for line in err if "CT marker(s)" in line]
    assert len(marker_lines) == 1
    assert all(m in marker_lines[0] for m in registration["unpaired_image_markers"])


def test_live_navigate_uses_the_registration_ports(cases, tmp_path, capsys):
    """The live path (a replay published on OpenIGTLink) takes the registration's ports as the offline one does,
    and says when the ports given differ."""
    registration = cases / "reg" / "registration.json"
    live = ["--igtl-port", "0", "--fast", "--duration", "60"]
    capsys.readouterr()
    assert _navigate(registration, cases / "cabled" / "navigation.csv", tmp_path / "live", *live) == 0
    assert "warning" not in capsys.readouterr().err
    offline = tmp_path / "offline"
    assert _navigate(registration, cases / "cabled" / "navigation.csv", offline) == 0
    rows = (tmp_path / "live" / "navigation.csv").read_text().splitlines()
    expected = (offline / "navigation.csv").read_text().splitlines()
    assert set(rows) <= set(expected) and len(rows) > 0.9 * len(expected) > 10  # live may skip a stale sample
    # the ports given win, with the one-line warning (ports 1 / 2 are absent from this recording: exit 2)
    code = _navigate(registration, cases / "cabled" / "navigation.csv", tmp_path / "given", *live,
                     "--reference-sensor", "1", "--probe-sensor", "2")
    err = capsys.readouterr().err
    assert "differ from those of the registration's calibration (reference 3, probe 4" in err
    assert code == 2
    # swapped ports on a live replay: refused as offline, before anything is published
    code = _navigate(registration, cases / "cabled" / "navigation.csv", tmp_path / "swapped", *live,
                     "--reference-sensor", "4", "--probe-sensor", "3")
    assert code == 2 and "swapped" in capsys.readouterr().err
