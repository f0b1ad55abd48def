"""The docs stay in step with the CLI."""

import re
from pathlib import Path

import typer

from boostnerf_cli.cli import app

DOCS = Path(__file__).parent.parent / "docs"


def _commands():
    group = typer.main.get_command(app)
    return group.commands


def test_cli_reference_lists_every_command_and_option():
    text = (DOCS / "cli.md").read_text()
    for name, cmd in _commands().items():
        assert f"## `boostnerf {name}`" in text, name
        section = text.split(f"## `boostnerf {name}`", 1)[1].split("\n## ", 1)[0]
        for param in cmd.params:
            for opt in param.opts + param.secondary_opts:
                if opt.startswith("-"):
                    assert opt in section, f"{name}: {opt} missing from docs/cli.md (regenerate it)"


def test_stage_guide_mentions_every_command():
    text = (DOCS / "stages.md").read_text()
    for name in _commands():
        assert f"boostnerf {name}" in text, name


def test_readme_has_exactly_two_setup_commands():
    readme = (Path(__file__).parent.parent / "README.md").read_text()
    blocks = readme.split("## Set-up and run", 1)[1].split("\n## ", 1)[0].split("```bash")[1:]
    commands = [b.split("```")[0].strip() for b in blocks]
    assert len(commands) == 2
    assert "torch==2.13.0" in commands[0] and "torch==2.13.0" in commands[1]
    ci = (Path(__file__).parent.parent / ".ci" / "run").read_text()
    assert commands[1] in ci


def test_reliability_table_lists_at_least_25_faults_each_backed_by_a_test_or_command():
    text = (DOCS / "reliability.md").read_text()
    table = text.split("## Faults and bad inputs tried", 1)[1].split("\n### ", 1)[0]
    rows = [ln for ln in table.splitlines() if ln.startswith("| ") and ln.split("|")[1].strip().isdigit()]
    assert len(rows) >= 25
    assert [int(r.split("|")[1]) for r in rows] == list(range(1, len(rows) + 1))
    tests_dir = Path(__file__).parent
    sources = "\n".join(p.read_text() for p in tests_dir.glob("test_*.py"))
    for row in rows:
        how = row.split("|")[3]
        assert "test" in how or "cmd" in how, row
        for name in re.findall(r"`(?:[\w.]+::)?(test_\w+)(?!\w|\.py)", how):  # every test named exists
            assert f"def {name}" in sources, name
