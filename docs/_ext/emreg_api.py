"""The API reference's pages, written from the package's layout when the build starts.

One page per top-level module of ``EMRegModule`` and one per subpackage (its ``__init__`` and every module in
it, on the same page), into ``docs/reference/api/`` (git-ignored): a module added to the package is documented
without anyone listing it, and the site's navigation stays a few dozen pages long (a page per submodule made the
theme's sidebar, computed for every page, the larger part of the build time).
"""

from __future__ import annotations

import pkgutil
from pathlib import Path

PACKAGE = "EMRegModule"
SKIPPED = {"__main__"}  # runs the command line when imported


def _modules(path: Path, prefix: str) -> list[tuple[str, bool]]:
    """(dotted name, is a package) of the modules directly in ``path``, in name order."""
    return sorted((prefix + info.name, info.ispkg) for info in pkgutil.iter_modules([str(path)])
                  if info.name not in SKIPPED)


def _walk(path: Path, prefix: str) -> list[str]:
    names = []
    for name, is_package in _modules(path, prefix):
        names.append(name)
        if is_package:
            names += _walk(path / name.rsplit(".", 1)[-1], name + ".")
    return names


def _page(title: str, modules: list[str]) -> str:
    lines = [title, "=" * len(title), ""]
    for module in modules:
        lines += [f".. automodule:: {module}", ""]
    return "\n".join(lines)


def pages(root: Path) -> dict[str, str]:
    """File name -> reST text of every API page."""
    package = root / PACKAGE
    result = {f"{PACKAGE}.rst": _page(PACKAGE, [PACKAGE])}
    for name, is_package in _modules(package, PACKAGE + "."):
        modules = [name] + (_walk(package / name.rsplit(".", 1)[-1], name + ".") if is_package else [])
        result[f"{name}.rst"] = _page(name + ("/" if is_package else ""), modules)
    return result


def write_pages(app) -> None:
    folder = Path(app.srcdir) / "reference" / "api"
    folder.mkdir(parents=True, exist_ok=True)
    wanted = pages(Path(app.srcdir).parent)
    for stale in folder.glob("*.rst"):
        if stale.name not in wanted:
            stale.unlink()
    for name, text in wanted.items():
        path = folder / name
        if not path.is_file() or path.read_text(encoding="utf-8") != text:  # unchanged pages stay unchanged
            path.write_text(text, encoding="utf-8")


def setup(app):
    app.connect("builder-inited", write_pages)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
