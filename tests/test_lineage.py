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


# --- the survey: a command reads its workspace once ----------------------------------------------------------------
def _counting_reads(monkeypatch) -> dict:
    """Count every header `lineage` reads, by file name."""
    import boostnerf_cli.lineage as lineage

    reads: dict = {}
    real = lineage.read_meta

    def counted(path):
        reads[path.name] = reads.get(path.name, 0) + 1
        return real(path)

    monkeypatch.setattr(lineage, "read_meta", counted)
    return reads


def test_finetune_reads_each_header_once(mixture_ws, tmp_path, monkeypatch):
    """A finished top2 asked for again: moe/init's staleness, the routing, the source digest and the finished model's
    signature come from one survey, each file's header read once (a finetune once read moe/init's up to three
    times, through three separate staleness checks)."""
    import shutil

    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.recipe import recorded_recipe
    from boostnerf_cli.stages import finetune
    from boostnerf_cli.workspace import Workspace

    ws = Workspace(shutil.copytree(mixture_ws, tmp_path / "ws"))
    rec = recorded_recipe(ws.manifest()["recipe"], ws.manifest_path)
    rec.moe.iters = 5  # as mixture_ws finetuned it
    reads = _counting_reads(monkeypatch)
    survey = Survey(ws)
    unused, _ = finetune.unused_settings(survey, "top2", 2, rec.moe, {"moe.lam"})
    report = finetune.run(survey, "top2", 2, rec.moe, "cpu", False)  # finished: skipped
    assert report["name"] == "top2" and unused == []
    assert reads and max(reads.values()) == 1, reads
    assert {"init.safetensors", "top2.safetensors"} <= set(reads), reads


def test_a_survey_is_told_what_its_command_wrote(mixture_ws, tmp_path):
    """Staleness follows what the command itself writes: after `wrote`, the new header is read and what was made
    from the old one is stale."""
    import shutil

    import safetensors.torch as st

    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.workspace import Workspace, read_meta, save_tensors

    ws = Workspace(shutil.copytree(mixture_ws, tmp_path / "ws"))
    survey = Survey(ws)
    assert survey.stale("top2") is None and survey.usable() == survey.models
    tensors = st.load_file(ws.model_path("init"))
    meta = read_meta(ws.model_path("init"))
    save_tensors(ws.model_path("init"), {k: v + 1 if v.is_floating_point() else v for k, v in tensors.items()},
                 {k: v for k, v in meta.items() if k != "digest"})
    assert survey.stale("top2") is None  # what it read at the start
    survey.wrote("init")
    what, command = survey.stale("top2")
    assert "moe/init was rebuilt" in what and "--topk 2 --force" in command
    with pytest.raises(BoostNerfError, match="top2 is stale"):
        survey.current(["top2"])
