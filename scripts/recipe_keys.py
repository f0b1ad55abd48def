"""Write docs/recipe-keys.md: every recipe key, its default, its allowed values and what it does.

Made from the code, so it cannot fall behind it: the keys and defaults from the recipe dataclasses
(`boostnerf_cli/recipe.py`) and the families' configs (`fields/dvgo.py`, `tensorf.py`, `ngp.py`), the allowed
values from each field's rule (`limits.limit`), the text from the comment on the field's line (or the comment
lines just above it). A key without such a comment stops the script: a new key gets its sentence where it is
declared. `--check` compares instead of writing (tests/test_docs.py runs it).

    python scripts/recipe_keys.py [--check]
"""

from __future__ import annotations

import dataclasses
import inspect
import io
import sys
import tokenize
import typing
from pathlib import Path

from boostnerf_cli.fields.registry import CONFIGS
from boostnerf_cli.limits import Range, rule_of
from boostnerf_cli.recipe import Recipe

OUT = Path(__file__).resolve().parents[1] / "docs" / "recipe-keys.md"

HEAD = """# Recipe keys

Every key a recipe accepts, generated from the code by `python scripts/recipe_keys.py` (a test checks that this
page is in step with it). A recipe sets any of them; a key it leaves out keeps the default below, and a command-line
flag overrides both (docs/recipes.md). Values out of the allowed range are refused in one line before anything runs.

"""

FAMILY_NOTE = """A family section (`pretrain.dvgo`, `pretrain.tensorf`, `pretrain.ngp`) sets the \
architecture of that family's
experts. Each value is one value for every expert, or a mapping from resolution to value, one per expert
(`hidden: {64: 64, 96: 128}`; a resolution it does not list takes the nearest listed one's). The resolutions
themselves are `pretrain.res` (for `ngp`, the number of levels L).
"""


def comments(cls: type) -> dict[str, str]:
    """{field name: its comment} in the source of the class that declares it (`cls` or a base, as the moe section
    extends `moe.mixture.Routing`): the comment on the field's line, else the comment lines just above it."""
    found: dict[str, str] = {}
    for klass in reversed([c for c in cls.__mro__ if dataclasses.is_dataclass(c)]):
        found.update(_own_comments(klass))
    return found


def _own_comments(cls: type) -> dict[str, str]:
    source = inspect.getsource(cls)
    lines = source.splitlines()
    trailing: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            trailing[tok.start[0]] = tok.string.lstrip("#").strip()
    found: dict[str, str] = {}
    for name in (f.name for f in dataclasses.fields(cls)):
        row = next((i for i, line in enumerate(lines, 1) if line.strip().startswith(f"{name}:")), None)
        if row is None:
            continue
        if row in trailing:  # a comment on the field's own line
            found[name] = trailing[row]
            continue
        above, i = [], row - 1
        while i >= 1 and lines[i - 1].strip().startswith("#"):
            above.insert(0, trailing[i])
            i -= 1
        if above:
            found[name] = " ".join(above)
    return found


def _default(value: typing.Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    return str(value)


def _allowed(f: dataclasses.Field, hint: typing.Any) -> str:
    rule = rule_of(f)
    text = str(rule) if rule is not None else ""
    if rule == Range():
        text = "numbers"
    if hint is bool:
        text = "true or false"
    elif hint is str and not text:
        text = "text"
    if typing.get_origin(hint) is list or "list" in str(hint):
        text = "a list of numbers" if text == "numbers" else f"a list, each {text}" if text else "a list"
    if "None" in str(hint):
        text = f"{text}, or none" if text else "none"
    return text


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def rows(cls: type, default: typing.Any, where: str) -> list[tuple[str, str, str, str]]:
    """(key, default, allowed, what) for every field of `cls` under `where`, sections after their parents' keys."""
    hints = typing.get_type_hints(cls)
    text = comments(cls)
    out, later = [], []
    for f in dataclasses.fields(cls):
        path = f"{where}.{f.name}" if where else f.name
        value = getattr(default, f.name)
        if dataclasses.is_dataclass(value):
            later.append((type(value), value, path))
            continue
        if f.name in CONFIGS and hints[f.name] is dict:
            later.append((CONFIGS[f.name], CONFIGS[f.name](), path))
            continue
        if f.name == "res" and cls in CONFIGS.values():
            continue  # the resolutions are pretrain.res
        if f.name not in text:
            raise SystemExit(f"{cls.__module__}.{cls.__name__}.{f.name} has no comment to describe it: add one on "
                             "its line")
        out.append((path, _default(value), _allowed(f, hints[f.name]), text[f.name]))
    for section_cls, value, path in later:
        out += rows(section_cls, value, path)
    return out


def page() -> str:
    table = rows(Recipe, Recipe(), "")
    parts = [HEAD]
    by_section: dict[str, list] = {}
    for row in table:
        section = row[0].rsplit(".", 1)[0] if "." in row[0] else "(top level)"
        by_section.setdefault(section, []).append(row)
    for section, items in by_section.items():
        parts.append(f"## `{section}`\n\n" if section != "(top level)" else "## Top level\n\n")
        if section == f"pretrain.{next(iter(CONFIGS))}":  # before the first family's section
            parts.append(FAMILY_NOTE + "\n")
        parts.append("| key | default | allowed | what it does |\n|---|---|---|---|\n")
        for key, default, allowed, what in items:
            parts.append(f"| `{key}` | {_cell(default)} | {_cell(allowed)} | {_cell(what)} |\n")
        parts.append("\n")
    return "".join(parts).rstrip() + "\n"


def main(argv: list[str]) -> int:
    text = page()
    if "--check" in argv:
        if not OUT.exists() or OUT.read_text() != text:
            print(f"{OUT} is not in step with the code: run python scripts/recipe_keys.py", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text)
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
