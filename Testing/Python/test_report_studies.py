"""Smoke test of the accuracy-study scripts (scripts/study_*.py) at tiny sizes.

The studies are scripts, not tests: this only checks that each one runs on the simulated
standard case and prints its table beside the paper's figure. The real figures come from
running them at full size (see each script's docstring).
"""

import importlib
import sys
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"

STUDIES = {
    "study_calibration": (["--repetitions", "2"], ["FRE mean (mm)", "1.38", "FRE distribution"]),
    "study_board": ([], ["L1", "75.32 / 0.18", "all edges within 1 mm"]),
    "study_tre": (["--registrations", "1", "--placements", "2"], ["TRE mean +/- std", "1.38 +/- 0.32"]),
    "study_prediction": (["--repetitions", "2"], ["predicted RMS TRE", "estimated by the registration"]),
    "study_noise": (["--scales", "0", "1", "--repetitions", "1"], ["noise scale", "registration TRE RMS"]),
    "study_markers": (["--counts", "3", "6", "--repetitions", "1"], ["markers", "refusals: 1 x pairing needs"]),
}


@pytest.fixture(scope="module")
def study_modules():
    sys.path.insert(0, str(SCRIPTS))
    try:
        yield {name: importlib.import_module(name) for name in STUDIES}
    finally:
        sys.path.remove(str(SCRIPTS))


@pytest.mark.parametrize("name", list(STUDIES))
def test_study_prints_its_table(name, study_modules, standard_case, tmp_path_factory, capsys):
    work = tmp_path_factory.getbasetemp() / "study-work"  # shared: the CT is detected once for all studies
    extra, expected = STUDIES[name]
    code = study_modules[name].main(["--case", str(standard_case), "--work", str(work), "--quick", *extra])
    out = capsys.readouterr().out
    assert code == 0
    for text in expected:
        assert text in out, f"{name}: {text!r} missing from\n{out}"
    assert "| " in out  # a table
