"""``crfedit eval recon | edits | ablation`` and the protocols behind them, on a tiny trained
category (2 chairs × 6 views at 16×16 with ground-truth twins, 40 training steps, once per module).

PSNR and SSIM themselves are checked against known values in tests/test_metrics.py."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest
import torch

from crfedit.ablation import ABLATION_ARCHS, PARAM_TOLERANCE, ablation_configs, matched_width, network_parameters, run_ablation
from crfedit.config import ARCHS, make_config
from crfedit.data.loading import load_category
from crfedit.data.synth import SynthConfig, write_synth_category
from crfedit.edit import EditOptions
from crfedit.errors import CrfError
from crfedit.evaluation import (
    NERF_BASELINE,
    PAPER_METHOD,
    SSIM_NOTE,
    UNEDITED,
    NerfBaseline,
    below_unedited,
    edit_tables,
    evaluate_edits,
    evaluate_recon,
    fingerprint_warning,
    held_out_split,
    load_twin_cases,
    score_model,
    strategy_problem,
)
from crfedit.field import ConditionalRadianceField
from crfedit.model import CategoryModel, load_model
from crfedit.train import train

from cli_helpers import assert_user_error, invoke

TINY = dict(steps=40, rays=256, occ_res=16, grid_res=16, checkpoint_every=10**9)


@pytest.fixture(autouse=True)
def no_lpips(monkeypatch):
    monkeypatch.delenv("CRFEDIT_LPIPS_WEIGHTS", raising=False)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("eval") / "chairs"
    write_synth_category(root, SynthConfig(instances=2, views=6, res=16))
    return root


@pytest.fixture(scope="module")
def model_path(data) -> Path:
    path = data.parent / "model.safetensors"
    train(load_category(data), make_config("fast", TINY), path, torch.device("cpu"), seed=0)
    return path


# ----------------------------------------------------------------------------- eval recon


def test_recon_prints_a_table_per_instance_with_the_metric_notes(model_path, data):
    result = invoke("eval", "recon", model_path, data, "--device", "cpu")
    assert result.exit_code == 0, result.output
    out = result.stdout
    for text in ("chair_000", "chair_001", "mean", "PSNR (dB)", "SSIM", "test split"):
        assert text in out, out
    assert "SSIM: 11×11 Gaussian window, σ=1.5, on RGB" in out
    assert "LPIPS: skipped (no weights)" in out
    assert "LPIPS " not in out.split("SSIM: 11")[0]  # no LPIPS column without weights
    # the dataset is the model's: no warning, only a progress line per instance
    assert [line.split(" (")[0] for line in result.stderr.splitlines()] == ["chair_000", "chair_001"], result.stderr
    assert "(2/2): " in result.stderr and "s left" in result.stderr


def test_recon_of_a_baked_model_says_its_edited_instances_score_as_edited(model_path, data, tmp_path):
    """A model with an edit baked in scored its edited chair against the unedited data without a
    word (a tester read 20.8 dB as a bad model, and eval edits' 'unedited' rows were the edit)."""
    edit, baked = tmp_path / "t.safetensors", tmp_path / "baked.safetensors"
    assert invoke("transfer", model_path, "--instance", 0, "--color-from", 1, "--out", edit, "--device", "cpu").exit_code == 0
    assert invoke("edits", "bake", model_path, "--edit", edit, "--out", baked).exit_code == 0
    result = invoke("eval", "recon", baked, data, "--device", "cpu")
    assert result.exit_code == 0 and "has 1 edit baked in (crfedit info lists them): the instances they edit are scored as edited" in result.stderr
    assert "baked in" not in invoke("eval", "recon", model_path, data, "--device", "cpu").stderr


def test_recon_json_is_valid_json_with_the_expected_keys(model_path, data):
    result = invoke("eval", "recon", model_path, data, "--json", "--max-views", 1, "--device", "cpu")
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert result.stderr.count(" view, PSNR ") == 2  # progress on stderr (one view each), JSON alone on stdout
    assert {"model", "data", "split", "n", "psnr", "ssim", "lpips", "lpips_note", "ssim_note", "dataset_match", "instances"} <= set(report)
    assert report["split"] == "test" and report["n"] == 2 and report["dataset_match"] is True
    assert report["lpips"] is None and "no weights" in report["lpips_note"]
    assert report["ssim_note"] == SSIM_NOTE
    assert set(report["instances"]) == {"chair_000", "chair_001"}
    for scores in report["instances"].values():
        assert set(scores) == {"n", "psnr", "ssim", "lpips"} and scores["n"] == 1
        assert 0 < scores["psnr"] < 60 and -1 <= scores["ssim"] <= 1
    mean = sum(s["psnr"] for s in report["instances"].values()) / 2
    assert report["psnr"] == pytest.approx(mean)


def test_recon_scores_match_the_library(model_path, data):
    model, _ = load_model(model_path)
    score = evaluate_recon(model, load_category(data), "test")
    cli = json.loads(invoke("eval", "recon", model_path, data, "--json", "--device", "cpu").stdout)
    assert cli["psnr"] == pytest.approx(score["psnr"]) and cli["ssim"] == pytest.approx(score["ssim"])


def test_held_out_split_prefers_a_split_any_instance_has():
    from types import SimpleNamespace as NS

    category = lambda *splits: NS(instances=[NS(splits=dict.fromkeys(s, [])) for s in splits])
    mixed = category(("train", "val"), ("train", "test"))
    assert held_out_split(mixed, "val") == "val" and held_out_split(mixed, "test") == "test"
    assert held_out_split(category(("train", "test")), "val") == "test"  # training's end score without val
    assert held_out_split(category(("train", "val"), ("train",)), "test") == "val"
    with pytest.raises(CrfError, match="expected test or val"):
        held_out_split(mixed, "train")


def test_score_model_is_the_loop_behind_evaluate_recon(model_path, data):
    model, _ = load_model(model_path)
    category = load_category(data)
    recon = evaluate_recon(model, category, "test", max_views=2)
    score = score_model(model, category, "test", max_views=2)
    assert {k: recon[k] for k in score} == score
    assert score["n"] == sum(min(2, len(inst.splits["test"])) for inst in category.instances)
    one = score_model(model, category, "test", max_views=2, instances=[1])
    assert list(one["instances"]) == ["chair_001"] and one["psnr"] == score["instances"]["chair_001"]["psnr"]
    lone = dataclasses.replace(model, names=["chair_000", "elsewhere"])
    assert list(score_model(lone, category, "test", 1)["instances"]) == ["chair_000"]  # default: the ones it holds
    with pytest.raises(CrfError, match="'elsewhere' of the model is not in the dataset"):
        score_model(lone, category, "test", 1, instances=[0, 1])
    with pytest.raises(CrfError, match="none of the model.s instances has dev views"):
        score_model(model, category, "dev")
    assert score["without_views"] == []
    category.instances[0].splits["test"] = []  # an instance without views of the split: named, not dropped in silence
    gap = score_model(model, category, "test", max_views=2)
    assert gap["without_views"] == [category.instances[0].name] and category.instances[0].name not in gap["instances"]


def test_recon_on_another_dataset_warns_or_fails_with_strict(model_path, data, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(data, other)
    (other / "instances.txt").write_text((data / "instances.txt").read_text() + "# edited\n")
    model, _ = load_model(model_path)
    assert fingerprint_warning(model, load_category(other)) is not None

    result = invoke("eval", "recon", model_path, other, "--json", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert result.stderr.startswith("warning: ") and "not the one the model was trained on" in result.stderr
    assert json.loads(result.stdout)["dataset_match"] is False  # stdout stays pure JSON

    assert_user_error(invoke("eval", "recon", model_path, other, "--strict", "--device", "cpu"), "fingerprint")


def test_recon_user_errors(model_path, data, tmp_path):
    assert_user_error(invoke("eval", "recon", model_path, data, "--max-views", 0), "--max-views 0")
    result = invoke("eval", "recon", model_path, data, "--split", "dev")
    assert result.exit_code == 2 and "'dev'" in result.stderr and "Traceback" not in result.output
    assert_user_error(invoke("eval", "recon", model_path, data, "--lpips-weights", tmp_path / "none.safetensors"), "not found")
    assert_user_error(invoke("eval", "recon", tmp_path / "missing.safetensors", data), "missing.safetensors")


def test_a_dataset_of_training_views_only_trains_without_a_held_out_score(model_path, data, tmp_path):
    scene = tmp_path / "chair"  # a NeRF-synthetic scene without val or test views, named like no model instance
    shutil.copytree(data / "chair_000", scene)
    for split in ("val", "test"):
        (scene / f"transforms_{split}.json").unlink(missing_ok=True)
    r = invoke("train", scene, "--out", tmp_path / "m.safetensors", "--steps", 2, "--set", "rays=64", "--device", "cpu")
    assert r.exit_code == 0 and "-> " in r.stdout.splitlines()[-1], r.output
    assert "note: no held-out score" in r.stderr and "error" not in r.stderr
    assert_user_error(invoke("eval", "recon", tmp_path / "m.safetensors", scene, "--device", "cpu"), "has test views in this dataset (only train)")
    r = invoke("eval", "recon", model_path, scene, "--device", "cpu")  # after the other-dataset warning
    assert r.exit_code == 2 and r.stderr.splitlines()[-1].startswith("error: none of the model's instances (chair_000, chair_001) is in"), r.output


# ----------------------------------------------------------------------------- eval edits


def test_edits_with_one_strategy_runs_end_to_end(model_path, data):
    args = ["eval", "edits", model_path, data, "--strategies", "hybrid", "--steps", 3, "--rays", 64, "--no-nerf-baseline", "--device", "cpu"]
    result = invoke(*args)
    assert result.exit_code == 0, result.output
    for text in ("Table 2 (colour edits)", "Table 3 (shape edits: removal)", "unedited", "hybrid", SSIM_NOTE, "LPIPS: skipped (no weights)"):
        assert text in result.stdout, result.stdout
    assert "chair_000_color: hybrid" in result.stderr  # progress goes to stderr
    # the NeRF's budget without the NeRF: said (it was ignored in silence)
    assert_user_error(invoke(*args, "--nerf-steps", 3), "--nerf-steps and --nerf-minutes belong to --nerf-baseline")

    report = json.loads(invoke(*args, "--json").stdout)
    assert set(report["tables"]) == {"color", "remove"}
    assert report["settings"] == {"seed": 0, "strategies": ["hybrid"], "steps": 3, "lr": 0.01, "rays": 64, "penalty": "element",
                                  "recolor": "shading", "nerf_baseline": None, "device": "cpu", "threads": torch.get_num_threads(),
                                  "world_size": 1, "lpips": False}  # what the scores depend on
    for kind, rows in report["tables"].items():
        assert [r["method"] for r in rows] == [UNEDITED, "hybrid", PAPER_METHOD]
        assert all(r["n"] == 2 and r["psnr"] is not None and r["seconds"] >= 0 for r in rows)
        assert rows[0]["seconds"] == 0.0 and rows[0]["gap_closed"] == 0.0 and rows[0]["below_unedited"] == 0
        for row in rows:  # the count agrees with the per-twin runs
            harmed = [r for r in report["runs"] if r["kind"] == kind and r["method"] == row["method"] and r["psnr"] < r["psnr_before"]]
            assert row["below_unedited"] == len(harmed)
    assert "below: twins the edit left with a lower PSNR than no edit at all" in result.stdout
    assert len(report["runs"]) == 4 * 3  # 4 twins × (unedited, hybrid, paper)
    for run in report["runs"]:  # the honest-evaluation numbers, consistent with each other
        before = next(r["psnr"] for r in report["runs"] if r["twin"] == run["twin"] and r["method"] == UNEDITED)
        assert run["psnr_before"] == before and run["psnr_ceiling"] is not None
        if run["gap_closed"] is not None:
            assert run["gap_closed"] == pytest.approx((run["psnr"] - before) / (run["psnr_ceiling"] - before))
        assert run["psnr_outside"] is not None
    assert {r["twin"] for r in report["runs"]} == {"chair_000_color", "chair_000_remove", "chair_001_color", "chair_001_remove"}


def test_edits_user_errors(model_path, data, tmp_path):
    assert_user_error(invoke("eval", "edits", model_path, data, "--strategies", "hybrid,best"), "'best'")
    assert_user_error(invoke("eval", "edits", model_path, data, "--steps", 0), "--steps 0")
    bare = tmp_path / "bare"
    shutil.copytree(data, bare)
    (bare / "twins.json").unlink()
    assert_user_error(invoke("eval", "edits", model_path, bare, "--device", "cpu"), "no ground-truth twins")


def test_edit_protocol_with_the_single_instance_nerf_baseline(model_path, data, tmp_path):
    model, _ = load_model(model_path)
    category = load_category(data)
    cases = load_twin_cases(model, category)
    assert [c.spec.kind for c in cases] == ["color", "remove", "color", "remove"]
    case = cases[0]
    assert case.scribble.shape == (16, 16) and case.scribble.any() and case.keep.any()
    assert len(case.views) == 1  # the twin's test views: the source's test poses

    report = evaluate_edits(
        model, category, cases[:1], ("codes",), EditOptions(steps=2, rays=64), NerfBaseline(steps=3),
        workdir=tmp_path,
    )
    assert [r["method"] for r in report["tables"]["color"]] == [UNEDITED, "codes", PAPER_METHOD, NERF_BASELINE]
    assert (tmp_path / "nerf_chair_000.safetensors").is_file()
    baseline, _ = load_model(tmp_path / "nerf_chair_000.safetensors")
    assert baseline.cfg.arch == "nerf" and baseline.names == ["chair_000"] and baseline.cfg.steps == 3
    assert set(report["nerf_train_seconds"]) == {"chair_000"}
    # the NeRF row's gap is the NeRF's own: its unedited render against the twin, its reconstruction of the source
    from crfedit.evaluation import render_views
    from crfedit.metrics import score_images

    own = lambda views: score_images([o.rgb.clamp(0, 1).numpy() for o in render_views(baseline, 0, [v.camera for v in views])],
                                     [v.rgb for v in views])["psnr"]
    row = next(r for r in report["runs"] if r["method"] == NERF_BASELINE)
    source_views = category.instance(case.spec.source).splits["test"][: len(case.views)]
    assert row["psnr_before"] == pytest.approx(own(case.views)) and row["psnr_ceiling"] == pytest.approx(own(source_views))
    assert row["psnr_before"] != next(r for r in report["runs"] if r["method"] == UNEDITED)["psnr"]


def test_a_strategy_the_arch_cannot_use_is_skipped_not_fatal():
    cfg = make_config("fast", {"arch": "nerf", "grid_res": 0, "occ_res": 4})
    model = CategoryModel(ConditionalRadianceField(cfg, 2), ["a", "b"])
    assert "no separate color code" in strategy_problem(model, "color", "codes")
    assert strategy_problem(model, "color", "hybrid") is None and strategy_problem(model, "remove", "all") is None


def test_a_strategy_is_skipped_only_for_the_kinds_it_cannot_edit(data):
    """arch single has one code for shape and colour: ``codes`` can edit shape (the shared code)
    but has no colour code of its own."""
    cfg = make_config("fast", {"arch": "single", "grid_res": 0, "occ_res": 8})
    model = CategoryModel(ConditionalRadianceField(cfg, 2), ["chair_000", "chair_001"])
    category = load_category(data)
    cases = load_twin_cases(model, category)[:2]
    report = evaluate_edits(model, category, cases, ("codes",), EditOptions(steps=1, rays=16), paper=False)
    assert [r["method"] for r in report["tables"]["color"]] == [UNEDITED]
    assert [r["method"] for r in report["tables"]["remove"]] == [UNEDITED, "codes"]
    assert [(e["method"], e["kind"]) for e in report["skipped"]] == [("codes", "color")]


def test_edit_tables_average_per_kind_and_method_in_order():
    runs = [
        {"kind": "color", "method": "hybrid", "psnr": 20.0, "ssim": 0.8, "lpips": None, "seconds": 1.0},
        {"kind": "color", "method": "hybrid", "psnr": 24.0, "ssim": 0.9, "lpips": None, "seconds": 3.0},
        {"kind": "color", "method": UNEDITED, "psnr": 15.0, "ssim": 0.7, "lpips": None, "seconds": 0.0},
        {"kind": "remove", "method": "all", "psnr": 18.0, "ssim": 0.6, "lpips": 0.2, "seconds": 2.0},
    ]
    tables = edit_tables(runs, [UNEDITED, "hybrid", "all"])
    assert [r["method"] for r in tables["color"]] == [UNEDITED, "hybrid"]
    hybrid = tables["color"][1]
    assert hybrid["n"] == 2 and hybrid["psnr"] == 22.0 and hybrid["ssim"] == pytest.approx(0.85) and hybrid["seconds"] == 2.0
    assert hybrid["lpips"] is None and tables["remove"][0]["lpips"] == 0.2
    assert hybrid["below_unedited"] is None  # these runs carry no psnr_before


def test_below_unedited_counts_the_twins_an_edit_harmed():
    runs = [{"psnr": 20.0, "psnr_before": 18.0}, {"psnr": 17.9, "psnr_before": 18.0}, {"psnr": 18.0, "psnr_before": 18.0}]
    assert below_unedited(runs) == 1  # equal is not below
    assert below_unedited(runs[:1]) == 0 and below_unedited([{"psnr": None, "psnr_before": 18.0}]) is None
    rows = [{"kind": "remove", "method": m, "psnr": p, "psnr_before": 18.0, "ssim": 0.5, "lpips": None, "seconds": 0.0}
            for m, p in ((UNEDITED, 18.0), ("hybrid", 17.0), ("hybrid", 19.0))]
    table = edit_tables(rows, [UNEDITED, "hybrid"])["remove"]
    assert [r["below_unedited"] for r in table] == [0, 1]


def test_the_gap_closed_averages_the_twins_whose_gap_is_defined():
    """A twin the model reconstructs no better than unedited (ceiling ≤ before) has no gap:
    None on each of its rows, left out of the mean, which says over how many it is."""
    rows = [{"kind": "color", "method": "hybrid", "psnr": 20.0, "ssim": 0.5, "lpips": None, "seconds": 0.0, "gap_closed": g}
            for g in (0.5, None, 0.9)]
    row = edit_tables(rows, ["hybrid"])["color"][0]
    assert row["gap_closed"] == pytest.approx(0.7) and row["gap_closed_n"] == 2 and row["n"] == 3
    none = edit_tables(rows[1:2], ["hybrid"])["color"][0]
    assert none["gap_closed"] is None and none["gap_closed_n"] == 0


# ----------------------------------------------------------------------------- ablation


@pytest.mark.parametrize("preset", ["fast", "paper"])
def test_matched_widths_give_parameter_counts_within_5_percent(preset):
    base = make_config(preset)
    configs = ablation_configs(base)
    assert list(configs) == list(ABLATION_ARCHS) and set(ABLATION_ARCHS) == set(ARCHS)
    target = network_parameters(configs["ours"])
    assert configs["ours"].width == base.width
    for arch, cfg in configs.items():
        assert cfg.arch == arch
        assert abs(network_parameters(cfg) / target - 1) <= PARAM_TOLERANCE, (arch, cfg.width)
    # the variants that drop modules need a wider trunk to hold as many parameters
    assert configs["separate"].width > base.width and configs["nerf"].width > configs["separate"].width


def test_matched_width_is_the_closest_width():
    base = make_config("fast")
    target = network_parameters(base)
    w = matched_width(base, "nerf", target)
    count = lambda width: abs(network_parameters(dataclasses.replace(base, arch="nerf", width=width)) - target)
    assert count(w) <= count(w - 1) and count(w) <= count(w + 1)
    assert matched_width(base, "ours") == base.width
    with pytest.raises(CrfError, match="arch 'big'"):
        matched_width(base, "big")


def test_network_parameters_leave_out_codes_and_the_feature_grid():
    cfg = make_config("fast", {"occ_res": 4})
    field = ConditionalRadianceField(cfg, 3)
    total = sum(p.numel() for p in field.parameters())
    assert network_parameters(cfg) == total - 2 * 3 * cfg.code_dim - cfg.grid_features * cfg.grid_res**3


def test_run_ablation_trains_each_arch_and_scores_held_out(data, tmp_path):
    base = make_config("fast", {k: v for k, v in TINY.items() if k != "steps"})
    rows = run_ablation(load_category(data), steps=2, base=base, archs=("nerf", "ours"), max_views=1, workdir=tmp_path)
    assert [r["arch"] for r in rows] == ["nerf", "ours"]
    for r in rows:
        assert r["steps"] == 2 and r["split"] == "test" and r["n"] == 2
        assert abs(r["params_vs_ours"] - 1) <= PARAM_TOLERANCE and r["psnr"] > 0
        trained = load_model(tmp_path / f"{r['arch']}.safetensors")[0]
        assert trained.cfg.width == r["width"]
        # the count is of the network trained (a part head training drops was counted in before)
        assert r["params"] == sum(p.numel() for n, p in trained.field.named_parameters()
                                  if n not in ("shape_codes", "color_codes") and not n.endswith(".grid"))
    with pytest.raises(CrfError, match="budget"):
        run_ablation(load_category(data))


def test_ablation_command_needs_a_budget(data):
    assert_user_error(invoke("eval", "ablation", data), "--minutes")


def test_ablation_says_lpips_is_not_computed(data, tmp_path):
    r = invoke("eval", "ablation", data, "--steps", 1, "--max-views", 1, "--device", "cpu")
    assert r.exit_code == 0, r.output
    assert "LPIPS: skipped (the ablation does not compute it;" in r.stdout
    report = json.loads(invoke("eval", "ablation", data, "--steps", 1, "--max-views", 1, "--json", "--device", "cpu").stdout)
    assert report["lpips_note"].startswith("the ablation does not compute it") and all(row["lpips"] is None for row in report["rows"])
