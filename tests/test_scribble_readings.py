"""Scribble images are read the way people draw them (issue 18): white on black, alpha, coloured
strokes on a transparent PNG, or strokes painted over the render of the view; a scribble over
more than half the view is refused unless --force."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from crfedit.masks import strokes_mask
from crfedit.edit.scribble import check_coverage, load_mask, read_scribble
from crfedit.errors import CrfError
from crfedit.io import write_png
from crfedit.model import load_model
from crfedit.renderer import render_camera

from cli_helpers import invoke

PAINT = np.array([1.0, 0.0, 1.0])  # magenta: far from the chairs' colours and the white background


@pytest.fixture(scope="module")
def view(tiny_model):
    """(model, camera of train view 0 of instance 0, its render [H, W, 3] as written to PNG, strokes mask)."""
    model, _ = load_model(tiny_model)
    camera = model.views["train"].cameras(0)[0]
    render = render_camera(model.field_for(0), camera, 0).rgb.clamp(0, 1).numpy()
    render = np.round(render * 255) / 255  # what `crfedit render` writes
    mask = strokes_mask((camera.height, camera.width), [np.array([[4.0, 5.0], [11.0, 9.0]])], 1.5)
    assert 0 < mask.sum() < 0.3 * mask.size
    assert (np.abs(render[mask] - PAINT).max(axis=-1) > 0.2).all()  # the strokes are visible on the render
    return model, camera, render, mask


def read(path: Path, view, with_render: bool = True):
    _, camera, render, _ = view
    return read_scribble(path, camera.width, camera.height, "scribble", (lambda: render) if with_render else None)


def test_white_on_black(view, tmp_path):
    mask = view[3]
    write_png(tmp_path / "m.png", mask.astype(np.uint8) * 255)
    got = read(tmp_path / "m.png", view, with_render=False)
    assert got.reading == "white on black" and np.array_equal(got.mask, mask)


def test_an_all_black_image_reads_as_no_stroke(view, tmp_path):
    """It read as "grey strokes on black, 0 pixels" (there are none to be grey)."""
    _, cam, _, _ = view
    write_png(tmp_path / "black.png", np.zeros((cam.height, cam.width), np.uint8))
    got = read_scribble(tmp_path / "black.png", cam.width, cam.height, "copy")
    assert got.reading == "an all-black image: no stroke" and not got.mask.any()


def test_strokes_mask_measures_each_segment_in_its_box_alone():
    """The same bits as every segment measured over the whole view (the arithmetic the
    generator's twin scribbles and recorded digests were made with), for random strokes and
    radii; a back-and-forth line of 20 000 points (the page's request limit) draws as its one
    segment."""
    def whole_view(shape, strokes, radius):
        yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
        pix = np.stack([xx, yy], -1).astype(np.float64)
        mask = np.zeros(shape, bool)
        for points in strokes:
            for a, b in list(zip(points[:-1], points[1:])) or [(points[0], points[0])]:
                ab = b - a
                s = np.clip(((pix - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
                mask |= np.linalg.norm(pix - (a + s[..., None] * ab), axis=-1) <= radius
        return mask

    rng = np.random.default_rng(0)
    for _ in range(400):
        h, w = (int(v) for v in rng.integers(4, 48, 2))
        radius = float(rng.choice([0.5, 1.0, 4 / 3, 2.5, rng.uniform(0.3, 6.0)]))
        strokes = [rng.uniform(-8, max(h, w) + 8, (int(rng.integers(1, 6)), 2)) for _ in range(int(rng.integers(1, 3)))]
        strokes = [np.round(p * 2) / 2 if rng.random() < 0.5 else p for p in strokes]
        assert np.array_equal(strokes_mask((h, w), strokes, radius), whole_view((h, w), strokes, radius))
    line = np.array([[0.0, 0.0], [63.0, 63.0]] * 10000)
    assert np.array_equal(strokes_mask((64, 64), [line], 1.0), whole_view((64, 64), [line[:3]], 1.0))


def test_a_0_1_mask_saved_unscaled_reads_its_ones(view, tmp_path):
    """numpy's bool mask saved as uint8 without * 255 (pixels 0 and 1) read as an empty mask
    ("white on black, 0 pixels"); its ones are the strokes.  A float image is refused."""
    from PIL import Image

    mask = view[3]
    Image.fromarray(mask.astype(np.uint8)).save(tmp_path / "m01.png")
    got = read(tmp_path / "m01.png", view, with_render=False)
    assert got.reading.startswith("0/1 values") and np.array_equal(got.mask, mask)
    rgba = np.zeros((*mask.shape, 4), np.uint8)
    rgba[..., 0], rgba[..., 3] = 255, mask  # the same 0/1 mask as the alpha channel
    Image.fromarray(rgba).save(tmp_path / "a01.png")
    got = read(tmp_path / "a01.png", view, with_render=False)
    assert got.reading.startswith("0/1 alpha values") and np.array_equal(got.mask, mask)
    Image.fromarray(np.where(mask, 2, 0).astype(np.uint8)).save(tmp_path / "dim.png")  # a dim stroke is no 0/1 mask
    assert not read(tmp_path / "dim.png", view, with_render=False).mask.any()
    Image.fromarray(mask.astype(np.float32), "F").save(tmp_path / "m.tiff")
    with pytest.raises(CrfError, match=r"m\.tiff: image mode F \(32-bit float\) is not supported"):
        read(tmp_path / "m.tiff", view, with_render=False)


def test_alpha_mask(view, tmp_path):
    mask = view[3]
    rgba = np.zeros(mask.shape + (4,), np.uint8)
    rgba[..., :3] = 255
    rgba[..., 3] = mask * 255
    write_png(tmp_path / "a.png", rgba)
    got = read(tmp_path / "a.png", view, with_render=False)
    assert got.reading.startswith("opaque pixels") and np.array_equal(got.mask, mask)


def test_coloured_strokes_on_a_transparent_png(view, tmp_path):
    """Red strokes on transparency were refused as empty (their gray level is below 128)."""
    mask = view[3]
    rgba = np.zeros(mask.shape + (4,), np.uint8)
    rgba[mask] = (255, 0, 0, 255)
    write_png(tmp_path / "red.png", rgba)
    got = read(tmp_path / "red.png", view, with_render=False)
    assert got.reading.startswith("opaque pixels") and np.array_equal(got.mask, mask)


def test_coloured_strokes_on_black(view, tmp_path):
    """Red strokes on black (the README's scribble colour on a mask's ground) were refused; a
    softened edge below half brightness is not a stroke, as white on black reads it."""
    mask = view[3]
    rgb = np.zeros(mask.shape + (3,), np.uint8)
    rgb[mask] = (255, 0, 0)
    edge = np.roll(mask, 1, axis=1) & ~mask
    rgb[edge] = (90, 0, 0)
    write_png(tmp_path / "rb.png", rgb)
    got = read(tmp_path / "rb.png", view, with_render=False)
    assert got.reading == "coloured strokes on black" and np.array_equal(got.mask, mask | edge)  # every non-black pixel
    dark = np.zeros(mask.shape + (3,), np.uint8)
    dark[mask] = (0, 100, 0)  # CSS darkgreen: 0.39, read as no stroke when strokes needed half brightness
    write_png(tmp_path / "dg.png", dark)
    assert np.array_equal(read(tmp_path / "dg.png", view, with_render=False).mask, mask)
    # red and blue in one image: the scribble and the keep strokes of the README's pictures, refused as one mask
    both = rgb.copy()
    both[np.roll(mask, 3, axis=0) & ~mask & ~edge] = (0, 0, 255)
    write_png(tmp_path / "both.png", both)
    with pytest.raises(CrfError, match=r"both\.png: the scribble holds strokes of two colours \(red and blue\)"):
        read(tmp_path / "both.png", view, with_render=False)
    # whatever the ground (transparent here), and whichever two hues (red and yellow; a few blue pixels)
    rgba = np.zeros(mask.shape + (4,), np.uint8)
    rgba[mask] = (255, 0, 0, 255)
    rgba[np.roll(mask, 3, axis=0) & ~mask] = (255, 255, 0, 255)
    write_png(tmp_path / "ry.png", rgba)
    with pytest.raises(CrfError, match=r"two colours \(red and yellow\)"):
        read(tmp_path / "ry.png", view, with_render=False)
    few = rgb.copy()
    ys, xs = np.nonzero(np.roll(mask, 3, axis=0) & ~mask & ~edge)
    k = max(1, int(0.08 * (mask | edge).sum()))  # 7 % of the strokes blue slipped through a 10 % rule
    few[ys[:k], xs[:k]] = (0, 0, 255)
    write_png(tmp_path / "few.png", few)
    with pytest.raises(CrfError, match=r"two colours \(red and blue\)"):
        read(tmp_path / "few.png", view, with_render=False)
    grey = np.zeros(mask.shape + (3,), np.uint8)
    grey[mask] = 100  # a dark grey brush: strokes, as a dark coloured one is
    write_png(tmp_path / "grey.png", grey)
    got = read(tmp_path / "grey.png", view, with_render=False)
    assert got.reading == "grey strokes on black" and np.array_equal(got.mask, mask)


def test_strokes_painted_over_the_render(view, tmp_path):
    """The strokes, not the white background: the old reading counted ~84 % of the pixels."""
    _, _, render, mask = view
    painted = render.copy()
    painted[mask] = PAINT
    write_png(tmp_path / "p.png", painted)
    got = read(tmp_path / "p.png", view)
    assert got.reading.startswith("strokes painted over the render") and np.array_equal(got.mask, mask)
    with pytest.raises(CrfError, match="cannot tell the scribble strokes from the background"):
        read(tmp_path / "p.png", view, with_render=False)


def test_strokes_painted_over_another_render_keep_the_brush_colour(view, tmp_path):
    """A stroke painted over a render the model does not make (an edited stack given without its
    --edit, the dataset's own image) differs from the render there too: every such pixel was
    read as scribbled.  The brush's flat colour stands out among them: its pixels are the
    strokes, and the line says how many others were left out."""
    _, _, render, mask = view
    other = render.copy()
    region = np.zeros_like(mask)
    region[: mask.shape[0] // 3] = True
    region &= ~mask
    other[region] = other[region] * 0.5 + np.random.default_rng(1).random((int(region.sum()), 3)) * 0.4  # another render: varied colours
    painted = other.copy()
    painted[mask] = PAINT
    write_png(tmp_path / "p.png", painted)
    got = read(tmp_path / "p.png", view)
    assert np.array_equal(got.mask, mask) and "pixels of the brush's colour;" in got.reading and "are left out" in got.reading


def test_a_coloured_image_that_is_not_the_render_is_refused(view, tmp_path):
    noise = np.random.default_rng(0).random(view[2].shape)
    write_png(tmp_path / "n.png", noise)
    with pytest.raises(CrfError, match="transparent PNG, or strokes over a render"):
        read(tmp_path / "n.png", view)


def test_mask_image_and_strokes_json_together(view, tmp_path):
    _, camera, _, mask = view
    write_png(tmp_path / "m.png", mask.astype(np.uint8) * 255)
    (tmp_path / "s.json").write_text('{"strokes": [[[1, 14]]], "radius": 1}')
    got = load_mask(tmp_path / "m.png", tmp_path / "s.json", camera.width, camera.height, "scribble")
    assert got.reading == "white on black + strokes JSON"
    dot = strokes_mask(mask.shape, [np.array([[1.0, 14.0]])], 1.0)
    assert dot[14, 1] and not (dot & mask).any() and np.array_equal(got.mask, mask | dot)


def test_coverage_limit():
    half = np.zeros((4, 4), bool)
    half[:2] = True
    assert check_coverage(half) == 0.5
    more = half.copy()
    more[2, 0] = True
    with pytest.raises(CrfError, match=r"covers 56.2 % of the view .* --force"):
        check_coverage(more)
    assert check_coverage(more, force=True) == 0.5625


def test_edit_color_reports_the_reading_and_refuses_a_large_scribble(view, tiny_model, tmp_path):
    _, _, render, mask = view
    painted = render.copy()
    painted[mask] = PAINT
    write_png(tmp_path / "p.png", painted)
    base = ["edit-color", tiny_model, "--instance", 0, "--view", "train:0", "--color", "red", "--steps", 2, "--device", "cpu"]
    ok = invoke(*base, "--scribble", tmp_path / "p.png", "--out", tmp_path / "e.safetensors")
    assert ok.exit_code == 0, ok.output
    line = next(ln for ln in ok.stdout.splitlines() if ln.startswith("scribble: "))
    assert line.startswith("scribble: strokes painted over the render") and f" {int(mask.sum())} pixels " in line
    big = np.ones(mask.shape, np.uint8) * 255
    big[:2] = 0
    write_png(tmp_path / "big.png", big)
    refused = invoke(*base, "--scribble", tmp_path / "big.png", "--out", tmp_path / "big.safetensors")
    assert refused.exit_code == 2 and "more than half" in refused.stderr and "--force" in refused.stderr
    assert not (tmp_path / "big.safetensors").exists()
    forced = invoke(*base, "--scribble", tmp_path / "big.png", "--force", "--out", tmp_path / "big.safetensors")
    assert forced.exit_code == 0 and (tmp_path / "big.safetensors").is_file(), forced.output


def test_a_json_given_as_the_image_is_read_as_strokes(view, tmp_path):
    _, camera, _, _ = view
    (tmp_path / "s.json").write_text('{"strokes": [[[4, 5], [11, 9]]], "radius": 1.5}')
    got = load_mask(tmp_path / "s.json", None, camera.width, camera.height, "scribble")
    assert got.reading == "strokes JSON"
    assert np.array_equal(got.mask, view[3])


def test_every_command_reads_scribble_json_the_same(view, tiny_model, tmp_path):
    """The same ``--scribble strokes.json`` that `select` takes works for the edits (it was read as
    an image there), and equals ``--scribble-json``."""
    (tmp_path / "s.json").write_text('{"strokes": [[[4, 5], [11, 9]]], "radius": 1.5}')
    base = ["remove", tiny_model, "--instance", 0, "--view", "train:0", "--steps", 2, "--device", "cpu"]
    files = {}
    for option in ("--scribble", "--scribble-json"):
        files[option] = tmp_path / f"{option.strip('-')}.safetensors"
        r = invoke(*base, option, tmp_path / "s.json", "--out", files[option])
        assert r.exit_code == 0, r.output
        assert f"scribble: strokes JSON, {int(view[3].sum())} pixels" in r.stdout
    a, b = (load_file(files[o]) for o in ("--scribble", "--scribble-json"))
    assert a.keys() == b.keys() and all(torch.equal(a[n], b[n]) for n in a)  # the metadata holds the times
    sel = invoke("select", tiny_model, "--instance", 0, "--view", "train:0", "--scribble", tmp_path / "s.json",
                 "--for", "remove", "--device", "cpu", "--out", tmp_path / "s.sel.safetensors")
    assert sel.exit_code == 0, sel.output


def test_add_reads_the_copy_mask_as_drawn(view, tiny_model, tmp_path):
    """``add --copy`` reads its mask like a scribble: strokes painted over the donor view's render
    copy the same part as the same strokes drawn white on black."""
    model, _, _, mask = view
    camera = model.views["train"].cameras(1)[0]  # the mask is drawn on the donor's own train:0, --view's spec read on the donor
    donor = render_camera(model.field_for(1), camera, 1).rgb.clamp(0, 1).numpy()
    donor = np.round(donor * 255) / 255
    painted = donor.copy()
    painted[mask] = PAINT
    write_png(tmp_path / "painted.png", painted)
    write_png(tmp_path / "wob.png", mask.astype(np.uint8) * 255)
    base = ["add", tiny_model, "--instance", 0, "--view", "train:0", "--donor", 1, "--offset", "0,0", "--steps", 2, "--device", "cpu"]
    outs = []
    for name, reading in (("painted", "strokes painted over the render"), ("wob", "white on black")):
        outs.append(tmp_path / f"{name}.safetensors")
        r = invoke(*base, "--copy", tmp_path / f"{name}.png", "--out", outs[-1])
        assert r.exit_code == 0, r.output
        assert next(ln for ln in r.stdout.splitlines() if ln.startswith("copy: ")).startswith(f"copy: {reading}")
        # it says what it took of the donor, in select's words
        from crfedit.edit.selection import select_for

        made = select_for(model, 1, camera, mask, None, "add").meta
        said = [ln for ln in r.stdout.splitlines() if ln.startswith("donor selection: ")]
        assert len(said) == 1 and said[0].startswith(f"donor selection: {made['selected_cells']} of {made['occupied_cells']} occupied cells ("), r.stdout
        assert any(ln.startswith("strokes: ") for ln in r.stdout.splitlines()), r.stdout
        assert not any(ln.startswith("keep strokes: ") for ln in r.stdout.splitlines()), r.stdout  # a donor takes none
    a, b = (load_file(o) for o in outs)
    assert a.keys() == b.keys() and all(torch.equal(a[n], b[n]) for n in a)
    # --preview renders the edited instance, as remove's and edit-color's do
    r = invoke(*base, "--copy", tmp_path / "wob.png", "--out", tmp_path / "p.safetensors", "--preview", tmp_path / "prev", "--views", "orbit:2")
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "prev").iterdir()) == ["0000.png", "0001.png"]
    assert r.stdout.splitlines()[-1] == f"wrote previews of the edited chair_000 (orbit:2) to {tmp_path / 'prev'}/"
    assert "note:" not in r.stderr
    # a donor whose shape an earlier edit changed: the copy comes from it as edited, and a note says so
    removal = tmp_path / "rm.safetensors"
    assert invoke("remove", tiny_model, "--instance", 1, "--view", "train:0", "--scribble", tmp_path / "wob.png", "--steps", 2,
                  "--out", removal, "--device", "cpu").exit_code == 0
    r = invoke(*base, "--copy", tmp_path / "wob.png", "--edit", removal, "--out", tmp_path / "after.safetensors")
    # here the removal took the very part the mask copies: nothing is left of it to copy, as the note warns
    note, error = r.stderr.splitlines()
    assert r.exit_code == 2 and note.startswith("note: an earlier --edit changed chair_001's shape"), r.output
    assert error == "error: nothing to copy: the copy mask covers none of the donor's opaque pixels in the donor view"
    assert not (tmp_path / "after.safetensors").exists()


def test_keep_strokes_over_the_scribble_are_warned_of():
    """Keep strokes mark what must not change: over the scribbled part they hold the part back."""
    from crfedit.edit.scribble import keep_overlap

    fg = np.zeros((8, 8), bool)
    fg[2:4, 2:6] = True
    assert keep_overlap(fg, None) is None and keep_overlap(fg, np.zeros_like(fg)) is None
    near = np.zeros_like(fg)
    near[4:6, 2:6] = True  # beside the scribble: fine
    assert keep_overlap(fg, near) is None
    assert "cover 100% of the scribbled pixels" in keep_overlap(fg, fg)
    half = np.zeros_like(fg)
    half[2:4, 2:4] = True
    assert "cover 50%" in keep_overlap(fg, half)


def test_a_scribble_of_a_few_pixels_gets_a_note():
    from crfedit.edit.scribble import FEW_SCRIBBLED, few_pixels_note

    mask = np.zeros((8, 8), bool)
    assert few_pixels_note(mask) is None  # empty: the edit's own error says so
    mask[3, 3] = True
    assert few_pixels_note(mask).startswith("a scribble of 1 pixel says little about the part")
    mask[4, 3:3 + FEW_SCRIBBLED] = True
    assert few_pixels_note(mask) is None


def test_strokes_json_is_told_by_its_content(tmp_path):
    """A pipe (<(…)) has no suffix, nor does every file: strokes JSON that starts with { or [
    (after a BOM) is read as strokes wherever an image is expected, not 'not a readable image'."""
    from crfedit.edit.scribble import load_mask

    for name, text in (("list", '[[[3, 4], [9, 4]]]'), ("bom", '\ufeff{"strokes": [[[3, 4], [9, 4]]], "radius": 1}')):
        (tmp_path / name).write_text(text, encoding="utf-8")
        got = load_mask(tmp_path / name, None, 16, 16, "scribble")
        assert got.reading == "strokes JSON" and got.mask[4, 3:10].all() and not got.mask[12].any(), name
