"""The notebooks run as tests through nbmake (``--nbmake`` in pyproject.toml's addopts):
``make test`` executes the quick ones, ``make test-all`` all of them. A notebook listed
in SLOW (more than ~30 s in a fresh kernel: optimal control solves that compile for a
minute or more; the speed-vs-error study, whose solves the docs' guide and the
benchmarks run) is marked ``slow``; so is the impacts notebook (~19 s cold), whose scenes
tests/test_impacts*.py and docs/guides/impacts.md run in the default run."""

from pathlib import Path

import pytest

SLOW = {"01_falling_cat.ipynb", "02_spherical_robot.ipynb", "03_your_own_system.ipynb", "04_speed_vs_error.ipynb",
        "05_impacts.ipynb"}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if Path(str(item.fspath)).name in SLOW:
            item.add_marker(pytest.mark.slow)
