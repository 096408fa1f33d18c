"""Sphinx configuration: MyST Markdown, laid out as rosdoc2 builds a ROS 2 Python package
(docs/ beside package.xml, index.md at its top).

    sphinx-build -W --keep-going docs docs/_build/html

The reference pages of docs/reference/generated/ are written by docs/generate.py when the build
starts (from the CLI parser, the nodes' parameter specs and the block registry) and are not
kept in git.
"""
from __future__ import annotations

import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
sys.path.insert(0, str(DOCS))

import generate  # noqa: E402  (docs/generate.py, beside this file)

project = "perception_config"
author = "perception_config developers"
copyright = "2026, perception_config developers"
release = "0.1.0"

extensions = ["myst_parser"]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]
myst_heading_anchors = 3
html_theme = "alabaster"
html_static_path: list[str] = []
language = "en"

generate.write_reference(DOCS / "reference" / "generated")
