"""The product suite's fixtures and helpers (tests/conftest.py, tests/helpers.py), shared with the research tests.

research/tests is a package, so this module is `research.tests.conftest` and never takes the place of the product
suite's `conftest` module that the files in tests/ import by name.
"""

from __future__ import annotations

import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parents[2] / "tests"
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))

from conftest import tiny_recipe, tiny_scene, trained_ws  # noqa: E402, F401  (fixtures, found here by pytest)
from test_cli_families import family_ws  # noqa: E402, F401  (a TensoRF and an Instant-NGP model of one box)
