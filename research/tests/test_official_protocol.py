"""research/recipes/official-protocol.sh: the recipes it derives are the ones asked for.

`research/recipes/official-protocol.sh` writes each variant of the official recipe (other experts, the official
V_D, a gate source, a step) with `recipe_with`, then trains on it. A variant that silently kept the official
recipe's values would train and report the wrong thing, so these tests run the script's own recipe functions
(extracted from the script, without training anything) and read back what they wrote.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from boostnerf_cli.recipe import load_recipe

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "research" / "recipes" / "official-protocol.sh"
OFFICIAL = ROOT / "recipes" / "blender-dvgo-cpu-official.yaml"


def _functions(*names: str) -> str:
    """The bash definitions of the named functions of official-protocol.sh."""
    text = SCRIPT.read_text()
    found = [re.search(rf"^{name}\(\) {{.*?^}}$", text, re.S | re.M) for name in names]
    assert all(found), f"official-protocol.sh has no function {[n for n, f in zip(names, found) if not f]}"
    return "\n".join(f.group(0) for f in found)


def _run(out: Path, calls: str) -> subprocess.CompletedProcess:
    body = f"set -euo pipefail\nOUT={out}\nOFFICIAL={OFFICIAL}\n"
    body += _functions("recipe_with", "official_vd", "variant") + "\n" + calls
    return subprocess.run(["bash", "-c", body], capture_output=True, text=True)


def _changed(recipe: dict, official: dict, prefix: str = "") -> set[str]:
    """Dotted keys whose values differ between two parsed recipes."""
    keys = set(recipe) | set(official)
    out = set()
    for k in keys:
        a, b = recipe.get(k), official.get(k)
        if isinstance(a, dict) and isinstance(b, dict) and k != "hidden":
            out |= _changed(a, b, f"{prefix}{k}.")
        elif a != b:
            out.add(prefix + k)
    return out


def test_variants_change_exactly_the_keys_asked_for(tmp_path):
    proc = _run(tmp_path, 'variant ladder "50, 64, 80" "50: 128, 64: 128, 80: 128" 50\n'
                          'recipe_with "$OUT/official-ladder.yaml" "$OUT/step.yaml" moe.step_from=smallest\n'
                          'official_vd\n'
                          'recipe_with "$OFFICIAL" "$OUT/penalty.yaml" "moe.penalty=1, 1.5, 2.23"\n')
    assert proc.returncode == 0, proc.stderr
    written = proc.stdout.split("\n")
    assert written[:4] == [f"{tmp_path}/official-ladder.yaml", f"{tmp_path}/step.yaml",
                           f"{tmp_path}/official-vd-largest-visible.yaml", f"{tmp_path}/penalty.yaml"]
    official = yaml.safe_load(OFFICIAL.read_text())

    ladder = yaml.safe_load((tmp_path / "official-ladder.yaml").read_text())
    assert _changed(ladder, official) == {"pretrain.res", "pretrain.dvgo.hidden", "moe.gate_res"}
    rec = load_recipe(tmp_path / "official-ladder.yaml")  # a valid recipe, read as boostnerf reads it
    assert rec.pretrain.res == [50, 64, 80] and rec.moe.gate_res == 50
    assert rec.pretrain.dvgo["hidden"] == {50: 128, 64: 128, 80: 128}

    step = yaml.safe_load((tmp_path / "step.yaml").read_text())
    assert _changed(step, ladder) == {"moe.step_from"}
    assert load_recipe(tmp_path / "step.yaml").moe.step_from == "smallest"

    vd = load_recipe(tmp_path / "official-vd-largest-visible.yaml")
    assert (vd.moe.vd_source, vd.moe.vd_filter) == ("largest", "visible")
    assert _changed(yaml.safe_load((tmp_path / "official-vd-largest-visible.yaml").read_text()), official) == {
        "moe.vd_source", "moe.vd_filter"}
    assert load_recipe(tmp_path / "penalty.yaml").moe.penalty == "1, 1.5, 2.23"


@pytest.mark.parametrize("family", ["tensorf", "ngp"])
def test_the_other_families_get_the_official_protocol_and_keep_their_experts_and_gate(tmp_path, family):
    """tensorf-m3 / ngp-m3: the family's CPU recipe with the official budget and mixture training; the joint rates
    are that family's own pretraining rates (the official code trains the mixture at DVGO's)."""
    proc = _run(tmp_path, f'HERE={ROOT}\n' + _functions("family_official") + f"\nfamily_official {family}\n")
    assert proc.returncode == 0, proc.stderr
    path = tmp_path / f"official-{family}-m3.yaml"
    assert proc.stdout.strip() == str(path)
    source = yaml.safe_load((ROOT / "recipes" / f"blender-{family}-cpu.yaml").read_text())
    written = yaml.safe_load(path.read_text())
    assert _changed(written, source) == {"pretrain.iters", "moe.iters", "moe.lam", "moe.aux_norm", "moe.aux_samples",
                                         "moe.mix", "moe.train.lr_grid", "moe.train.lr_mlp", "moe.train.lr_decay"}
    rec = load_recipe(path)
    assert rec.pretrain.model == family and rec.pretrain.res == source["pretrain"]["res"]
    assert (rec.pretrain.iters, rec.moe.iters, rec.moe.lam) == (1000, 5000, 0.001)
    assert (rec.moe.aux_norm, rec.moe.aux_samples, rec.moe.mix, rec.moe.gate_init) == (
        "counts", "visible", "alpha", "random")
    pre = source["pretrain"]["train"]
    assert (rec.moe.train.lr_grid, rec.moe.train.lr_mlp, rec.moe.train.lr_decay) == (pre["lr_grid"], pre["lr_mlp"], 0.1)


def test_recipe_with_refuses_a_section_the_recipe_lacks(tmp_path):
    proc = _run(tmp_path, 'recipe_with "$OFFICIAL" "$OUT/bad.yaml" pretrain.tensorf.hidden=8\n')
    assert proc.returncode != 0
    assert proc.stderr.strip().splitlines() == [
        f"recipe_with: {OFFICIAL} has no section tensorf (in pretrain.tensorf.hidden)"]
    assert not (tmp_path / "bad.yaml").exists()


def test_an_unknown_step_is_refused_with_the_steps_there_are(tmp_path):
    proc = subprocess.run(["bash", str(SCRIPT), str(tmp_path / "lego"), str(tmp_path / "out"), "no-such-step"],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.startswith("unknown step no-such-step (m3, m4, m5,") and len(proc.stderr.splitlines()) == 1


def test_every_case_the_docs_run_is_a_case_of_the_table(tmp_path):
    """The cases docs/results.md, README.md and research/README.md (where `P` stands for the script and its two
    arguments) give official-protocol.sh are cases of its table (lamX stands for lam1e-4, penalty-P for
    penalty-none, ...)."""
    proc = subprocess.run(["bash", str(SCRIPT), str(tmp_path / "lego"), str(tmp_path / "out"), "no-such-step"],
                          capture_output=True, text=True)
    listed = proc.stderr.strip().split(" (", 1)[1].rstrip(")").split(", ")
    case = re.compile("|".join(re.sub(r"X$", "[0-9].*", re.sub(r"-P$", "-.+", n)) for n in listed))
    documented = set()
    for doc in (ROOT / "docs" / "results.md", ROOT / "README.md", ROOT / "research" / "README.md"):
        for command in re.findall(r"`([^`]*)`", doc.read_text()):
            words = command.split()
            after = "OUT" if "official-protocol.sh" in command else "P"
            if after in words:
                documented |= {w for w in words[words.index(after) + 1:] if not w.isupper()}  # not CASE...
    assert len(documented) > 40 and {"lam1e-4", "px200-alone", "collect"} <= documented
    assert sorted(n for n in documented if not case.fullmatch(n)) == []


def test_the_paper_table_trains_every_column_of_each_size_in_its_own_workspace(tmp_path):
    """`paper` (docs/results.md, the paper's appendix table at CPU size): with a stand-in `boostnerf` that only
    writes down its arguments, each size gets its own workspace, its own experts and the four models."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    log = tmp_path / "calls"
    (bin_dir / "boostnerf").write_text(f'#!/bin/sh\necho "$*" >> {log}\n')
    (bin_dir / "boostnerf").chmod(0o755)
    out = tmp_path / "out"
    env = {"PATH": f"{bin_dir}:/usr/bin:/bin", "HOME": str(tmp_path)}
    env["PATH"] += ":" + os.path.dirname(sys.executable)  # the python that runs recipe_with
    proc = subprocess.run(["bash", str(SCRIPT), "LEGO", str(out), "paper"], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    calls = log.read_text().splitlines()
    recipes = {3: str(OFFICIAL), 4: f"{out}/official-m4.yaml", 5: f"{out}/official-m5.yaml"}
    expected = []
    for m, recipe in recipes.items():
        ws = f"-w {out}/paper-m{m}"
        expected += [f"pretrain {ws} --data LEGO --recipe {recipe} --device cpu",
                     f"build-moe {ws} --recipe {recipe} --device cpu",
                     *(f"finetune {ws} --recipe {recipe} {flags} --device cpu"
                       for flags in ("--baseline", "--topk 1 --no-renormalize", "--topk 2", "--ensemble")),
                     f"eval {ws} --report --device cpu"]
    assert calls == expected
    assert load_recipe(recipes[4]).pretrain.res == [64, 72, 80, 88]
    assert load_recipe(recipes[5]).pretrain.res == [56, 64, 72, 80, 88] and load_recipe(recipes[5]).moe.gate_res == 56
