"""The experiments shipped with nhjax: scripts run by ``nhjax run <name>``.

Each ``*.py`` here (not starting with ``_``) is one experiment with a docstring and a
``__main__`` block taking ``--out`` (default: a folder named for the experiment under
the working directory). The repository keeps this folder at its top level; an install
(editable or not) puts it under nhjax's namespace as the package ``nhjax.experiments``
(pyproject.toml maps it there), so ``nhjax run cat_holonomy`` is
``python -m nhjax.experiments.cat_holonomy`` and nothing named ``experiments`` lands
in site-packages.
"""
