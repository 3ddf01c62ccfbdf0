"""The manual's own checks: a command line named in docs/ must be one ``emreg``'s parser knows.

``scripts/test`` builds the manual with warnings as errors; these tests pin the check that makes a renamed
option fail that build (``docs/_ext/emreg_cli.py``), without building the site.
"""

from __future__ import annotations

import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parents[2] / "docs"
sys.path.insert(0, str(DOCS / "_ext"))

from emreg_cli import problems  # noqa: E402 - docs/_ext is not a package


def test_a_known_command_line_passes_and_names_its_subcommand():
    assert problems("emreg run CASE --out OUT") == ("run", [])
    assert problems("emreg navigate --registration R --source replay:FILE --out OUT") == ("navigate", [])
    assert problems("emreg sim-tracker [--model trakstar|aurora]") == ("sim-tracker", [])
    assert problems("emreg --version") == ("", [])


def test_a_renamed_option_or_an_unknown_subcommand_is_named():
    assert problems("emreg run CASE --output OUT")[1] == ["emreg run has no option --output"]
    assert problems("emreg frobnicate X")[1] == ["no emreg subcommand 'frobnicate'"]
    assert problems("emreg detect CT --out OUT --series=3 --fast")[1] == ["emreg detect has no option --fast"]


def test_every_page_of_the_user_guide_is_in_a_table_of_contents():
    """``index.md`` takes ``guide/*`` by a glob, so a page added there needs no listing; the tutorials are named."""
    index = (DOCS / "index.md").read_text(encoding="utf-8")
    assert "guide/*" in index
    for page in sorted((DOCS / "tutorials").glob("*.md")):
        assert f"tutorials/{page.stem}" in index
