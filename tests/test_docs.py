"""The docs stay in step with the CLI."""

import re
from pathlib import Path

import pytest
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


def test_the_recipe_key_reference_lists_every_key_the_code_accepts():
    """docs/recipe-keys.md is what scripts/recipe_keys.py makes of the recipe dataclasses: every key, its default,
    its allowed values and its comment (keys such as pretrain.geometry.lr and moe.gate_hidden were documented
    nowhere before it)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("recipe_keys", DOCS.parent / "scripts" / "recipe_keys.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.main(["--check"]) == 0, "run python scripts/recipe_keys.py"
    text = (DOCS / "recipe-keys.md").read_text()
    for key in ("pretrain.geometry.lr", "moe.gate_hidden", "moe.gate_channels", "moe.vd_res", "pretrain.ngp.grid_res",
                "pretrain.tensorf.fit_steps", "pretrain.dvgo.view_pe", "pretrain.seed", "moe.seed", "name"):
        assert f"| `{key}` |" in text, key


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
    assert ci_runs_every_test((Path(__file__).parent.parent / ".ci" / "run").read_text(), commands[1])


def ci_runs_every_test(ci: str, command: str) -> bool:
    """Whether the CI script `ci` ends in exactly the README's test command (nothing appended that leaves tests out:
    `-m "not slow"`, `-k`, `--deselect`, `-x`) with CI=true set, under which a missing optional part (pycolmap,
    Chromium) fails its tests instead of skipping them (tests/conftest.py, `unavailable`)."""
    lines = [ln.split(" #", 1)[0].strip() for ln in ci.splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith("#")]
    return bool(lines) and lines[-1] == command and "export CI=true" in lines


@pytest.mark.parametrize("ci", [
    "export CI=true\npython -m pip install torch==2.13.0 -e \".[test]\" && python -m pytest -m 'not slow'\n",
    "export CI=true\npython -m pip install torch==2.13.0 -e \".[test]\" && python -m pytest -k 'not chromium'\n",
    "export CI=true\npython -m pip install torch==2.13.0 -e \".[test]\" && python -m pytest\necho skipped\n",
    "python -m pip install torch==2.13.0 -e \".[test]\" && python -m pytest\n",  # CI not set: skips, not fails
], ids=["not-slow", "deselected", "not-last", "ci-unset"])
def test_a_ci_script_that_leaves_tests_out_is_refused(ci):
    command = 'python -m pip install torch==2.13.0 -e ".[test]" && python -m pytest'
    assert ci_runs_every_test(f"export CI=true\n{command}\n", command)
    assert not ci_runs_every_test(ci, command)


def test_a_missing_part_fails_under_ci_and_is_skipped_elsewhere(monkeypatch):
    from conftest import unavailable

    def outcome() -> BaseException:  # a skip is caught too: one where a failure belongs must fail this test
        try:
            unavailable("pycolmap", "pip install pycolmap")
        except BaseException as e:  # noqa: BLE001 - pytest's outcomes derive from BaseException
            return e
        raise AssertionError("unavailable returned")

    monkeypatch.setenv("CI", "true")
    failed = outcome()
    assert isinstance(failed, pytest.fail.Exception) and "missing on this CI machine" in str(failed), repr(failed)
    monkeypatch.delenv("CI")
    skipped = outcome()
    assert isinstance(skipped, pytest.skip.Exception) and "pycolmap is not installed" in str(skipped), repr(skipped)


def test_pytest_runs_every_test_by_default():
    """pyproject's addopts select no marker and no name: `python -m pytest` (CI's command) runs the slow tests too."""
    text = (Path(__file__).parent.parent / "pyproject.toml").read_text()
    addopts = re.search(r'^addopts = "([^"]*)"', text, flags=re.MULTILINE).group(1).split()
    assert not {"-m", "-k", "--deselect", "-x", "--exitfirst"} & set(addopts), addopts


TESTS = Path(__file__).parent
REF = re.compile(r"^(?:(?P<file>test_\w+\.py)(?:::)?)?(?P<name>test_\w+|\.\.\.)?"
                 r"(?P<dots>\.\.\.)?(?:\[(?P<param>.+)\])?$")


def _check_how(cell: str, earlier: set[int], previous: str | None) -> str | None:
    """One "how it is checked" cell of docs/reliability.md: clauses separated by ';', each "cmd..." (a command
    that was run) or "test" followed by tests that exist -- `file.py::test_name`, `test_name`, `test_prefix...`,
    `test_name[param]`, `...[param]` (the previous row's test with another parameter), `test_file.py` -- or
    by an earlier row's number ("test 1", "test as row 25"). Raises AssertionError; -> the last test named."""
    clauses = [c.strip() for c in re.split(r";(?=(?:[^`]*`[^`]*`)*[^`]*$)", cell) if c.strip()]  # ; outside `code`
    assert clauses, f"empty cell: {cell!r}"
    for clause in clauses:
        if re.match(r"cmd\b", clause):
            assert len(clause) > len("cmd: x"), f"a command clause names no command: {clause!r}"
            continue
        assert re.match(r"test\b", clause), f"neither a test nor a command: {clause!r}"
        row = re.match(r"test (?:as row )?(\d+)\b", clause)
        if row:
            assert int(row.group(1)) in earlier, f"{clause!r} points at a row that is not an earlier one"
        named = 0
        for token in re.findall(r"`([^`]+)`", clause):
            m = REF.match(token)
            if not m or not (m["file"] or m["name"]):
                continue  # not a test reference (e.g. a function the test calls)
            file, name = m["file"], m["name"]
            if name == "...":
                assert previous and m["param"], f"{token!r} needs a test named in the row before"
                name = previous
            sources = [TESTS / file] if file else sorted(TESTS.glob("test_*.py"))
            assert all(f.exists() for f in sources), f"{file} does not exist"
            text = "\n".join(f.read_text() for f in sources)
            if name:
                assert re.search(rf"def {name}{'' if m['dots'] else '[(]'}", text), f"no test {name} ({token!r})"
                previous = name
            for param in (m["param"] or "").split(","):
                assert param.strip() in text, f"{token!r}: parameter {param.strip()!r} not in the tests"
            named += 1
        assert named or row, f"a test clause that names no test: {clause!r}"
    return previous


def test_reliability_tables_list_at_least_25_situations_each_backed_by_a_test_or_command():
    """docs/reliability.md, "What happens when something goes wrong?": one table per kind of situation, the rows
    numbered on through them all, each row's "how it is checked" naming a test that exists or a command."""
    text = (DOCS / "reliability.md").read_text()
    tables = text.split("## What happens when something goes wrong?", 1)[1].split("\n### The commands", 1)[0]
    rows = [ln for ln in tables.splitlines() if ln.startswith("| ") and ln.split("|")[1].strip().isdigit()]
    assert len(rows) >= 25
    assert [int(r.split("|")[1]) for r in rows] == list(range(1, len(rows) + 1))
    earlier, previous = set(), None
    for row in rows:
        cells = row.split("|")
        assert len(cells) == 7, row  # | # | when | what you see | what is kept | how it is checked |
        try:
            previous = _check_how(cells[5], earlier, previous)
        except AssertionError as e:
            raise AssertionError(f"docs/reliability.md row {cells[1].strip()}: {e}") from None
        earlier.add(int(cells[1]))


@pytest.mark.parametrize("cell", [
    "we ran the tests",  # the word "test" is no evidence
    "test of the resume path",  # a test clause naming no test
    "test `test_no_such_test_anywhere`",
    "test `test_cli.py::test_unknown_recipe`",  # a prefix without "..." must be the whole name
    "test `test_moe.py::test_unknown_recipe_key`",  # exists, but in another file
    "test 7",  # not an earlier row
    "test `test_faults.py::test_interrupt_stops_cleanly_and_the_rerun_resumes[SIGQUIT]`",
    "cmd",
])
def test_the_reliability_table_check_rejects_rows_without_evidence(cell):
    with pytest.raises(AssertionError):
        _check_how(cell, {1, 2}, None)


def test_cli_reference_is_the_help_as_printed_now():
    """docs/cli.md showed --holdout-every's help of an older release (the check above reads option
    names only): each command's section is now compared with its `--help`, as scripts/cli-reference.sh writes it."""
    from conftest import run_cli

    text = (DOCS / "cli.md").read_text()
    for name in ["", *_commands()]:  # "": `boostnerf --help`, the options of every command (-q, -v)
        heading = f"## `boostnerf {name}`" if name else "## `boostnerf`: options of every command"
        section = text.split(heading, 1)[1].split("```", 2)[1].strip("\n")
        proc = run_cli(*([name] if name else []), "--help", env_extra={"COLUMNS": "100"}, check=True)
        printed = "\n".join(line.rstrip() for line in (proc.stdout + proc.stderr).splitlines()).strip("\n")
        assert printed == section, f"boostnerf {name} --help differs from docs/cli.md: run scripts/cli-reference.sh"


ROOT = DOCS.parent
MANUAL = [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]

# words of a lab notebook: the docs say how things are and how they were measured; what changed and when is in
# CHANGELOG.md
HISTORY_WORDS = ["before:", "earlier figures", "older code", "old code", "today's", "that day", "(fixed)",
                 "newcomer", "on code before", "has changed since", "changed since this run", "since that run",
                 "fixes got", "before them", "earlier recipe", "earlier chains", "a loaded machine", "used to be",
                 "not made yet", "not measured yet", "not run yet", "not run on a gpu yet",
                 "| old ", "new / old", "before then", "replace them", "now recipe keys"]


def test_the_manual_speaks_in_the_present_tense():
    found = [f"{md.name}:{n}: {word!r}" for md in MANUAL for n, line in enumerate(md.read_text().splitlines(), 1)
             for word in HISTORY_WORDS if word in line.lower()]
    assert not found, "history belongs in CHANGELOG.md:\n" + "\n".join(found)
    changelog = (ROOT / "CHANGELOG.md").read_text()
    versions = re.findall(r"^## \[([^\]]+)\]", changelog, flags=re.M)
    assert versions and versions[0] == "Unreleased", "Keep a Changelog: newest first, [Unreleased] on top"


def test_the_history_check_catches_a_lab_notebook_line():
    line = "The figures below replace earlier figures taken on older code."
    assert [w for w in HISTORY_WORDS if w in line.lower()] == ["earlier figures", "older code"]


_PATH = re.compile(r"(?<![\w/.-])((?:research/recipes|recipes|research|scripts|tests)/[\w.{},/-]+?\.(?:yaml|sh|py))\b")
_RECIPE_NAME = re.compile(r"`([\w.{},-]+\.yaml)`")


def _expand(name: str) -> list[str]:
    """`blender-{dvgo,tensorf}-cpu.yaml` -> both names (one brace group at a time)."""
    m = re.search(r"\{([^{}]*)\}", name)
    if not m:
        return [name]
    return [n for part in m[1].split(",") for n in _expand(name[:m.start()] + part + name[m.end():])]


def _code(text: str) -> list[str]:
    """Every code span and code block line of a markdown text, continuation lines joined."""
    blocks = re.findall(r"^```[a-z]*\n(.*?)^```", text, flags=re.S | re.M)
    lines = [ln for b in blocks for ln in re.sub(r"\s*\\\n\s*", " ", b).splitlines()]
    prose = re.sub(r"^```[a-z]*\n.*?^```", "", text, flags=re.S | re.M)
    return lines + [" ".join(span.split()) for span in re.findall(r"`([^`]+)`", prose)]


def _named_files(text: str) -> set[str]:
    names = {n for m in _PATH.findall(text) for n in _expand(m)}
    for m in _RECIPE_NAME.findall(text):
        for n in _expand(m):
            if "/" not in n:
                names.add(n)
    return names


def _exists(name: str) -> bool:
    if "/" in name:
        return (ROOT / name).exists()
    return any((ROOT / d / name).exists() for d in ("recipes", "research/recipes"))


def _options(line: str) -> list[tuple[str, str]]:
    """(command, option) for each `boostnerf COMMAND ... --option` of a line, up to a comment or the next command."""
    found = []
    for m in re.finditer(r"boostnerf(?:\s+-[qv])?\s+([a-z][\w-]*)((?:\s+[^\s#|;&,()]+)*)", line):
        found += [(m[1], o.split("=")[0]) for o in re.findall(r"(?<!\S)(--?[a-z][\w-]*)", m[2])]
    return found


def test_every_file_command_and_option_the_manual_names_exists():
    commands = _commands()
    missing = []
    for md in MANUAL:
        text = md.read_text()
        missing += [f"{md.name}: {n}" for n in sorted(_named_files(text)) if not _exists(n)]
        for line in _code(text):
            for cmd, opt in _options(line):
                if cmd not in commands:
                    if re.match(rf"\s*boostnerf\s+{cmd}\b", line):
                        missing.append(f"{md.name}: boostnerf {cmd}")
                    continue
                opts = {o for p in commands[cmd].params for o in p.opts + p.secondary_opts} | {"--help"}
                if opt not in opts and opt not in {"-q", "-v", "--version"}:
                    missing.append(f"{md.name}: boostnerf {cmd} {opt}")
            for script, args in re.findall(r"python3? (scripts/[\w-]+\.py|research/[\w-]+\.py)([^#]*)", line):
                source = (ROOT / script).read_text() if (ROOT / script).exists() else ""
                missing += [f"{md.name}: {script} {o}" for o in re.findall(r"(?<!\S)(--[a-z][\w-]*)", args)
                            if o not in source]
    assert not missing, "the manual names what does not exist:\n" + "\n".join(sorted(set(missing)))


def test_the_name_check_catches_what_does_not_exist():
    text = "`recipes/blender-F-cpu.yaml`, `tiny.yaml` and `blender-{dvgo,ngp}-cpu.yaml`; `boostnerf eval --no-such`"
    assert sorted(n for n in _named_files(text) if not _exists(n)) == ["recipes/blender-F-cpu.yaml", "tiny.yaml"]
    assert ("eval", "--no-such") in _options(_code(text)[-1])


def _numbers(cell: str) -> list[str]:
    cell = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", cell)  # a link's target is no figure
    cell = re.sub(r"`[^`]*`", "", cell)
    cell = re.sub(r"(?:M|L) = \d+|\d+(?:\^3| px|-expert|-step)|dvgo-\d+|ngp-\d+|tensorf-\d+|NeRF 360", "", cell)
    return re.findall(r"(?<![\w.])\d[\d,]*(?:\.\d+)?", cell)


def _data_values() -> tuple[str, list[float]]:
    text = "\n".join(p.read_text() for p in sorted((DOCS / "data").glob("*.json")))
    return text, [float(v.replace(",", "")) for v in re.findall(r"\d[\d,]*(?:\.\d+)?", text)]


def test_every_number_in_the_readme_tables_is_in_docs_data():
    """A README table is generated by scripts/tables.py (tests/test_tables.py checks it is current) and each of its
    figures is a value of docs/data, as written or rounded; its ratios and differences are computed from them."""
    readme = (ROOT / "README.md").read_text()
    text, values = _data_values()
    marked = " ".join(m.group(0) for m in re.finditer(r"<!-- table: [\w.-]+ -->\n.*?<!-- /table -->", readme, re.S))
    missing = []
    for line in readme.splitlines():
        if not line.startswith("|") or set(line) <= set("|-: "):
            continue
        for cell in line.strip("|").split("|"):
            for number in _numbers(cell):
                if line not in marked:
                    missing.append(f"not generated: {line[:60]}")
                    break
                digits = len(number.split(".")[1]) if "." in number else 0
                value = float(number.replace(",", ""))
                derived = re.search(rf"[+-]{re.escape(number)}|{re.escape(number)}x|\({re.escape(number)}x\)", cell)
                if derived or number in text:
                    continue
                if not any(abs(round(v, digits) - value) < 1e-9 or abs(round(v / 60, digits) - value) < 1e-9
                           for v in values):  # as written, rounded, or seconds as minutes
                    missing.append(f"{number} in {line[:60]}")
    assert not missing, "README tables with figures docs/data does not hold:\n" + "\n".join(missing)


def _choice_lists(text: str) -> list[tuple[str, set[str]]]:
    """Every `--option a|b|c` of the manual's synopses (code lines and spans that start with `boostnerf`): the option
    and the values it lists."""
    return [(opt, set(values.split("|"))) for line in _code(text) if line.lstrip().startswith("boostnerf ")
            for opt, values in re.findall(r"(--[a-z][\w-]*)[ =]\[?([\w-]+(?:\|[\w-]+)+)", line)]


def test_every_synopsis_lists_every_value_of_its_option():
    """A synopsis that lists an option's values lists them all (`--format ...|colmap`, `--rig ...|unbounded`)."""
    from boostnerf_cli.scenes import FORMATS
    from boostnerf_cli.scenes.procedural import CONTENTS, LENSES, RIGS

    complete = {"--format": set(FORMATS), "--rig": set(RIGS), "--content": set(CONTENTS), "--lens": set(LENSES)}
    short = []
    for md in MANUAL:
        for opt, values in _choice_lists(md.read_text()):
            if opt in complete and complete[opt] - values - {"auto"}:
                short.append(f"{md.name}: {opt} leaves out {sorted(complete[opt] - values)}")
    assert not short, "\n".join(short)
    assert ("--rig", {"sphere", "forward"}) in _choice_lists("`boostnerf make-scene X --rig sphere|forward`")
