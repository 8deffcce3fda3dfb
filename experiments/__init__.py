"""The experiments shipped with nhjax: scripts run by ``nhjax run <name>``.

Each ``*.py`` here (not starting with ``_``) is one experiment with a docstring
and a ``__main__`` block. The folder is installed as the package ``experiments``
and registered in the entry-point group ``nhjax.experiments`` (pyproject.toml),
which is how ``nhjax list`` finds the scripts in an installed package; see
``nhjax.cli`` for where their outputs go.
"""
