"""Sphinx configuration of lungmech's documentation (``make docs``).

Pages are MyST Markdown; the API reference is generated from the docstrings by sphinx-autoapi,
which reads the sources without importing them (no MPI or DOLFINx needed to build it). Warnings
are errors (``make docs`` runs ``sphinx-build -W``).
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

project = "lungmech"
author = "the lungmech developers"
release = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
copyright = "2026, the lungmech developers"

# sphinx-mathjax-offline copies MathJax 3 into the site: pages render their formulas without a
# network (the browser check runs offline), as a downloaded copy of the site must
extensions = [
    "myst_nb",  # MyST Markdown, and the demos as executed notebooks
    "autoapi.extension",
    "sphinx.ext.mathjax",
    "sphinx-mathjax-offline",
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",
]
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store", "conf.py", "check_site.py"]

# The demos (demos/*.py, jupytext's percent format) are pages: copied to docs/demos/ and
# executed by myst-nb through jupyter-cache. tests/test_demos.py executes them into the same
# cache (docs/_build/.jupyter_cache), so a CI run executes each demo once, and a page's
# numbers ({glue:text}) are the ones the tests checked. The cache keys a notebook by its code
# cells: editing a demo's prose does not run it again.
nb_custom_formats = {".py": ["jupytext.reads", {"fmt": "py:percent"}]}
nb_execution_mode = "cache"
nb_execution_cache_path = str(ROOT / "docs" / "_build" / ".jupyter_cache")
nb_execution_in_temp = True
nb_execution_timeout = 1800
nb_execution_raise_on_error = True
nb_execution_show_tb = True
nb_merge_streams = True

myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

autoapi_type = "python"
autoapi_dirs = [str(ROOT / "lungmech")]
autoapi_root = "api"
autoapi_add_toctree_entry = False
autoapi_options = ["members", "show-inheritance"]  # no summary tables: the book theme pushes their text out of view
autoapi_keep_files = False
autoapi_python_class_content = "both"  # the class's docstring and its __init__'s
# lungmech's modules import one another in cycles autoapi's static resolver cannot follow; the
# names still resolve through the modules that define them
suppress_warnings = ["autoapi.python_import_resolution"]


def measured_results() -> None:
    """A page for every committed benchmark result (``benchmarks/results/<name>.md``, its quick
    case's left out) and one for the benchmarks' own README, each including the file as it is:
    the reports link them, and they are never copied by hand."""
    folder = ROOT / "docs" / "reports" / "results"
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.md"):
        old.unlink()
    sources = [ROOT / "benchmarks" / "README.md"] + sorted(
        p for p in (ROOT / "benchmarks" / "results").glob("*.md") if not p.stem.endswith("_quick")
    )
    for source in sources:
        name = "benchmarks" if source.name == "README.md" else source.stem
        relative = Path("../" * 3) / source.relative_to(ROOT)
        (folder / f"{name}.md").write_text(f"```{{include}} {relative.as_posix()}\n:heading-offset: 0\n```\n")


measured_results()


def demo_pages() -> None:
    """Copy every demo into docs/demos/ (a page is a file of the source folder), only where it
    changed, so Sphinx rebuilds only the pages whose demo did."""
    folder = ROOT / "docs" / "demos"
    demos = {p.name: p for p in (ROOT / "demos").glob("*.py")}
    for old in folder.glob("*.py"):
        if old.name not in demos:
            old.unlink()
    for name, demo in demos.items():
        copy = folder / name
        if not copy.is_file() or copy.read_bytes() != demo.read_bytes():
            copy.write_bytes(demo.read_bytes())


demo_pages()

html_theme = "sphinx_book_theme"
html_title = f"lungmech {release}"
html_theme_options = {"show_toc_level": 2, "use_download_button": False}
html_context = {"default_mode": "light"}  # the theme logs an error for a page without a mode
html_static_path = ["_static"]
html_css_files = ["wide.css"]


def bars_are_not_substitutions(app, what, name, obj, options, lines: list[str]) -> None:
    """lungmech's docstrings write |x| for an absolute value or a cardinality, which
    reStructuredText would read as a substitution: escape every | outside math and literals."""
    math_indent = None  # the indentation of the ``.. math::`` directive being read
    for index, line in enumerate(lines):
        stripped = line.lstrip()
        indent = len(line) - len(stripped)
        if math_indent is not None and stripped and indent <= math_indent:
            math_indent = None
        if stripped.startswith(".. math::"):
            math_indent = indent
            continue
        if math_indent is not None or "|" not in line:
            continue
        parts = re.split(r"(``.*?``|:math:`[^`]*`)", line)
        lines[index] = "".join(p if p.startswith(("``", ":math:")) else p.replace("|", r"\|") for p in parts)


def setup(app) -> None:
    app.connect("autodoc-process-docstring", bars_are_not_substitutions)
