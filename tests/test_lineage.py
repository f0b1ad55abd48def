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
    signature come from one survey, each file's header read once, not once per staleness check."""
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


def _agrees_with_the_files(survey) -> None:
    """`survey` answers what a survey made now, which reads every file afresh, answers."""
    from boostnerf_cli.lineage import Survey

    fresh = Survey(survey.ws)
    assert survey.models == fresh.models
    assert survey.manifest() == fresh.manifest()
    for name in ("geometry", *fresh.models):
        assert survey.digest(name) == fresh.digest(name), name
        assert survey.stale(name) == fresh.stale(name), name
        assert (survey.finished(name) is None) == (fresh.finished(name) is None), name


@pytest.mark.slow
def test_a_survey_follows_every_stage_that_writes(mixture_ws, tmp_path):
    """One survey, asked before and after each stage writes (pretrain adds an expert, build-moe rebuilds moe/init
    from it, finetune makes top2 again, prune prunes it), answers what the files now say: every write through the
    workspace makes it read again, with nothing to call by hand."""
    import shutil

    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.recipe import recorded_recipe
    from boostnerf_cli.stages import build_moe, finetune, pretrain, prune
    from boostnerf_cli.workspace import Workspace

    ws = Workspace(shutil.copytree(mixture_ws, tmp_path / "ws"))
    rec = recorded_recipe(ws.manifest()["recipe"], ws.manifest_path)
    rec.moe.iters = 5  # as mixture_ws finetuned it
    survey = Survey(ws)
    _agrees_with_the_files(survey)
    top2 = survey.digest("top2")

    rec.pretrain.res = [8, *rec.pretrain.res]
    pretrain.run(survey, None, rec, "cpu", False)
    _agrees_with_the_files(survey)
    assert "dvgo-8" in survey.models and "dvgo-8" in survey.manifest()["experts"]

    build_moe.build(survey, None, rec.moe, "cpu")
    _agrees_with_the_files(survey)
    what, command = survey.stale("top2")
    assert "moe/init was rebuilt" in what and "--topk 2 --force" in command

    finetune.run(survey, "top2", 2, rec.moe, "cpu", True)
    _agrees_with_the_files(survey)
    assert survey.stale("top2") is None and survey.digest("top2") != top2

    prune.run(survey, "top2", "train", "cpu", 1, False)
    _agrees_with_the_files(survey)
    assert survey.finished("top2-pruned") is not None and "top2-pruned" in survey.usable()


def test_the_baseline_of_a_mixture_rebuilt_without_its_expert_is_stale(mixture_ws, tmp_path):
    """The baseline is the largest expert of moe/init's mixture, finetuned alone. Rebuilt from smaller experts, moe/init
    has another largest: the old baseline (dvgo-16's) was still evaluated, every "vs baseline" ratio taken against an
    expert the mixture no longer holds. It is stale, as the mixtures are, with the command that makes it again."""
    import shutil

    from conftest import assert_clean_failure, run_cli

    ws = shutil.copytree(mixture_ws, tmp_path / "ws")
    run_cli("finetune", "-w", str(ws), "--baseline", "--iters", "5", "--device", "cpu", check=True)
    run_cli("pretrain", "-w", str(ws), "--res", "8", "--device", "cpu", check=True)
    run_cli("build-moe", "-w", str(ws), "--experts", "dvgo-8,dvgo-12", "--device", "cpu", check=True)
    proc = run_cli("eval", "-w", str(ws), "--model", "baseline", "--device", "cpu", "--no-costs")
    assert_clean_failure(proc, "baseline is stale: moe/init was rebuilt with dvgo-12 as its largest expert after "
                         "baseline was finetuned from dvgo-16", "--baseline --force")
    # its expert stale too (retrained geometry): that is said first, since it is remade first
    from boostnerf_cli.lineage import Survey
    from boostnerf_cli.workspace import Workspace

    survey = Survey(Workspace(ws))
    survey.stale("dvgo-12")
    survey._stale["dvgo-12"] = ("the geometry was retrained after dvgo-12 was trained on it", "pretrain it")
    assert survey._why_stale("baseline") == survey._stale["dvgo-12"]

