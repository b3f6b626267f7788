"""Sphinx configuration of dyknow's documentation site (``make docs`` builds it into ``site/``).

Pages are Markdown (MyST-Parser), the theme is furo, the API reference is autodoc over the public
names of ``dyknow`` and of each family's package. The build runs offline with warnings as errors
and nitpicky references (``-W --keep-going -n``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import dyknow

sys.path.insert(0, str(Path(__file__).resolve().parent / "_ext"))

project = "dyknow"
author = "the dyknow authors"
copyright = "the dyknow authors, Apache-2.0"
release = dyknow.__version__
version = release

# sphinx.ext.graphviz draws the concept pages' figures with Graphviz's dot at build time (make docs
# needs it: apt-get install graphviz); SVG, so they stay sharp and their text searchable
extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.graphviz", "dyknow_docs"]
graphviz_output_format = "svg"
source_suffix = {".md": "markdown"}
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
root_doc = "index"

myst_enable_extensions = ["colon_fence", "deflist"]
myst_heading_anchors = 3  # [text](page.md#a-section) links are checked, like any other reference

html_theme = "furo"
html_title = f"dyknow {release}"
html_static_path: list[str] = []
html_show_sourcelink = False

autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_default_options = {"members": True}

nitpicky = True
# Offline there are no inventories of Python's, numpy's or Zenoh's documentation to link to, so a
# reference to a name outside dyknow is shown as text. Every reference to a dyknow name must
# resolve (see dyknow_docs.resolve_public_alias).
nitpick_ignore_regex = [(r"py:.*", r"(?!dyknow\b).*")]
