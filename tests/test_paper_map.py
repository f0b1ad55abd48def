"""docs/paper-map.md names only functions that exist."""

import importlib
import re
from pathlib import Path

MAP = Path(__file__).parent.parent / "docs" / "paper-map.md"
REF = re.compile(r"`([\w/]+)\.py: ([\w., ]+)`")


def references() -> list[tuple[str, str]]:
    refs = []
    for module, names in REF.findall(MAP.read_text()):
        refs += [(module, name.strip()) for name in names.split(",") if name.strip()]
    return refs


def test_every_function_the_paper_map_names_exists():
    refs = references()
    assert len(refs) >= 40  # the map is read, not silently empty
    missing = []
    for module, name in refs:
        obj = importlib.import_module("boostnerf_cli." + module.replace("/", "."))
        for part in name.split("."):
            obj = getattr(obj, part, None)
            if obj is None:
                missing.append(f"{module}.py: {name}")
                break
    assert not missing, f"docs/paper-map.md names code that does not exist: {missing}"


def test_the_reference_pattern_catches_a_rename():
    assert REF.findall("`moe/router.py: top_k, Mixture.route`") == [("moe/router", "top_k, Mixture.route")]
