"""Procedural chairs: exact ray casting, shading, normalization, determinism, edit twins."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from crfedit.cameras import Camera, focal_from_angle, look_at
from crfedit.data import dataset_info, load_category, load_twins, read_mask
from crfedit.data.format import box_filter
from crfedit.data.loading import category_fingerprint
from crfedit.masks import dilate
from crfedit.data.raycast import LIGHT, box, camera_rays, cylinder, primitive_bounds
from crfedit.data.synth import (
    Chair,
    Part,
    SynthConfig,
    make_chair,
    render_chair,
    split_counts,
    twin_sources,
    write_synth_category,
)

from cli_helpers import assert_user_error, invoke

RES = 17  # odd: the center pixel's ray is the optical axis
CENTER = RES // 2


def head_on(eye) -> Camera:
    return Camera(look_at(eye), focal_from_angle(0.6911, RES), RES, RES)


def one_part(*prims) -> Chair:
    return Chair(tuple(prims), (Part(1, "a", "#ff8000"), Part(2, "b", "#0080ff")))


def test_box_head_on_exact_depth_and_shading():
    frame = render_chair(one_part(box((0, 0, 0), (0.2, 0.2, 0.2), 1)), head_on((0, -2, 0)))
    assert abs(frame.depth[CENTER, CENTER] - 1.8) < 1e-5
    assert frame.parts[CENTER, CENTER] == 1 and frame.rgba[CENTER, CENTER, 3] == 1
    # the face y = -0.2 has normal (0, -1, 0): rgb = albedo * (0.35 + 0.65 max(0, -L_y))
    expected = np.array([1.0, 128 / 255, 0.0]) * (0.35 + 0.65 * max(0.0, -LIGHT[1]))
    np.testing.assert_allclose(frame.rgba[CENTER, CENTER, :3], expected, atol=1e-6)
    # every hit pixel lies on the plane y = -0.2: t * d_y = 1.8
    _, d = camera_rays(head_on((0, -2, 0)))
    hit = frame.parts.ravel() == 1
    np.testing.assert_allclose(frame.depth.ravel()[hit] * d[hit, 1], 1.8, atol=1e-5)
    # a corner ray misses: background
    assert frame.depth[0, 0] == np.inf and frame.parts[0, 0] == 0 and frame.rgba[0, 0, 3] == 0
    np.testing.assert_array_equal(frame.rgba[0, 0, :3], 1.0)


def test_antialiased_alpha_is_pixel_coverage():
    """aa×aa supersamples, box-filtered: a box seen head on covers (2·f·0.19/1.81)² pixels, to
    within the 3×3 grid's quantization (≤ 1/6 px per edge pixel, so ≤ perimeter/6 in all)."""
    chair = one_part(box((0, 0, 0), (0.19, 0.19, 0.19), 1))
    cam = Camera(look_at((0, -2, 0)), focal_from_angle(0.6911, 64), 64, 64)
    sharp, smooth = render_chair(chair, cam, aa=1), render_chair(chair, cam, aa=3)
    side = 2 * cam.focal * 0.19 / 1.81
    alpha = smooth.rgba[..., 3]
    assert abs(alpha.sum() - side**2) <= 4 * side / 6
    assert set(np.unique(np.round(alpha * 9, 4))) <= set(range(10))  # multiples of 1/9
    assert ((alpha > 0) & (alpha < 1)).sum() > 0
    np.testing.assert_array_equal(sharp.rgba[..., 3] > 0, sharp.parts > 0)
    # depth and parts come from the center ray, whatever the supersampling
    np.testing.assert_array_equal(smooth.depth, sharp.depth)
    np.testing.assert_array_equal(smooth.parts, sharp.parts)
    # an edge pixel composited on white is the coverage-weighted mix of face colour and white
    j, i = np.argwhere((alpha > 0) & (alpha < 1))[0]
    face = sharp.rgba[32, 32, :3]
    np.testing.assert_allclose(smooth.rgba[j, i, :3] * alpha[j, i] + 1 - alpha[j, i], face * alpha[j, i] + 1 - alpha[j, i], atol=1e-6)


def test_box_filter_closed_form():
    rgb = np.array([[[0.2, 0.4, 0.6], [0.0, 0.0, 0.0]], [[1.0, 1.0, 1.0], [0.5, 0.5, 0.5]]])  # [S=2, N=2, 3]
    hit = np.array([[True, False], [False, False]])
    rgba = box_filter(rgb, hit)
    np.testing.assert_allclose(rgba, [[0.2, 0.4, 0.6, 0.5], [1.0, 1.0, 1.0, 0.0]])


@pytest.mark.parametrize(
    "prim, eye, depth",
    [
        (cylinder((0, 0, 0), 0.25, 0.3, 1), (2, 0, 0), 1.75),  # vertical, side
        (cylinder((0, 0, 0), 0.25, 0.3, 1), (0, 0, 2), 1.7),  # vertical, top cap
        (cylinder((0, 0, 0), 0.25, 0.3, 1, horizontal_yaw=0.0), (0, -2, 0), 1.75),  # along x, side
        (cylinder((0, 0, 0), 0.25, 0.3, 1, horizontal_yaw=0.0), (2, 0, 0), 1.7),  # along x, end cap
        (box((0, 0, 0), (0.1, 0.3, 0.2), 1, yaw=math.pi / 4), (2, 0, 0), 2 - 0.1 * math.sqrt(2)),  # rotated box: enters through the x-face
    ],
)
def test_exact_depth_at_center_pixel(prim, eye, depth):
    frame = render_chair(one_part(prim), head_on(eye))
    assert abs(frame.depth[CENTER, CENTER] - depth) < 1e-5 and frame.parts[CENTER, CENTER] == 1


def test_nearest_hit_wins_and_part_ids():
    chair = one_part(box((0, 0, 0), (0.3, 0.3, 0.3), 1), cylinder((0, -0.5, 0), 0.1, 0.1, 2))
    frame = render_chair(chair, head_on((0, -2, 0)))
    assert frame.parts[CENTER, CENTER] == 2 and abs(frame.depth[CENTER, CENTER] - 1.4) < 1e-5
    assert set(np.unique(frame.parts)) == {0, 1, 2}


@pytest.mark.parametrize("seed", range(6))
def test_chairs_are_normalized_and_upright(seed):
    chair = make_chair(np.random.default_rng(seed), arms=seed % 2 == 0)
    lo = np.min([primitive_bounds(p)[0] for p in chair.primitives], axis=0)
    hi = np.max([primitive_bounds(p)[1] for p in chair.primitives], axis=0)
    np.testing.assert_allclose(lo + hi, 0.0, atol=1e-12)
    assert abs((hi - lo).max() - 1.0) < 1e-12 and (hi - lo)[2] > 0.6  # taller than flat
    names = [p.name for p in chair.parts]
    assert {"seat", "back"} <= set(names) and ("legs" in names or "base" in names)
    assert ("arms" in names) == (seed % 2 == 0)
    assert [p.id for p in chair.parts] == list(range(1, len(names) + 1))


def test_split_counts():
    assert split_counts(50) == (40, 5, 5) and split_counts(3) == (1, 1, 1) and split_counts(2) == (2, 0, 0)
    assert split_counts(20) == (16, 2, 2)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth") / "chairs"
    write_synth_category(root, SynthConfig(instances=2, views=6, res=32, seed=3))
    return root


@pytest.fixture(scope="module")
def synth_aliased(tmp_path_factory):
    """One ray per pixel center: every pixel's colour belongs to the part its center hits."""
    root = tmp_path_factory.mktemp("synth1") / "chairs"
    write_synth_category(root, SynthConfig(instances=2, views=6, res=32, seed=3, aa=1))
    return root


def test_synth_is_deterministic(synth, tmp_path):
    write_synth_category(tmp_path / "again", SynthConfig(instances=2, views=6, res=32, seed=3))
    assert _files(synth) == _files(tmp_path / "again")
    write_synth_category(tmp_path / "other", SynthConfig(instances=2, views=6, res=32, seed=4))
    assert _files(synth) != _files(tmp_path / "other")


def test_synth_layout_and_info(synth):
    cat = load_category(synth, with_depth=True, with_parts=True)
    assert cat.names == ["chair_000", "chair_001"]
    assert {s: len(v) for s, v in cat.instances[0].splits.items()} == {"train": 4, "val": 1, "test": 1}
    view = cat.instances[0].splits["train"][0]
    assert view.rgb.shape == (32, 32, 3) and view.parts.dtype == np.uint8
    assert math.isclose(view.camera.camera_angle_x, 0.6911) and math.isclose(np.linalg.norm(view.camera.center), 2.0)
    assert (view.alpha[view.parts > 0] > 0).all()  # the center ray is one of the 3×3 samples
    assert ((view.alpha > 0) & (view.alpha < 1)).any()  # antialiased edges
    np.testing.assert_array_equal(np.isfinite(view.depth), view.parts > 0)
    info = dataset_info(cat)
    assert info["bbox"]["source"] == "depth" and info["twins"] == 4
    assert all(-0.5 - 1e-4 <= x <= 0.5 + 1e-4 for x in info["bbox"]["min"] + info["bbox"]["max"])


def test_twins(synth_aliased):
    synth = synth_aliased
    cat = load_category(synth, with_parts=True)
    twins = load_twins(synth)
    assert sorted((s.source, s.kind) for s, _ in twins) == [(n, k) for n in cat.names for k in ("color", "remove")]
    for spec, twin in twins:
        source = cat.instance(spec.source)
        part_id = next(p["id"] for p in json.loads((source.path / "parts.json").read_text()) if p["name"] == spec.part)
        scribbled = source.view(spec.view)
        fg, keep = read_mask(synth / spec.scribble), read_mask(synth / spec.keep)
        part = scribbled.parts == part_id
        assert fg.any() and keep.any()
        assert not (fg & ~part).any()  # foreground strictly inside the part
        assert not (keep & dilate(part, 1)).any()  # keep strokes away from it
        assert spec.view.startswith("train:")
        if spec.kind == "color":
            assert spec.part in ("seat", "back") and spec.color.startswith("#")
        else:
            assert spec.part == "arms" and spec.color is None
        for src_view, twin_view in zip(source.splits["test"], twin.splits["test"]):
            np.testing.assert_array_equal(src_view.camera.c2w, twin_view.camera.c2w)
            changed = np.abs(src_view.rgb - twin_view.rgb).max(-1) > 0
            assert changed.any() or not (src_view.parts == part_id).any()
            assert not (changed & (src_view.parts != part_id)).any()  # differs only where the part was


def test_cli_synth(tmp_path):
    result = invoke("dataset", "synth", tmp_path / "d", "--instances", "1", "--views", "3", "--res", "16")
    assert result.exit_code == 0, result.output
    assert "wrote 1 chairs" in result.stdout and (tmp_path / "d" / "twins.json").is_file()
    assert assert_user_error(invoke("dataset", "synth", tmp_path / "e", "--views", "2")).startswith("error: --views 2")
    (tmp_path / "f").mkdir()
    (tmp_path / "f" / "keep.txt").write_text("x")
    assert_user_error(invoke("dataset", "synth", tmp_path / "f", "--no-twins"), "not empty")


def test_more_twin_sources_only_add_twins(tmp_path):
    assert twin_sources(24) == [0, 6, 12, 18] and twin_sources(24, 8) == [0, 3, 6, 9, 12, 15, 18, 21]
    for n in (1, 3, 5, 7, 10):
        for count in (4, 5, 6, 9):
            got = twin_sources(n, count)
            assert set(twin_sources(n)) <= set(got) and len(got) == min(count, n) == len(set(got))
    small = dict(instances=6, views=3, res=12, aa=1)
    base, more = write_synth_category(tmp_path / "a", SynthConfig(**small)), write_synth_category(
        tmp_path / "b", SynthConfig(**small, twin_sources=6))
    assert {t.name for t in base.twins} < {t.name for t in more.twins}
    assert category_fingerprint(tmp_path / "a", base.names) == category_fingerprint(tmp_path / "b", more.names)
    for t in base.twins:  # the default twins, scribbles included, come out byte-identical
        for f in sorted((tmp_path / "a" / t.folder).rglob("*")):
            if f.is_file():
                assert f.read_bytes() == (tmp_path / "b" / f.relative_to(tmp_path / "a")).read_bytes(), f
    bad = invoke("dataset", "synth", tmp_path / "c", "--twin-sources", "0")  # Typer's range check (main() makes it one line)
    assert bad.exit_code == 2 and "'--twin-sources'" in bad.output and "Traceback" not in bad.output
