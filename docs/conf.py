"""Sphinx configuration of EMReg's manual (MyST Markdown, furo theme).

Built by ``scripts/test`` with warnings as errors, so that a broken link, a renamed option or a docstring
Sphinx cannot read fails the tests. Nothing is fetched at build time: no intersphinx, the theme and every
extension come from the locked environment.
"""

import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
sys.path.insert(0, str(DOCS.parent))  # EMRegModule of this checkout, for autodoc and the CLI reference
sys.path.insert(0, str(DOCS / "_ext"))

from EMRegModule import __version__  # noqa: E402

project = "EMReg"
author = "The EMReg developers"
copyright = "2026, The EMReg developers"
version = release = __version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinxarg.ext",
    "emreg_cli",  # docs/_ext/emreg_cli.py: the {cli} role, checked against emreg's parser
    "emreg_api",  # docs/_ext/emreg_api.py: the API reference's pages, from the package's layout
    "emreg_docstrings",  # docs/_ext/emreg_docstrings.py: a norm |x| in a docstring stays a norm
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
myst_enable_extensions = ["colon_fence", "deflist"]
myst_heading_anchors = 3
# Short names in docstrings (``stages``, ``protocol``, a re-exported class) may match several modules; the
# first match is a fine link, and the ambiguity is no error of the manual.
suppress_warnings = ["ref.python"]

# The API reference: pages written at build time into reference/api/ (git-ignored), see docs/_ext/emreg_api.py.
# A package documents what it defines; what it re-exports is documented where it is defined.
autodoc_default_options = {"members": True, "ignore-module-all": True}
autodoc_member_order = "bysource"
# numpy's ArrayLike by its name, not the union it stands for (a dozen lines in every signature)
autodoc_type_aliases = {"ArrayLike": "ArrayLike", "NDArray": "NDArray"}
add_module_names = False
python_maximum_signature_line_length = 100
# Optional extras and 3D Slicer's application: documented from their source without importing them.
autodoc_mock_imports = ["qt", "ndicapi", "dask", "distributed"]
nitpicky = False

html_theme = "furo"
html_title = f"EMReg {release}"
html_static_path = ["_static"]
html_logo = "_static/images/EMReg.png"
html_show_sourcelink = False
