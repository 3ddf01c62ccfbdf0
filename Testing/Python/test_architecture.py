"""The package keeps its shape (issues 25, 36): one-way layers, no import circle, a pure core, imports at module tops,
front ends that reach only the pipeline.

``scripts/architecture.py`` reads the source and lists every finding; each test here asserts one list is
empty, so a change that adds an upward import, a circle or an import hidden in a function fails with its name; sizes
are reported by the script, never asserted.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _architecture():
    spec = importlib.util.spec_from_file_location("emreg_architecture", ROOT / "scripts" / "architecture.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def shape():
    return _architecture().survey(ROOT)


def test_every_module_has_a_layer(shape):
    assert shape.unlayered == []


def test_no_import_runs_up_a_layer(shape):
    assert shape.upward == []


def test_no_import_circle(shape):
    assert shape.circles == []


def test_core_imports_only_the_base_and_itself(shape):
    """Issue 36: the algorithms are pure; no file format, device, workflow or front end reaches into them."""
    architecture = _architecture()
    allowed = {i for i, (layer, _) in enumerate(architecture.LAYERS) if layer in ("base", "core")}
    reached = {(name, target) for name, targets in shape.imports.items() if name.startswith("EMRegModule.core")
               for target in targets if architecture.layer_of(target) not in allowed}
    assert reached == set()


def test_imports_are_at_module_top_but_for_the_deferred_ones(shape):
    """Issue 36: every import at its module's top, where a reader sees what depends on what, but for the optional
    extras and heavy libraries ``DEFERRED_IMPORTS`` lists (each with its reason) and the 3D Slicer module's own
    package (``DEFERRED_IN_MODULES``)."""
    assert shape.inner_imports == []


def test_no_private_name_is_imported_from_another_module(shape):
    assert shape.private_imports == []


def test_front_ends_reach_only_the_pipeline_io_devices_and_base(shape):
    """The command line and the Slicer module parse, call the pipeline (``pipeline/``, ``live/``, ``studies/``) and
    print: no algorithm (``core``) or product (report, rendering, scene bundle, simulation) is called from them."""
    assert shape.front_end_reach == []


def test_the_survey_sees_a_planted_circle_and_an_upward_import(tmp_path):
    """The checks can fail: a copy of two modules that import each other, one of them from above."""
    package = tmp_path / "EMRegModule"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "core").mkdir()
    (package / "core" / "__init__.py").write_text("")
    (package / "core" / "transforms.py").write_text("from ..cli import main\n\ndef _helper():\n    pass\n")
    (package / "cli.py").write_text("from .core.transforms import _helper\n\ndef main():\n" + "    x = 1\n" * 95)
    found = _architecture().survey(tmp_path)
    assert found.circles == [["EMRegModule.cli", "EMRegModule.core.transforms"]]
    assert found.upward == [("EMRegModule.core.transforms", "EMRegModule.cli")]
    assert found.private_imports == [("EMRegModule.cli", "EMRegModule.core.transforms", "_helper")]
    assert found.front_end_reach == [("EMRegModule.cli", "EMRegModule.core.transforms")]
    assert [(name, function) for _, name, function in found.long_functions] == [("EMRegModule.cli", "main")]


def test_the_survey_sees_an_import_inside_a_function_unless_deferred(tmp_path):
    package = tmp_path / "EMRegModule"
    (package / "core").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "core" / "__init__.py").write_text("")
    (package / "core" / "pivot.py").write_text("def fit():\n    import json\n    import scipy.optimize\n"
                                                "    from ..errors import EMRegError\n")
    (package / "errors.py").write_text("")
    found = _architecture().survey(tmp_path)
    assert found.inner_imports == [("EMRegModule.core.pivot", "json"), ("EMRegModule.core.pivot", "EMRegModule.errors")]


def test_the_slicer_module_defers_only_the_package(tmp_path):
    """The 3D Slicer module imports the package inside its functions (``DEFERRED_IN_MODULES``), nothing else."""
    package = tmp_path / "EMRegModule"
    (package / "slicer").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "errors.py").write_text("")
    (package / "slicer" / "EMReg.py").write_text("def load():\n    import json\n    from EMRegModule import errors\n")
    found = _architecture().survey(tmp_path)
    assert found.inner_imports == [("EMRegModule.slicer.EMReg", "json")]
