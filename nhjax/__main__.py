"""``python -m nhjax``: the ``nhjax`` command line (see ``nhjax.cli``)."""

from .cli import main

raise SystemExit(main())
