"""The rules of docs/design.md, read from the source: which packages may import which, no cycles, no private names
across modules, the maths packages free of files; and functions a reader can hold (length, parameters)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "boostnerf_cli"

# Lowest first. A module may import modules of lower layers and of its own package (a package's modules import
# each other), never a higher layer nor another package of its own layer.
LAYERS = [
    ["errors"],
    ["limits", "flops", "metrics", "workspace", "device", "startup", "adam", "cameras"],
    ["fields"],
    ["render"],
    ["moe", "scenes"],
    ["recipe", "distributed", "images"],
    ["lineage"],
    ["train", "models"],
    ["tasks", "costs", "faults"],  # faults: the tests' kill points, armed by cli.main (it wraps train's checkpoint)
    ["stages.common", "viewpoint"],  # viewpoint: one camera's picture of a model (view, render --camera)
    ["stages"],
    ["cli"],
    ["__main__"],
]
MATHS = ("fields", "moe", "render")  # modules and maths: no files, no workspace, no model I/O
BENCH_RUNS = {"pretrain", "build_moe", "finetune", "evaluate"}  # the stages `bench` drives
CHAIN_RUNS = BENCH_RUNS | {"count_params", "render"}  # the stages `chain` runs, one after another


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules(root: Path = ROOT) -> dict[str, Path]:
    return {module_name(p, root): p for p in sorted((root / "boostnerf_cli").rglob("*.py"))}


def _type_checking_only(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def imports(path: Path, root: Path = ROOT) -> list[tuple[str, list[str], int]]:
    """Every import in the file, at any depth except under `if TYPE_CHECKING:`: (module, names, line)."""
    found = []

    def visit(node: ast.AST, package: str) -> None:
        if _type_checking_only(node):
            return
        if isinstance(node, ast.Import):
            found.extend((a.name, [], node.lineno) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative import
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([node.module] if node.module else []))
            found.append((base, [a.name for a in node.names], node.lineno))
        for child in ast.iter_child_nodes(node):
            visit(child, package)

    name = module_name(path, root) if path.is_relative_to(root) else path.stem
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    visit(ast.parse(path.read_text()), package)
    return found


def own_targets(path: Path, known: dict[str, Path], root: Path = ROOT) -> list[tuple[str, int]]:
    """The boostnerf_cli modules a file imports (`from pkg import mod` counts as importing pkg.mod)."""
    out = []
    for mod, names, line in imports(path, root):
        if not mod.startswith("boostnerf_cli"):
            continue
        targets = [f"{mod}.{n}" for n in names if f"{mod}.{n}" in known] or [mod]
        out += [(t, line) for t in targets]
    return out


def layer_of(module: str) -> tuple[int, str]:
    """(layer index, the layer entry the module belongs to), most specific entry first."""
    rel = module.removeprefix("boostnerf_cli").lstrip(".")
    best = None
    for i, entries in enumerate(LAYERS):
        for entry in entries:
            if rel == entry or rel.startswith(entry + "."):
                if best is None or len(entry) > len(best[1]):
                    best = (i, entry)
    assert best is not None, f"{module} is in no layer of test_layout.LAYERS: add it"
    return best


def layer_violations(root: Path = ROOT) -> list[str]:
    known = modules(root)
    wrong = []
    for name, path in known.items():
        if name == "boostnerf_cli":
            continue
        mine, my_entry = layer_of(name)
        for target, line in own_targets(path, known, root):
            theirs, their_entry = layer_of(target) if target != "boostnerf_cli" else (-1, "")
            if target == "boostnerf_cli" or their_entry == my_entry and my_entry != "stages":
                continue  # the same package
            if my_entry == "stages" and their_entry == "stages":
                if name.endswith(".bench") and target.rsplit(".", 1)[-1] in BENCH_RUNS:
                    continue  # bench runs the pipeline's stages, by design
                if name.endswith(".chain") and target.rsplit(".", 1)[-1] in CHAIN_RUNS:
                    continue  # and so does chain
                wrong.append(f"{name}:{line} imports {target}: a stage never imports another stage")
            elif theirs >= mine:
                wrong.append(f"{name}:{line} imports {target} (layer {their_entry}, not below {my_entry})")
    return wrong


def find_cycle(root: Path = ROOT) -> list[str]:
    """One import cycle among the modules (imports at any depth), or []."""
    known = modules(root)
    graph = {name: {t for t, _ in own_targets(path, known, root) if t in known and t != name}
             for name, path in known.items()}
    graph = {n: {t for t in ts if not n.startswith(t + ".")} for n, ts in graph.items()}  # a module's own package
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str]:
        state[n] = 1
        stack.append(n)
        for t in sorted(graph[n]):
            if state.get(t) == 1:
                return stack[stack.index(t):] + [t]
            if t not in state and (cycle := visit(t)):
                return cycle
        stack.pop()
        state[n] = 2
        return []

    for n in sorted(graph):
        if n not in state and (cycle := visit(n)):
            return cycle
    return []


def private_imports(files: list[Path], root: Path = ROOT) -> list[str]:
    wrong = []
    for path in files:
        for mod, names, line in imports(path, root):
            if mod == "__future__":
                continue
            for n in names:
                if n.startswith("_") and not n.startswith("__"):
                    wrong.append(f"{path.relative_to(root)}:{line} imports {n} from {mod}")
    return wrong


def file_imports_in_maths(root: Path = ROOT) -> list[str]:
    banned = ("boostnerf_cli.workspace", "boostnerf_cli.models", "safetensors", "json", "yaml", "imageio")
    wrong = []
    for name, path in modules(root).items():
        if name.split(".")[1:2] and name.split(".")[1] in MATHS:
            for mod, _, line in imports(path, root):
                if mod in banned or mod.startswith(banned):
                    wrong.append(f"{name}:{line} imports {mod}")
    return wrong


def test_every_module_imports_only_lower_layers_or_its_own_package():
    wrong = layer_violations()
    assert not wrong, "\n".join(wrong)


def test_no_import_cycles():
    cycle = find_cycle()
    assert not cycle, "import cycle: " + " -> ".join(cycle)


def test_no_module_imports_another_modules_private_names():
    files = [*PACKAGE.rglob("*.py"), *(ROOT / "scripts").rglob("*.py"), *(ROOT / "tests").rglob("*.py")]
    wrong = private_imports(files)
    assert not wrong, "\n".join(wrong)


def test_the_maths_packages_read_and_write_no_files():
    wrong = file_imports_in_maths()
    assert not wrong, "\n".join(wrong)


def test_the_renderer_loads_without_the_expert_families_or_files():
    code = ("import sys, boostnerf_cli.render.renderer; "
            "print(sorted(m for m in sys.modules if m.startswith(('boostnerf_cli', 'safetensors'))))")
    loaded = eval(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                                 cwd=ROOT).stdout)
    assert "boostnerf_cli.render.renderer" in loaded
    for heavy in ("boostnerf_cli.fields.dvgo", "boostnerf_cli.fields.registry", "boostnerf_cli.workspace",
                  "boostnerf_cli.models", "safetensors"):
        assert heavy not in loaded, (heavy, loaded)


def test_each_command_has_one_stage_module():
    """`boostnerf X` calls into stages/X (make-scene into scenes): no command reaches into two stages."""
    tree = ast.parse((PACKAGE / "cli.py").read_text())
    wrong = []
    for fn in tree.body:
        if not isinstance(fn, ast.FunctionDef) or not fn.decorator_list:
            continue
        stages = set()
        for node in ast.walk(fn):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("boostnerf_cli.stages"):
                stages |= {f"{node.module}.{a.name}" if node.module == "boostnerf_cli.stages" else node.module
                           for a in node.names}
        stages.discard("boostnerf_cli.stages.common")
        if len(stages) > 1:
            wrong.append(f"{fn.name}: {sorted(stages)}")
    assert not wrong, wrong


def test_the_rules_see_each_kind_of_violation(tmp_path):
    """On a made-up package with one violation of each rule, every check reports it."""
    def write(rel: str, text: str) -> Path:
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
        return p

    for rel in ("boostnerf_cli/__init__.py", "boostnerf_cli/workspace.py", "boostnerf_cli/stages/__init__.py",
                "boostnerf_cli/stages/prune.py", "boostnerf_cli/scenes/__init__.py", "boostnerf_cli/scenes/blender.py"):
        write(rel, "")
    write("boostnerf_cli/fields/__init__.py", "")
    leaky = write("boostnerf_cli/fields/leaky.py", "from boostnerf_cli.workspace import save_tensors\n"
                                                    "def f():\n    from boostnerf_cli.scenes.blender import _frame\n")
    write("boostnerf_cli/stages/count_params.py", "from boostnerf_cli.stages import prune\n")
    write("boostnerf_cli/scenes/llff.py", "import boostnerf_cli.scenes.nsvf\n")
    write("boostnerf_cli/scenes/nsvf.py", "from boostnerf_cli.scenes import llff\n")
    layers = layer_violations(tmp_path)
    assert any("fields.leaky" in w and "scenes.blender" in w for w in layers), layers  # upward, inside a function
    assert any("stages.count_params" in w and "another stage" in w for w in layers), layers
    assert not any("workspace" in w for w in layers)  # a lower layer is allowed
    assert find_cycle(tmp_path) in (
        ["boostnerf_cli.scenes.llff", "boostnerf_cli.scenes.nsvf", "boostnerf_cli.scenes.llff"],
        ["boostnerf_cli.scenes.nsvf", "boostnerf_cli.scenes.llff", "boostnerf_cli.scenes.nsvf"])
    assert private_imports([leaky], tmp_path) == [
        "boostnerf_cli/fields/leaky.py:3 imports _frame from boostnerf_cli.scenes.blender"]
    assert file_imports_in_maths(tmp_path) == ["boostnerf_cli.fields.leaky:1 imports boostnerf_cli.workspace"]


def _functions():
    """(module path, function) for every function and method of boostnerf_cli."""
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield path.relative_to(PACKAGE.parent), node


def test_no_function_is_over_80_lines():
    long = [f"{path}:{f.lineno} {f.name} ({f.end_lineno - f.lineno + 1} lines)" for path, f in _functions()
            if f.end_lineno - f.lineno + 1 > 80]
    assert not long, long


def _is_command(f) -> bool:
    """A Typer command or callback of cli.py (`@app.command(...)`, `@app.callback()`): its parameters are its options,
    each declared in its signature, where Typer and a reader see them (docs/cli.md lists them)."""
    return any(ast.unparse(d).startswith(("app.command", "app.callback")) for d in f.decorator_list)


def test_at_most_five_functions_take_eight_or_more_parameters():
    """Functions other than the CLI's commands (whose parameters are their options); `self` and `cls` do not count."""
    def count(f) -> int:
        a = f.args
        names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs]
        return len(names) - (names[:1] in (["self"], ["cls"]))

    many = [f"{path} {f.name} ({count(f)})" for path, f in _functions() if count(f) >= 8 and not _is_command(f)]
    assert len(many) <= 5, many


def test_the_viewpoint_package_docstrings_name_what_exists_and_no_module_has_a_second_psnr():
    """viewpoint.py's docstring named a `scene_geometry` that did not exist, and it had its own `psnr` beside
    metrics/image.py's: each backquoted name of the viewpoint package's docstrings is a module or a name of the package
    (or of `boostnerf_cli.cameras`), and `psnr` is defined once, in metrics/image.py."""
    import importlib
    import re

    package = importlib.import_module("boostnerf_cli.viewpoint")
    parts = {p.stem: importlib.import_module(f"boostnerf_cli.viewpoint.{p.stem}")
             for p in (PACKAGE / "viewpoint").glob("*.py") if p.stem != "__init__"}
    cameras = importlib.import_module("boostnerf_cli.cameras")
    def exists(name: str) -> bool:
        """A module of the package, a module of boostnerf_cli and a name in it, or a name of the package's modules (or
        of cameras.py), each dotted part an attribute of the one before."""
        if name.removesuffix(".py") in parts:
            return True
        bits = name.removeprefix("boostnerf_cli.").split(".")
        for k in range(len(bits), 0, -1):
            try:
                obj, rest = importlib.import_module("boostnerf_cli." + ".".join(bits[:k])), bits[k:]
                break
            except ImportError:
                continue
        else:
            owner = next((m for m in (*parts.values(), cameras) if hasattr(m, bits[0])), None)
            if owner is None:
                return False
            obj, rest = getattr(owner, bits[0]), bits[1:]
        for attr in rest:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True

    for mod in (package, *parts.values()):
        for name in re.findall(r"`([A-Za-z_][\w.]*)`", mod.__doc__ or ""):
            assert exists(name), f"{mod.__name__}'s docstring names {name!r}, which does not exist"
    defined = [m for m, p in modules().items() if re.search(r"^def psnr\(", p.read_text(), re.M)]
    assert defined == ["boostnerf_cli.metrics.image"], defined
