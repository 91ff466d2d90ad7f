"""Sphinx configuration: the Markdown docs (MyST) and the library's API reference (autodoc + napoleon).

Built by ``make docs`` (warnings are errors), as rosdoc2 would build a ROS package's docs.
"""

project = "gsrmr"
author = "gsrmr developers"
extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon"]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
# The source is the repository root, so that README.md's and CHANGELOG.md's links resolve as on a Git host.
root_doc = "docs/index"
include_patterns = ["README.md", "CHANGELOG.md", "docs/*.md"]
myst_heading_anchors = 4  # `page.md#a-heading` links, as GitHub renders them
myst_enable_extensions = ["dollarmath"]
autodoc_member_order = "bysource"
autodoc_typehints = "description"
napoleon_google_docstring = True
napoleon_numpy_docstring = False
html_theme = "alabaster"
