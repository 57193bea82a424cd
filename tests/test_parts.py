"""The part head F_part (:mod:`crfedit.parts`): its loss in closed form, the labelled points it
trains on, what training with part maps learns, and where selections and edits read it."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from crfedit.config import PRESETS, Config, make_config
from crfedit.data.loading import load_category
from crfedit.data.synth import SynthConfig, write_synth_category
from crfedit.edit.params import trained_prefixes
from crfedit.edit.selection import ScribbleView, keep_summary, options_for, part_summary, select
from crfedit.edit.selection.classify import nearest_cosine
from crfedit.errors import CrfError
from crfedit.field import ConditionalRadianceField
from crfedit.masks import dilate, erode
from crfedit.model import load_model
from crfedit.parts import (
    labelled_instances, labelled_points, part_config, part_contrastive_loss, sample_parts,
)

from cli_helpers import invoke


def test_part_contrastive_loss_closed_form():
    """Two parts on orthogonal unit embeddings: each point's logits are 1/τ (its own centre) and
    0 (the other), so the loss is log(1 + e^(−1/τ)); a group holding one part adds exactly 0;
    labels that no point of a group has are masked, not counted as parts."""
    a, b = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    emb = torch.stack([a, a, b, b])[None]  # [G=1, P=4, D=3]
    labels = torch.tensor([[1, 1, 2, 2]])
    tau = 0.1
    expected = math.log1p(math.exp(-1.0 / tau))
    assert float(part_contrastive_loss(emb, labels, 5, tau)) == pytest.approx(expected, rel=1e-6)
    # one part in the group: softmax over one present centre is 1 → loss 0
    assert float(part_contrastive_loss(emb[:, :2], labels[:, :2], 5, tau)) == pytest.approx(0.0, abs=1e-7)
    # a worked 2-D case at 45°: centres a and (a+b)/√2, cosine 1/√2 between them
    c = F.normalize(a + b, dim=0)
    emb2 = torch.stack([a, c])[None]
    got = float(part_contrastive_loss(emb2, torch.tensor([[1, 2]]), 3, tau))
    assert got == pytest.approx(math.log1p(math.exp((1 / math.sqrt(2) - 1) / tau)), rel=1e-6)
    # mixed parts are worse than separated ones, and the gradient pulls them apart
    mixed = F.normalize(torch.stack([a, b, a, b]) + 0.1, dim=-1)[None].requires_grad_(True)
    loss = part_contrastive_loss(mixed, labels, 5, tau)
    assert float(loss.detach()) > expected and bool(torch.isfinite(torch.autograd.grad(loss, mixed)[0]).all())


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    """A 4-chair × 6-view 16² synthetic category with twins, loaded with part maps and depth."""
    root = tmp_path_factory.mktemp("parts") / "chairs"
    write_synth_category(root, SynthConfig(instances=4, views=6, res=16, seed=0, twin_sources=2))
    return load_category(root, with_depth=True, with_parts=True)


def test_labelled_points_lift_part_pixels_to_the_surface(labelled):
    """Each labelled pixel becomes the point at its depth along its ray: a chair's seat points
    lie above its legs' or base's (Z up), every label is one of the instance's parts, and
    ``not-twins`` leaves the twins' sources out."""
    every = labelled_instances(labelled, "all")
    pts = labelled_points(labelled, every, per_view=50, seed=0)
    assert pts is not None and pts.instance.tolist() == every
    assert int(pts.counts.sum()) == len(pts.points) == len(pts.labels) and int(pts.counts.max()) <= 50 * 4
    assert pts.offsets.tolist() == (torch.cumsum(pts.counts, 0) - pts.counts).tolist()
    box = 0.65  # synth chairs are normalized into [-0.6, 0.6]³ (a rim for the pixel footprint)
    assert float(pts.points.abs().max()) < box
    for i, k in enumerate(every):
        inst = labelled.instances[k]
        names = {p["id"]: p["name"] for p in json.loads((inst.path / "parts.json").read_text())}
        sl = slice(int(pts.offsets[i]), int(pts.offsets[i] + pts.counts[i]))
        labels, z = pts.labels[sl], pts.points[sl, 2]
        assert set(labels.tolist()) <= set(names)
        seat = next(p for p, n in names.items() if n == "seat")
        low = [p for p, n in names.items() if n in ("legs", "base")]
        assert float(z[labels == seat].mean()) > float(z[torch.isin(labels, torch.tensor(low))].mean())
    sources = {json.loads((labelled.root / "twins.json").read_text())["twins"][0]["source"]}
    not_twins = labelled_instances(labelled, "not-twins")
    assert not sources & {labelled.instances[k].name for k in not_twins} and len(not_twins) < len(every)
    # the draw is seeded; a category loaded without depth has nothing to lift
    again = labelled_points(labelled, every, per_view=50, seed=0)
    assert torch.equal(again.points, pts.points) and torch.equal(again.labels, pts.labels)
    assert labelled_points(load_category(labelled.root, with_parts=True), every) is None


def test_part_labels_can_hold_out_named_instances(labelled):
    """``not:NAME,…`` hides the named instances' part maps (``twins``: the twins' sources), a
    name the dataset lacks is a one-line error naming it, and the grammar is checked up front."""
    names = labelled.names
    sources = {t["source"] for t in json.loads((labelled.root / "twins.json").read_text())["twins"]}
    assert len(sources) == 2
    other = next(n for n in names if n not in sources)
    assert [names[k] for k in labelled_instances(labelled, f"not:{other}")] == [n for n in names if n != other]
    both = labelled_instances(labelled, f"not:twins, {other}")
    assert {names[k] for k in both} == set(names) - sources - {other}
    assert labelled_instances(labelled, "not:twins") == labelled_instances(labelled, "not-twins")
    with pytest.raises(CrfError, match=r"has no instance 'chair_099'"):
        labelled_instances(labelled, "not:twins,chair_099")
    assert make_config("fast", sets=[f"part_labels=not:{other},twins"]).part_labels == f"not:{other},twins"
    for bad in ("not:", "not:a,,b", "none"):
        with pytest.raises(CrfError, match="part_labels"):
            make_config("fast", sets=[f"part_labels={bad}"])


def test_sample_parts_draws_within_each_instance(labelled):
    pts = labelled_points(labelled, labelled_instances(labelled, "all"), per_view=20, seed=1)
    gen = torch.Generator().manual_seed(0)
    x, inst, labels = sample_parts(pts, gen, groups=3, per_group=7)
    assert x.shape == (21, 3) and inst.shape == (21,) and labels.shape == (3, 7)
    for g in range(3):  # each group's points are points of its one instance, with their labels
        k = int(inst[7 * g])
        assert bool((inst[7 * g: 7 * g + 7] == k).all())
        i = int((pts.instance == k).nonzero())
        own = pts.points[int(pts.offsets[i]): int(pts.offsets[i] + pts.counts[i])]
        own_labels = pts.labels[int(pts.offsets[i]): int(pts.offsets[i] + pts.counts[i])]
        for p, lab in zip(x[7 * g: 7 * g + 7], labels[g]):
            hit = (own == p).all(dim=1)
            assert bool(hit.any()) and int(own_labels[hit][0]) == int(lab)


def test_part_config_and_presets(labelled, tiny_chairs):
    cfg = make_config("fast")
    assert cfg.part_dim == 16 and PRESETS["paper"].part_dim == 0
    assert part_config(labelled, cfg) == cfg
    # no part maps or no depth: no head is trained or stored
    assert part_config(load_category(tiny_chairs), cfg).part_dim == 0
    assert part_config(load_category(tiny_chairs, with_parts=True), cfg).part_dim == 0
    with pytest.raises(CrfError, match="part_labels"):
        make_config("fast", sets=["part_labels=some"])
    # a model file written before the head existed reads as having none
    old = json.loads(cfg.to_json())
    del old["part_dim"], old["part_weight"], old["part_labels"]
    assert Config.from_json(json.dumps(old)).part_dim == 0
    field = ConditionalRadianceField(make_config("fast", sets=["part_dim=0"]), 2)
    assert field.F_part is None and "F_part" not in dict(field.named_children())


def test_the_all_strategy_does_not_train_the_part_head():
    field = ConditionalRadianceField(PRESETS["fast"], 2)
    assert field.F_part is not None
    for group in ("color", "shape"):
        assert not any(p.startswith("F_part") for p in trained_prefixes(field, group, "all"))
        assert not any(p.startswith("F_part") for p in trained_prefixes(field, group, "hybrid"))


@pytest.fixture(scope="module")
def headed(trained_category):
    """(model file, model, category) trained with part maps and depth: 3 chairs at 32², 400 steps."""
    path, model, category, result = trained_category(
        "parts", SynthConfig(instances=3, views=10, res=32, seed=0, twins=False), dict(
            steps=400, rays=512, grid_res=16, occ_res=32, width=32, rad_width=32,
            occ_warmup=100, occ_every=8, checkpoint_every=10**9,
        ), with_parts=True, with_depth=True)
    assert result.train_psnr > 12, f"the fixture's training failed (PSNR {result.train_psnr:.1f})"
    return path, model, category


def test_training_with_part_maps_separates_each_instance_s_parts(headed):
    """After training, F_part's embedding of held-out labelled surface points (the test views')
    is nearest its own part's centre (taken on the train views) for most points of every
    instance: the head learned the parts, not the points it was shown.  (Trained here: 0.99–1.0;
    the same model trained with ``part_weight`` 0, its head a random projection of F_fuse:
    0.95 / 0.83 / 0.75.)"""
    _, model, category = headed
    field = model.field
    assert field.F_part is not None and model.cfg.part_dim == 16
    from crfedit.data.loading import Category

    for k, inst in enumerate(category.instances):
        train = labelled_points(Category(category.root, [inst], category.fingerprint), [0], per_view=300, seed=0)
        test_inst = type(inst)(**{**inst.__dict__, "splits": {"train": inst.splits["test"] + inst.splits["val"]}})
        test = labelled_points(Category(category.root, [test_inst], category.fingerprint), [0], per_view=300, seed=0)
        with torch.no_grad():
            e_train = field.part_embedding(field.fuse_features(field.normalize(train.points), k))
            e_test = field.part_embedding(field.fuse_features(field.normalize(test.points), k))
        ids = sorted(set(train.labels.tolist()))
        centres = F.normalize(torch.stack([e_train[train.labels == i].mean(0) for i in ids]), dim=-1)
        nearest = torch.tensor(ids)[(e_test @ centres.T).argmax(dim=1)]
        accuracy = float((nearest == test.labels).float().mean())
        assert accuracy > 0.95, f"instance {k}: held-out nearest-centre accuracy {accuracy:.2f}"


def test_the_model_file_records_whose_labels_the_head_learned(headed):
    """Training writes the instances whose part maps F_part learned into the file, and ``eval
    edits`` warns for a twin whose source is among them, as when the twins come from another
    dataset of the same chairs (``dataset synth --twin-sources``); a file written before the
    record warns only for ``part_labels=all``."""
    from types import SimpleNamespace

    from crfedit.evaluation import part_labels_seen, part_labels_warning
    from crfedit.parts import labelled_names

    path, _, category = headed
    model, _ = load_model(path)
    assert labelled_names(model.meta) == category.names  # no twins: every chair's maps
    case = lambda source: SimpleNamespace(spec=SimpleNamespace(source=source))
    warning = part_labels_warning(model, [case("chair_001"), case("chair_009")])
    assert warning is not None and "1 of the twins' sources (chair_001)" in warning
    assert part_labels_seen(model, [case("chair_001"), case("chair_009"), case("chair_001")]) == ["chair_001"]
    assert part_labels_warning(model, [case("chair_009")]) is None and part_labels_warning(model, []) is None
    old = dataclasses.replace(model, meta={k: v for k, v in model.meta.items() if k != "part_labelled"})
    assert labelled_names(old.meta) is None and part_labels_seen(old, [case("chair_001")]) is None
    assert part_labels_warning(old, [case("chair_001")]) is None
    old.field.cfg = dataclasses.replace(model.cfg, part_labels="all")  # (a fresh load: no fixture shares it)
    assert "part_labels=all" in part_labels_warning(old, [case("chair_001")])


def test_a_selection_reads_the_part_head_where_the_scribble_is_one_part(headed):
    """The seat's scribbled points agree in the head's embedding, so the selection reads it;
    told not to, or with a coherence cut above what the points reach, it does not, and says
    why in its metadata (which ``crfedit select`` and the page print)."""
    _, model, category = headed
    k = 1
    inst = category.instances[k]
    pid = next(p["id"] for p in json.loads((inst.path / "parts.json").read_text()) if p["name"] == "seat")
    view = max(inst.splits["train"], key=lambda v: int(erode(v.parts == pid, 1).sum()))
    strokes = ScribbleView(view.camera, erode(view.parts == pid, 1), (view.parts > 0) & ~dilate(view.parts == pid, 1))
    told = select(model, k, [strokes], dataclasses.replace(options_for("color"), part_head=False))
    assert "part_head" not in told.meta and part_summary(told.meta) is None
    read = select(model, k, [strokes], options_for("color"))
    info = read.meta["part_head"]
    assert "part" in read.meta["features"] and info["used"] and 0.9 <= info["coherence"] <= 1.0 + 1e-6
    assert part_summary(read.meta).startswith("read (")
    strict = select(model, k, [strokes], dataclasses.replace(options_for("color"), part_coherence=1.01))
    assert "part" not in strict.meta["features"] and not strict.meta["part_head"]["used"]
    assert part_summary(strict.meta).startswith("not read (coherence ") and "< 1.01" in part_summary(strict.meta)
    assert torch.equal(strict.values, told.values) and not torch.equal(read.values, told.values)


def test_the_part_veto_leaves_out_only_the_parts_the_keep_strokes_mark(headed):
    """A real mesh's parts are its materials, a procedural chair's its seat, back and legs, so
    the head's veto of another part of the scribble's colour is right on one and wrong on the
    other; the keep strokes say which.  Kept strokes on the rest of the chair: the veto leaves
    cells out, and only cells at least as near a keep point's embedding as the scribble's.
    Without keep strokes it leaves nothing out (the selection is the one without a veto);
    ``part_veto_keep=False`` vetoes by the cosine alone, as before."""
    _, model, category = headed
    k = 1
    inst = category.instances[k]
    pid = next(p["id"] for p in json.loads((inst.path / "parts.json").read_text()) if p["name"] == "seat")
    view = max(inst.splits["train"], key=lambda v: int(erode(v.parts == pid, 1).sum()))
    scribble, keep = erode(view.parts == pid, 1), (view.parts > 0) & ~dilate(view.parts == pid, 1)
    opts = options_for("color")
    kept = select(model, k, [ScribbleView(view.camera, scribble, keep)], opts)
    assert kept.meta["part_head"]["used"] and kept.meta["part_head"]["veto_by"] == "keep strokes"
    assert kept.meta["part_head"]["vetoed"] > 0 and "selected cells left out as parts the keep strokes mark" in part_summary(kept.meta)
    alone = ScribbleView(view.camera, scribble, None)
    bare = select(model, k, [alone], opts)
    assert bare.meta["part_head"]["vetoed"] == 0 and bare.meta["keep_points"] == 0
    assert "left out" not in part_summary(bare.meta) and "the part head leaves no other part out" in keep_summary(bare.meta)
    assert keep_summary(kept.meta) is None
    assert torch.equal(bare.values, select(model, k, [alone], dataclasses.replace(opts, part_veto=0.0)).values)
    old = select(model, k, [alone], dataclasses.replace(opts, part_veto_keep=False))
    assert old.meta["part_head"]["vetoed"] > 0 and old.meta["part_head"]["veto_by"] == "cosine"
    assert not torch.equal(old.values, bare.values)


def test_the_part_join_takes_no_cell_of_another_hue(headed):
    """``part_join_hue``: the head's join adds back no cell that the hue veto calls unlike the
    scribble.  With a veto that calls every cell but the scribbled points' own hue unlike, the
    join adds nothing the selection without a join lacks; with the test off it does."""
    _, model, category = headed
    k = 1
    inst = category.instances[k]
    pid = next(p["id"] for p in json.loads((inst.path / "parts.json").read_text()) if p["name"] == "seat")
    view = max(inst.splits["train"], key=lambda v: int(erode(v.parts == pid, 1).sum()))
    strokes = [ScribbleView(view.camera, erode(view.parts == pid, 1), (view.parts > 0) & ~dilate(view.parts == pid, 1))]
    strict = dataclasses.replace(options_for("color"), veto_chroma=1e-3, veto_floor=0.0, part_join_hue=1e-6)
    tested = select(model, k, strokes, strict)
    assert tested.meta["part_head"]["used"]
    assert torch.equal(tested.values, select(model, k, strokes, dataclasses.replace(strict, part_join=0.0)).values)
    assert not torch.equal(tested.values, select(model, k, strokes, dataclasses.replace(strict, part_join_hue=0.0)).values)
    assert options_for("color").part_join_hue == 0.3 and options_for("remove").part_join_hue == 0.0


def test_a_sure_part_head_s_join_passes_the_shape_gate(headed, monkeypatch):
    """``part_join_sure``: with a shape gate that leaves out everything a join would add, a
    head not sure enough (cut above its coherence) joins nothing (the selection is the one
    without the join, to the bit), and a sure head (cut at or below it) joins what it joins
    ungated; the metadata and the summary line say which.  Recolours are sure at
    :data:`PART_JOIN_SURE`, removals and additions never."""
    from crfedit.edit.selection import pipeline
    from crfedit.edit.selection.options import PART_JOIN_SURE

    _, model, category = headed
    k = 1
    inst = category.instances[k]
    pid = next(p["id"] for p in json.loads((inst.path / "parts.json").read_text()) if p["name"] == "seat")
    view = max(inst.splits["train"], key=lambda v: int(erode(v.parts == pid, 1).sum()))
    strokes = [ScribbleView(view.camera, erode(view.parts == pid, 1), None)]
    monkeypatch.setattr(pipeline, "gate_pieces", lambda added, odd, share: added)  # the gate leaves every added cell out
    opts = dataclasses.replace(options_for("remove"), chroma_union=0.0)
    coherence = select(model, k, strokes, opts).meta["part_head"]["coherence"]
    assert coherence >= opts.part_coherence
    unsure = select(model, k, strokes, dataclasses.replace(opts, part_join_sure=coherence + 0.01))
    sure = select(model, k, strokes, dataclasses.replace(opts, part_join_sure=coherence - 0.01))
    bare = select(model, k, strokes, dataclasses.replace(opts, part_join=0.0))
    assert unsure.meta["part_head"]["join_gated"] and not sure.meta["part_head"]["join_gated"]
    assert part_summary(sure.meta).endswith(f"; sure of the part (coherence ≥ {coherence - 0.01:g}), so the shape gate leaves its join alone")
    assert "sure of the part" not in part_summary(unsure.meta)
    assert torch.equal(unsure.values, bare.values)
    assert not torch.equal(sure.values, bare.values) and bool((sure.mask | ~bare.mask).all())
    assert options_for("color").part_join_sure == PART_JOIN_SURE > 0.9
    assert options_for("remove").part_join_sure == options_for("add").part_join_sure == 0.0


def test_nearest_cosine_is_the_greatest_cosine_with_any_point():
    g = torch.Generator().manual_seed(0)
    cells, points = F.normalize(torch.randn(50, 16, generator=g), dim=-1), F.normalize(torch.randn(7, 16, generator=g), dim=-1)
    assert torch.allclose(nearest_cosine(cells, points, chunk=8), (cells @ points.T).max(dim=1).values)
    assert torch.isneginf(nearest_cosine(cells, points[:0])).all()


def test_select_prints_whether_it_read_the_part_head(headed, tiny_model, tmp_path):
    from PIL import Image

    path, model, category = headed
    inst = category.instances[1]
    pid = next(p["id"] for p in json.loads((inst.path / "parts.json").read_text()) if p["name"] == "seat")
    index, view = max(enumerate(inst.splits["train"]), key=lambda iv: int(erode(iv[1].parts == pid, 1).sum()))
    Image.fromarray((erode(view.parts == pid, 1) * 255).astype(np.uint8)).save(tmp_path / "fg.png")
    args = ["--instance", inst.name, "--view", f"train:{index}", "--scribble", str(tmp_path / "fg.png")]
    r = invoke("select", path, *args, "--out", tmp_path / "s.safetensors")
    assert r.exit_code == 0, r.output
    assert "part head: read (the scribbled points' part embeddings agree: coherence " in r.stdout
    assert "shape gate" not in r.stdout  # a recolour's selection reads no shape
    assert "never learned" not in r.stdout  # the head learned every chair's maps here
    read = {"coherence": 0.95, "cut": 0.9, "used": True}
    assert "never learned this chair's part maps" in part_summary({"part_head": {**read, "learned": False}})
    assert all("never learned" not in part_summary({"part_head": {**read, **extra}}) for extra in ({"learned": True}, {"learned": None}, {}))
    r = invoke("select", path, *args, "--for", "remove", "--out", tmp_path / "r.safetensors")
    assert r.exit_code == 0, r.output
    assert "shape gate: " in r.stdout and ("nothing left out" in r.stdout or "out of the joins" in r.stdout)
    # a model without a head (trained without part maps) prints no such line
    assert load_model(tiny_model)[0].field.F_part is None
    Image.fromarray(np.full((16, 16), 255, np.uint8)).save(tmp_path / "all.png")
    r = invoke("select", tiny_model, "--instance", "0", "--view", "train:0", "--scribble", tmp_path / "all.png",
               "--out", tmp_path / "t.safetensors")
    assert r.exit_code == 0, r.output
    assert "wrote " in r.stdout and "part head" not in r.stdout


def test_train_says_why_a_dataset_with_part_maps_gets_no_part_head(tmp_path):
    """Two chairs, both twin sources: part_labels=not-twins leaves every part map out, and the
    fast preset's head is dropped with a note (it used to be dropped silently)."""
    write_synth_category(tmp_path / "d", SynthConfig(instances=2, views=4, res=16, seed=0, twins=True, twin_sources=2))
    r = invoke("train", tmp_path / "d", "--out", tmp_path / "m.safetensors", "--steps", 1, "--set", "rays=64", "--device", "cpu")
    assert r.exit_code == 0, r.output
    assert "note: no part head: every instance with part maps is left out by part_labels=not-twins" in r.stderr, r.stderr
    assert load_model(tmp_path / "m.safetensors")[0].cfg.part_dim == 0
    r = invoke("train", tmp_path / "d", "--out", tmp_path / "a.safetensors", "--steps", 1, "--set", "rays=64",
               "--set", "part_labels=all", "--device", "cpu")
    assert r.exit_code == 0 and "no part head" not in r.stderr and load_model(tmp_path / "a.safetensors")[0].cfg.part_dim > 0
