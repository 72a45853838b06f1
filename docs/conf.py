"""Sphinx configuration of the torchsoil manual: Markdown pages (MyST), the API reference
from the docstrings (autodoc), the settings and benchmark pages generated at build time.

Build: `python3 -m sphinx -W -b html docs out/docs` (warnings are errors; the tests do it)."""

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from _gen import write_pages  # noqa: E402

project = "torchsoil"
author = "the torchsoil developers"
extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon"]
source_suffix = {".md": "markdown"}
exclude_patterns = ["_build", "bench", "diagnosis_example/report.md"]
myst_enable_extensions = ["colon_fence", "dollarmath"]
myst_heading_anchors = 3
html_theme = "furo"
html_title = "torchsoil"
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": False}
suppress_warnings = ["myst.header"]
write_pages(HERE / "reference")
