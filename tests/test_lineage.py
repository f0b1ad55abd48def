"""`lineage.decide`, the one rule every stage applies to what it finds where it writes: each row of its table, with
and without --force, and the reasons it gives."""

import pytest

from boostnerf_cli.errors import BoostNerfError
from boostnerf_cli.lineage import MAKE, REFUSE, REMAKE, RESUME, SKIP, Decision, Found, GeometrySpec, decide
from boostnerf_cli.recipe import GeometryRecipe

SIG = {"artifact": "expert", "model": "dvgo", "res": 12, "iters": 30, "seed": 0}
OTHER = {**SIG, "iters": 50}  # the same expert, trained for other steps
STALE = ("expert dvgo-12 was retrained after top2 was finetuned from it", "`boostnerf finetune -w ws --topk 2 --force`")

# (what is found, the signature wanted, --force) -> the action; one row per line of decide's table
RULES = [
    ("nothing there", None, SIG, False, MAKE),
    ("nothing there, --force", None, SIG, True, MAKE),
    ("a checkpoint of the same signature", Found("dvgo-12", SIG, checkpoint=True), SIG, False, RESUME),
    ("a checkpoint of the same signature, --force", Found("dvgo-12", SIG, checkpoint=True), SIG, True, RESUME),
    ("a checkpoint of another signature", Found("dvgo-12", SIG, checkpoint=True), OTHER, False, REFUSE),
    ("a checkpoint of another signature, --force", Found("dvgo-12", SIG, checkpoint=True), OTHER, True, MAKE),
    ("a finished artifact, --force", Found("dvgo-12", SIG), SIG, True, MAKE),
    ("a finished artifact of another signature, --force", Found("dvgo-12", SIG), OTHER, True, MAKE),
    ("a finished stale artifact, --force", Found("top2", SIG, STALE), SIG, True, MAKE),
    ("a finished artifact made from a changed input", Found("top2", SIG, STALE), SIG, False, REMAKE),
    ("stale comes before other settings", Found("top2", SIG, STALE), OTHER, False, REMAKE),
    ("a finished artifact of another signature", Found("dvgo-12", SIG), OTHER, False, REFUSE),
    ("a finished artifact of the same signature", Found("dvgo-12", SIG), SIG, False, SKIP),
    ("a reader asks for any signature", Found("dvgo-12", SIG), None, False, SKIP),
    ("an artifact without a signature (older files)", Found("dvgo-12", None), SIG, False, SKIP),
]


@pytest.mark.parametrize("found, wanted, force, action", [r[1:] for r in RULES], ids=[r[0] for r in RULES])
def test_decide_applies_each_rule_of_its_table(found, wanted, force, action):
    decision = decide(found, wanted, force)
    assert decision.action == action
    if action in (MAKE, SKIP, RESUME):
        assert decision.check() is decision and decision.reason == ""
    else:
        with pytest.raises(BoostNerfError) as refused:
            decision.check()
        assert str(refused.value) == decision.reason


def test_the_reasons_name_the_setting_and_the_command():
    assert decide(Found("dvgo-12", SIG), OTHER).reason == (
        "dvgo-12 was trained with other settings (pretrain.iters: 30, now 50): add --force to retrain it, or rerun "
        "with the settings it was trained with")
    assert decide(Found("dvgo-12", SIG, checkpoint=True), OTHER).reason.startswith(
        "training checkpoint dvgo-12 was written with other settings (pretrain.iters: 30, now 50): rerun with the "
        "settings it was made with to resume, add --force")
    stale = decide(Found("top2", SIG, STALE), SIG)
    assert stale == Decision(REMAKE, f"top2 is stale: {STALE[0]}; make it again with {STALE[1]}", STALE[1])


def test_a_geometry_setting_is_named_by_its_recipe_key():
    """The geometry is decided as every artifact is: a changed setting is named `pretrain.geometry.<key>`."""
    box = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
    old = GeometrySpec.of("geometry", "scene", GeometryRecipe(iters=100), 0, box).signature()
    new = GeometrySpec.of("geometry", "scene", GeometryRecipe(iters=60), 0, box).signature()
    assert decide(Found("geometry", old), old).action == SKIP
    assert "(pretrain.geometry.iters: 100, now 60): add --force to retrain it" in decide(Found("geometry", old),
                                                                                         new).reason
    moved = GeometrySpec.of("geometry", "scene", GeometryRecipe(iters=100), 5, box).signature()
    assert "(pretrain.seed: 0, now 5)" in decide(Found("geometry", old), moved).reason
