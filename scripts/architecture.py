"""The shape of EMRegModule: its layers, the imports between them, and the signs a review looks at.

Reads the package's source (no import of it) and reports:

- the layer of every module (``LAYERS``, lowest first) and any import that runs from a lower layer up to a
  higher one;
- import circles (strongly connected modules, a package's ``__init__`` counted as a module);
- private names (``_x``) imported from another module;
- imports inside a function whose module is not in ``DEFERRED_IMPORTS`` (each deferred one has its reason there)
  nor, in a module of ``DEFERRED_IN_MODULES``, one of the modules it defers;
- for a reviewer, not a rule: functions over ``MAX_FUNCTION_LINES``, modules over ``MAX_MODULE_LINES``, classes
  over ``MAX_METHODS``. Code is split by concern; a size is a place to look, never a number to serve.

    .venv/bin/python scripts/architecture.py [--root .]

``Testing/Python/test_architecture.py`` asserts that the layers, circles and private-import lists are empty; the
sizes are only reported.
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

#: The layers, lowest first: a module may import from its own layer and the layers below it, never above.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("base", ("__init__", "errors", "names", "tables", "progress", "interrupts", "marker_model", "settings",
              "stages")),
    ("core", ("core",)),
    ("io", ("io",)),
    ("devices", ("devices",)),
    ("products", ("rendering", "report", "slicer_export", "simulation")),
    ("pipeline", ("pipeline", "live", "studies")),
    ("faces", ("cli", "__main__", "slicer")),
)
#: The front ends (they parse, call the pipeline and print) and the only layers they may import from.
FRONT_ENDS = ("cli", "slicer", "__main__")
FRONT_END_REACH = ("base", "io", "devices", "pipeline")
#: The one place imports inside a function are allowed: optional extras (installed with an extra, or present only
#: inside 3D Slicer) and the heavy libraries a command loads only when it gets to the step that needs them, each with
#: its reason. Every other import is at the top of its module, where a reader sees what depends on what.
DEFERRED_IMPORTS: dict[str, str] = {
    # optional extras (pyproject's optional-dependencies) and 3D Slicer's own
    "franky": "the robot extra (franky-control): only a franka:// robot URL needs it",
    "magpylib": "the studies extra: one held-out distortion family of the trust study",
    "distributed": "the studies extra (Dask): only emreg study runs on a cluster",
    "slicer": "slicer-core (the optional extra slicer) or 3D Slicer's own: only the scene bundle's process and the "
              "Slicer module load it",
    # heavy libraries a command loads only at the step that needs them (python -X importtime, CPU after numpy)
    "SimpleITK": "~0.1 s: a DICOM series read into numpy (emreg detect), navigate and the run folder's readers need "
                 "none",
    "pydicom": "~0.1 s: DICOM folders only (Testing/Python/test_import_weight.py)",
    "pyvista": "~0.2 s with VTK's rendering: the report's figures only (test_import_weight)",
    "scipy.special": "~0.18 s: the error model's and the checkpoints' distribution tails, when they are computed; "
                     "the controller and emreg --help load no scipy",
    "scipy.optimize": "~0.28 s: the sensor-offset and distortion fits, at registration (test_import_weight)",
    "scipy.spatial": "~0.23 s: the pairing's k-d tree, at registration",
    "vtkmodules": "~0.1 s (its filters; the package itself is only looked for): the marker mesh and the rendering "
                  "load it, emreg --help and the readers do not",
    "scipy.ndimage": "~0.2 s: detection's segmentation and the report's context surface and slices",
    "EMRegModule.core.detection.detect": "scipy.ndimage and VTK, ~0.36 s: imported in the background while the CT "
                                         "is read; readers of markers.json do not need it",
    "EMRegModule.io.ct_header": "the CT file readers' header code loads SimpleITK and ISA-L (~0.1 s), which a DICOM "
                                "folder's read does not need",
    "EMRegModule.io.fast_read": "the CT file reader (SimpleITK, ISA-L, ~0.1 s): not for a DICOM folder",
    "EMRegModule.io.dicom_read": "the DICOM series reader (~45 ms, its thread pool): only for a folder",
    "EMRegModule.core.handeye_profile": "the hand-eye solver's scipy.stats and scipy.signal (seconds, cold): only the "
                                        "report of a folder with robot_calibration.json needs them",
    "EMRegModule.io.tre_map": "SimpleITK (a 270 MB library, 50 ms of CPU to load): only where tre_map.nrrd is written; "
                              "emreg detect on an uncompressed DICOM series never loads it",
    "EMRegModule.io.ct_stream": "SimpleITK, as for io.tre_map: the report's streamed read of a CT file",
    "EMRegModule.report.writer": "the report's figures (rendering, OpenCV, SciPy's ndimage: ~0.26 s): emreg report "
                                 "(pipeline.reporting, report.batch) loads them once its CT's read has started in the "
                                 "background",
}
#: Modules that import some modules only inside their functions, whatever those modules cost: module -> (the
#: prefix of the names it defers, why).
DEFERRED_IN_MODULES: dict[str, tuple[str, str]] = {
    "EMRegModule.slicer.EMReg": (
        "EMRegModule", "3D Slicer loads the module file before its panel or Logic has installed the packages EMReg "
                       "needs (ensureEMRegImportable), and on Pythons too old for the package, which it then names: "
                       "only the plain base modules names and errors are at its top"),
}
MAX_FUNCTION_LINES = 90
MAX_MODULE_LINES = 700
MAX_METHODS = 30
#: Classes whose method count is reported (the controller; drivers mirror a device's command set).
BOUNDED_CLASSES = ("EMRegController",)


@dataclass
class Shape:
    """What :func:`survey` found: the layer, circle and private-import lists are findings (empty when the code is
    in shape); the size lists are for a reviewer to look at."""

    modules: dict[str, Path]
    lines: dict[str, int]
    imports: dict[str, set[str]]
    circles: list[list[str]] = field(default_factory=list)
    upward: list[tuple[str, str]] = field(default_factory=list)
    long_functions: list[tuple[int, str, str]] = field(default_factory=list)
    big_modules: list[tuple[int, str]] = field(default_factory=list)
    big_classes: list[tuple[int, str, str]] = field(default_factory=list)
    private_imports: list[tuple[str, str, str]] = field(default_factory=list)
    inner_imports: list[tuple[str, str]] = field(default_factory=list)
    front_end_reach: list[tuple[str, str]] = field(default_factory=list)
    unlayered: list[str] = field(default_factory=list)


def layer_of(module: str) -> int | None:
    """Index into ``LAYERS`` of a dotted module name ``EMRegModule.x...`` (None: in no layer)."""
    parts = module.split(".")
    top = parts[1] if len(parts) > 1 else "__init__"
    return next((i for i, (_, names) in enumerate(LAYERS) if top in names), None)


def _top(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _deferred(target: str, importer: str = "") -> bool:
    """Whether ``target`` may be imported inside a function (of ``importer``)."""
    names = [*DEFERRED_IMPORTS, *(DEFERRED_IN_MODULES[importer][:1] if importer in DEFERRED_IN_MODULES else ())]
    return any(target == name or target.startswith(name + ".") for name in names)


def _inner_imports(module: str, tree: ast.Module, is_package: bool) -> Iterator[str]:
    """The modules imported inside a function of ``module`` (absolute names; ``__future__`` aside)."""
    for function in ast.walk(tree):
        if not isinstance(function, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        for node in ast.walk(function):
            if isinstance(node, ast.Import):
                yield from (alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                yield _target(module, node, is_package)


def _modules(root: Path) -> dict[str, Path]:
    found = {}
    for path in sorted((root / "EMRegModule").rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found[".".join(parts)] = path
    return found


def _target(module: str, node: ast.ImportFrom, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".")[: len(module.split(".")) - (node.level - (1 if is_package else 0))]
    return ".".join(base + ([node.module] if node.module else []))


def _imports(module: str, tree: ast.Module, is_package: bool, modules: dict[str, Path],
             shape: Shape) -> Iterator[str]:
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names if alias.name in modules)
        elif isinstance(node, ast.ImportFrom):
            target = _target(module, node, is_package)
            if target in modules:
                yield target
            for alias in node.names:
                if f"{target}.{alias.name}" in modules:
                    yield f"{target}.{alias.name}"
                elif target in modules and alias.name.startswith("_") and not alias.name.startswith("__"):
                    shape.private_imports.append((module, target, alias.name))


def _circles(imports: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in imports:
        if start in index:
            continue
        work = [(start, iter(sorted(imports[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(imports[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def survey(root: Path) -> Shape:
    """The shape of ``root/EMRegModule``."""
    modules = _modules(root)
    shape = Shape(modules, {}, {name: set() for name in modules})
    for name, path in modules.items():
        text = path.read_text(encoding="utf-8")
        shape.lines[name] = text.count("\n")
        tree = ast.parse(text)
        shape.imports[name] = set(_imports(name, tree, path.name == "__init__.py", modules, shape)) - {name}
        shape.inner_imports += [(name, target) for target in _inner_imports(name, tree, path.name == "__init__.py")
                                if not _deferred(target, name)]
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    shape.long_functions.append((length, name, node.name))
            elif isinstance(node, ast.ClassDef) and node.name in BOUNDED_CLASSES:
                methods = sum(isinstance(b, ast.FunctionDef | ast.AsyncFunctionDef) for b in node.body)
                if methods > MAX_METHODS:
                    shape.big_classes.append((methods, name, node.name))
        if shape.lines[name] > MAX_MODULE_LINES:
            shape.big_modules.append((shape.lines[name], name))
        if layer_of(name) is None:
            shape.unlayered.append(name)
    shape.circles = _circles(shape.imports)
    front_end_layers = {i for i, (layer, _) in enumerate(LAYERS) if layer in FRONT_END_REACH}
    for name, targets in shape.imports.items():
        if _top(name) in FRONT_ENDS:
            shape.front_end_reach += [(name, t) for t in sorted(targets)
                                      if _top(t) not in FRONT_ENDS and layer_of(t) not in front_end_layers]
    for name, targets in shape.imports.items():
        here = layer_of(name)
        shape.upward += [(name, t) for t in sorted(targets)
                         if here is not None and (there := layer_of(t)) is not None and there > here]
    return shape


def describe(shape: Shape) -> list[str]:
    """The report, a line per fact."""
    lines = []
    for i, (layer, _) in enumerate(LAYERS):
        members = [m for m in shape.modules if layer_of(m) == i]
        total = sum(shape.lines[m] for m in members)
        longest = max((shape.lines[m], m) for m in members) if members else (0, "-")
        lines.append(f"layer {i} {layer:9s} {len(members):3d} modules {total:6d} lines, largest {longest[1]} "
                     f"({longest[0]})")
    longest_function = max((length, f"{m}.{f}") for length, m, f in shape.long_functions) \
        if shape.long_functions else None
    lines.append(f"import circles: {len(shape.circles)}" + "".join(f"\n  {c}" for c in shape.circles))
    lines.append(f"upward imports: {len(shape.upward)}" + "".join(f"\n  {a} -> {b}" for a, b in shape.upward))
    lines.append(f"functions over {MAX_FUNCTION_LINES} lines: {len(shape.long_functions)}"
                 + (f" (longest {longest_function[1]}, {longest_function[0]})" if longest_function else ""))
    lines += [f"  {length} {m}.{f}" for length, m, f in sorted(shape.long_functions, reverse=True)]
    lines.append(f"modules over {MAX_MODULE_LINES} lines: {len(shape.big_modules)}")
    lines += [f"  {length} {m}" for length, m in sorted(shape.big_modules, reverse=True)]
    lines.append(f"classes over {MAX_METHODS} methods: {len(shape.big_classes)}")
    lines += [f"  {n} {m}.{c}" for n, m, c in shape.big_classes]
    lines.append(f"private names imported across modules: {len(shape.private_imports)}")
    lines += [f"  {m} imports {t}.{n}" for m, t, n in shape.private_imports]
    lines.append(f"imports inside functions, not in DEFERRED_IMPORTS: {len(shape.inner_imports)}")
    lines += [f"  {m} imports {t}" for m, t in shape.inner_imports]
    lines.append(f"front-end imports beyond {', '.join(FRONT_END_REACH)}: {len(shape.front_end_reach)}")
    lines += [f"  {m} imports {t}" for m, t in shape.front_end_reach]
    lines.append(f"modules in no layer: {len(shape.unlayered)}" + "".join(f"\n  {m}" for m in shape.unlayered))
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parent.parent)
    args = parser.parse_args(argv)
    print("\n".join(describe(survey(args.root))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
