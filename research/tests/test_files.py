"""research/'s own files meet the product's rules: every recipe loads, every shell script parses, and no script
imports another module's private names (the product suite checks the same of recipes/, scripts/ and tests/)."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_layout import private_imports
from test_workspace import test_every_recipe_loads as recipe_loads
from test_workspace import test_every_shell_script_parses as shell_script_parses

RESEARCH = Path(__file__).resolve().parents[1]
RECIPES = sorted((RESEARCH / "recipes").glob("*.yaml"))
SHELL_SCRIPTS = sorted(RESEARCH.rglob("*.sh"))


def test_research_has_recipes_and_shell_scripts_to_check():
    assert RECIPES and SHELL_SCRIPTS


@pytest.mark.parametrize("path", RECIPES, ids=[p.name for p in RECIPES])
def test_every_research_recipe_loads(path):
    recipe_loads(path)


@pytest.mark.parametrize("script", SHELL_SCRIPTS, ids=lambda p: str(p.relative_to(RESEARCH)))
def test_every_research_shell_script_parses(script):
    shell_script_parses(script)


def test_no_research_script_imports_another_modules_private_names():
    wrong = private_imports(sorted(RESEARCH.rglob("*.py")))
    assert not wrong, "\n".join(wrong)
