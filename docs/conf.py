"""Sphinx configuration of pporpe's documentation site (``make docs``).

The pages are MyST Markdown, so the Markdown files under ``docs/`` read the same on a code
host and in the site; the API reference is generated from the docstrings by autodoc and
autosummary into ``docs/_autosummary/`` (not committed). The build runs with warnings as
errors (``-W --keep-going``): a broken link between pages, a missing image or include, or a
malformed docstring fails it. Only the network-free parts of Sphinx are used (no
intersphinx).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Any

DOCS = Path(__file__).resolve().parent
sys.path.insert(0, str(DOCS.parent / "src"))

import pporpe  # noqa: E402

project = "pporpe"
author = "pporpe developers"
copyright = "2026, pporpe developers"
release = version = pporpe.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
templates_path = ["_templates"]
exclude_patterns = ["_build", "_templates"]
OPTIONAL_PAGES = ["testbed"]
"""Pages that another change may add: listed in the index's toctree only while they exist,
so that the build neither misses them nor warns about their absence."""

myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

autosummary_generate = True
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_class_signature = "separated"
napoleon_google_docstring = True
napoleon_numpy_docstring = False

# A few docstrings write the absolute values |A| and |rho - 1| in plain text, which
# reStructuredText reads as substitutions; these definitions print them as written.
rst_prolog = """
.. |A| unicode:: U+7C A U+7C
.. |rho - 1| unicode:: U+7C rho U+20 - U+20 1 U+7C
"""
# Short names in docstrings (`updates`, `stats`) that match attributes of several classes or
# modules: Sphinx links the first; without nitpicky mode an unresolved Python name is not a
# warning either, so this keeps only the Markdown links and includes checked strictly.
suppress_warnings = ["ref.python"]

html_theme = "furo"
html_title = f"pporpe {release}"
html_static_path: list[str] = []


def _fix_docstring(
    app: Any, what: str, name: str, obj: Any, options: Any, lines: list[str]
) -> None:
    """Two plain-text habits of the docstrings that reStructuredText would misread, fixed
    after napoleon: ``**kwargs`` in a ``:param:`` line (an unclosed strong emphasis) and an
    ``(a)``/``(b)`` enumeration whose items wrap without indentation."""
    for i, line in enumerate(lines):
        line = re.sub(r"^(:param\s+)\*\*", r"\1\\*\\*", line)
        lines[i] = re.sub(r"^(\s*)\(([a-z])\) ", r"\1\\(\2) ", line)


def _optional_pages(app: Any, docname: str, source: list[str]) -> None:
    """Drop the index's toctree entries of :data:`OPTIONAL_PAGES` that do not exist."""
    if docname != "index":
        return
    for page in OPTIONAL_PAGES:
        if not (DOCS / f"{page}.md").exists():
            source[0] = re.sub(rf"^{page}\n", "", source[0], flags=re.M)


def setup(app: Any) -> None:
    app.connect("autodoc-process-docstring", _fix_docstring, priority=600)
    app.connect("source-read", _optional_pages)
