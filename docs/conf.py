"""Sphinx configuration of the sb3-mtte docs: MyST Markdown pages, the furo theme, the API by autodoc.

Build: ``python -m sphinx -W --keep-going -b html docs <out>`` (``pip install "sb3-mtte[docs]"``).
"""

from __future__ import annotations

import sb3_mtte

project = "sb3-mtte"
author = "sb3-mtte contributors"
copyright = "the sb3-mtte contributors, MIT License"
release = sb3_mtte.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx_copybutton",
]

source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = [
    "_build",
    "records/**",
    "results/**",
    "figures/*.md",
    "figures/*.json",
    "*.json",
]

# MyST: anchors for headings down to level 3, so ``page.md#a-heading`` links resolve.
myst_heading_anchors = 3
myst_enable_extensions = ["colon_fence"]

# autodoc: the package's docstrings are reST with SB3's ``:param x:`` fields.
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_preserve_defaults = True
autodoc_typehints_description_target = "documented_params"
autodoc_default_options = {"exclude-members": "__init__, __new__"}
napoleon_google_docstring = False
napoleon_numpy_docstring = False
napoleon_use_rtype = False

html_theme = "furo"
html_title = f"sb3-mtte {release}"
html_static_path: list[str] = []
copybutton_prompt_text = r"\$ "
copybutton_prompt_is_regexp = True
