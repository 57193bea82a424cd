"""File I/O: atomic writes, one-line errors that name the file, image and EXR round trips."""

from __future__ import annotations

import os
import re
import struct
import zlib
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from PIL import Image

from crfedit.errors import CrfError
from crfedit.io import (
    atomic_path,
    atomic_write_bytes,
    atomic_write_text,
    read_exr,
    read_image,
    read_json,
    write_exr,
    write_json,
    write_png,
)


def listing(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def assert_one_line_naming(error: pytest.ExceptionInfo, path: Path) -> str:
    msg = str(error.value)
    assert "\n" not in msg and "\r" not in msg
    assert str(path) in msg
    return msg


def png16(path: Path, array: np.ndarray, color_type: int) -> None:
    """A minimal 16-bit PNG encoder (Pillow cannot write 16-bit colour): 0 gray, 2 RGB, 4 LA, 6 RGBA."""
    height, width = array.shape[:2]
    raw = b"".join(b"\x00" + array[i].astype(">u2").tobytes() for i in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 16, color_type, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


# ------------------------------------------------------------------------------ atomic writes


def test_writes_leave_no_temp_file(tmp_path):
    write_json(tmp_path / "a.json", {"x": [1, 2]})
    atomic_write_text(tmp_path / "b.txt", "héllo\n")
    atomic_write_bytes(tmp_path / "c.bin", b"\x00\x01")
    write_png(tmp_path / "d.png", np.zeros((4, 5, 3)))
    write_exr(tmp_path / "e.exr", {"Z": np.ones((4, 5), np.float32)})
    assert listing(tmp_path) == ["a.json", "b.txt", "c.bin", "d.png", "e.exr"]
    assert read_json(tmp_path / "a.json") == {"x": [1, 2]}
    assert (tmp_path / "b.txt").read_text(encoding="utf-8") == "héllo\n"
    assert (tmp_path / "c.bin").read_bytes() == b"\x00\x01"


def test_write_replaces_existing_file(tmp_path):
    target = tmp_path / "m.json"
    write_json(target, {"v": 1})
    write_json(target, {"v": 2})
    assert read_json(target) == {"v": 2}
    assert listing(tmp_path) == ["m.json"]


@pytest.mark.parametrize("exc", [RuntimeError("disk on fire"), KeyboardInterrupt()])
def test_failure_midway_keeps_old_file(tmp_path, exc):
    target = tmp_path / "model.bin"
    target.write_bytes(b"old contents")
    with pytest.raises(type(exc)):
        with atomic_path(target) as tmp:
            assert tmp.parent == tmp_path and tmp != target
            tmp.write_bytes(b"half of the new con")
            raise exc
    assert target.read_bytes() == b"old contents"
    assert listing(tmp_path) == ["model.bin"]


def test_png_writer_failing_midway_keeps_old_file(tmp_path, monkeypatch):
    target = tmp_path / "view.png"
    write_png(target, np.full((3, 3, 3), 0.5))
    before = target.read_bytes()

    def broken_save(self, fp, format=None, **params):
        Path(fp).write_bytes(b"\x89PNG partial")
        raise OSError("No space left on device")

    monkeypatch.setattr(Image.Image, "save", broken_save)
    with pytest.raises(OSError, match="No space left"):
        write_png(target, np.zeros((3, 3, 3)))
    assert target.read_bytes() == before
    assert listing(tmp_path) == ["view.png"]


def test_a_full_disk_names_the_file_being_written_not_its_temporary(tmp_path, monkeypatch):
    import errno

    def full(self, fp, format=None, **params):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Image.Image, "save", full)
    with pytest.raises(OSError) as caught:
        write_png(tmp_path / "view.png", np.zeros((3, 3, 3)))
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(tmp_path / "view.png")
    assert listing(tmp_path) == []


def test_a_target_that_is_not_a_regular_file_is_refused(tmp_path):
    """The rename would replace a folder's name, a pipe or a device node (/dev/full) with a file."""
    os.mkfifo(tmp_path / "pipe")
    (tmp_path / "folder").mkdir()
    for target in (tmp_path / "pipe", tmp_path / "folder"):
        with pytest.raises(CrfError, match="not a regular file"):
            write_png(target, np.zeros((3, 3, 3)))
    assert (tmp_path / "pipe").is_fifo() and (tmp_path / "folder").is_dir() and listing(tmp_path) == ["folder", "pipe"]


def test_exr_writer_failing_midway_keeps_old_file(tmp_path, monkeypatch):
    target = tmp_path / "depth.exr"
    write_exr(target, {"Z": np.full((2, 3), 7.0, np.float32)})

    class BrokenFile:
        def __init__(self, header, channels):
            pass

        def write(self, path):
            Path(path).write_bytes(b"v/1\x01 partial")
            raise RuntimeError("write failed")

    monkeypatch.setattr(OpenEXR, "File", BrokenFile)
    with pytest.raises(RuntimeError, match="write failed"):
        write_exr(target, {"Z": np.zeros((2, 3), np.float32)})
    monkeypatch.undo()
    assert np.array_equal(read_exr(target)["Z"], np.full((2, 3), 7.0, np.float32))
    assert listing(tmp_path) == ["depth.exr"]


def test_write_into_missing_folder_is_user_error(tmp_path):
    target = tmp_path / "no" / "such" / "out.png"
    with pytest.raises(CrfError) as e:
        write_png(target, np.zeros((2, 2, 3)))
    assert_one_line_naming(e, target)
    assert not (tmp_path / "no").exists()


def test_write_below_a_file_is_user_error(tmp_path):
    blocker = tmp_path / "blocker"
    blocker.write_text("I am a file")
    for write in (lambda p: write_json(p, {}), lambda p: write_exr(p, {"Z": np.zeros((1, 1))})):
        target = blocker / "out.json"
        with pytest.raises(CrfError) as e:
            write(target)
        assert_one_line_naming(e, target)
    assert blocker.read_text() == "I am a file"


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root ignores folder permissions")
def test_write_into_read_only_folder_is_user_error(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        with pytest.raises(CrfError, match="not writable") as e:
            write_json(folder / "x.json", {})
        assert_one_line_naming(e, folder / "x.json")
    finally:
        folder.chmod(0o755)


def test_an_output_folder_nothing_can_be_written_in_is_refused_before_the_work(tmp_path, monkeypatch):
    """``check_folder_target`` (run before long work) asks the file system whether the folder,
    or the nearest one above a folder still to be made, takes files: a read-only mount failed
    only after an edit's previews (or a render) had been computed.  (os.access answers for the
    read-only mount even for root; the permission case is simulated.)"""
    from crfedit.io import check_folder_target

    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, *a, **k: False if Path(p) == ro else real(p, mode, *a, **k))
    for target in (ro, ro / "new" / "deeper"):
        with pytest.raises(CrfError, match=rf"^--out {re.escape(str(target))}: cannot write in {re.escape(str(ro))} \(a read-only file system, or no permission\)$"):
            check_folder_target(target, "--out")
    check_folder_target(tmp_path / "fine", "--out")  # a writable parent: nothing to say


# ------------------------------------------------------------------------------ read errors


def test_missing_files_are_one_line_errors(tmp_path):
    for reader, name in ((read_image, "gone.png"), (read_exr, "gone.exr"), (read_json, "gone.json")):
        path = tmp_path / name
        with pytest.raises(CrfError, match="file not found") as e:
            reader(path)
        assert_one_line_naming(e, path)


def test_corrupt_png_is_one_line_error(tmp_path):
    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"this is\nnot a png\n" * 10)
    with pytest.raises(CrfError, match="not a readable image") as e:
        read_image(garbage)
    assert_one_line_naming(e, garbage)

    good = tmp_path / "good.png"
    write_png(good, np.random.default_rng(0).random((64, 64, 3)))
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(CrfError, match="not a readable image") as e:
        read_image(truncated)
    assert_one_line_naming(e, truncated)

    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(CrfError) as e:
        read_image(empty)
    assert_one_line_naming(e, empty)


def test_corrupt_exr_is_one_line_error(tmp_path):
    garbage = tmp_path / "garbage.exr"
    garbage.write_bytes(b"\x76\x2f\x31\x01 nonsense\n" * 4)
    with pytest.raises(CrfError, match="not a readable EXR") as e:
        read_exr(garbage)
    assert_one_line_naming(e, garbage)

    good = tmp_path / "good.exr"
    write_exr(good, {"Z": np.random.default_rng(1).random((32, 32)).astype(np.float32)})
    truncated = tmp_path / "truncated.exr"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(CrfError, match="not a readable EXR") as e:
        read_exr(truncated)
    assert_one_line_naming(e, truncated)


def test_corrupt_json_is_one_line_error(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"a": 1,\n "b": }\n')
    with pytest.raises(CrfError, match="malformed JSON") as e:
        read_json(bad)
    assert "line 2" in assert_one_line_naming(e, bad)

    binary = tmp_path / "binary.json"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(CrfError) as e:
        read_json(binary)
    assert_one_line_naming(e, binary)


# ------------------------------------------------------------------------------ EXR


def test_exr_round_trip_of_non_contiguous_arrays(tmp_path):
    rng = np.random.default_rng(2)
    base = rng.random((12, 20)).astype(np.float32)
    transposed = base.T  # [20, 12], Fortran order
    strided = base[::2, ::3]  # [6, 7]
    assert not transposed.flags.c_contiguous and not strided.flags.c_contiguous
    for name, arr in (("t", transposed), ("s", strided)):
        path = tmp_path / f"{name}.exr"
        write_exr(path, {"Z": arr})
        back = read_exr(path)["Z"]
        assert back.dtype == np.float32 and back.shape == arr.shape
        assert np.array_equal(back, arr)


def test_exr_float64_and_several_channels(tmp_path):
    rng = np.random.default_rng(3)
    depth = rng.random((5, 4)) * 10.0  # float64: stored as float32
    mask = (rng.random((5, 4)) > 0.5).astype(np.float32)
    write_exr(tmp_path / "d.exr", {"Z": depth, "A": mask})
    back = read_exr(tmp_path / "d.exr")
    assert set(back) == {"Z", "A"}
    assert np.array_equal(back["Z"], depth.astype(np.float32))
    assert np.array_equal(back["A"], mask)


# ------------------------------------------------------------------------------ images


def test_png_round_trip_quantizes_to_8_bits(tmp_path):
    img = np.random.default_rng(4).random((6, 7, 3))
    write_png(tmp_path / "x.png", img)
    back = read_image(tmp_path / "x.png")
    assert back.dtype == np.float32 and back.shape == (6, 7, 3)
    assert np.abs(back - img).max() <= 0.5 / 255 + 1e-6
    rgba = np.random.default_rng(5).random((6, 7, 4))
    write_png(tmp_path / "y.png", rgba)
    assert read_image(tmp_path / "y.png").shape == (6, 7, 4)
    write_png(tmp_path / "z.png", rgba[..., :1])
    assert read_image(tmp_path / "z.png").shape == (6, 7, 3)


@pytest.fixture
def rgba8() -> np.ndarray:
    return np.random.default_rng(6).integers(0, 256, (5, 6, 4), dtype=np.uint8)


def test_read_image_rgb_and_rgba(tmp_path, rgba8):
    Image.fromarray(rgba8[..., :3], "RGB").save(tmp_path / "rgb.png")
    Image.fromarray(rgba8, "RGBA").save(tmp_path / "rgba.png")
    assert np.array_equal(read_image(tmp_path / "rgb.png"), rgba8[..., :3] / np.float32(255))
    assert np.array_equal(read_image(tmp_path / "rgba.png"), rgba8 / np.float32(255))


def test_read_image_gray_and_gray_alpha(tmp_path, rgba8):
    gray, alpha = rgba8[..., 0], rgba8[..., 3]
    Image.fromarray(gray, "L").save(tmp_path / "l.png")
    Image.fromarray(np.stack([gray, alpha], -1), "LA").save(tmp_path / "la.png")
    l_img = read_image(tmp_path / "l.png")
    assert l_img.shape == (5, 6, 3)
    assert all(np.array_equal(l_img[..., c], gray / np.float32(255)) for c in range(3))
    la_img = read_image(tmp_path / "la.png")
    assert la_img.shape == (5, 6, 4)
    assert np.array_equal(la_img[..., 1], gray / np.float32(255))
    assert np.array_equal(la_img[..., 3], alpha / np.float32(255))


def test_read_image_palette(tmp_path):
    palette = [255, 0, 0, 0, 255, 0, 0, 0, 255, 10, 20, 30]
    index = np.array([[0, 1, 2, 3], [3, 2, 1, 0]], dtype=np.uint8)
    im = Image.fromarray(index, "P")
    im.putpalette(palette + [0] * (768 - len(palette)))
    im.save(tmp_path / "p.png")
    colors = np.array(palette, np.float32).reshape(4, 3) / 255
    got = read_image(tmp_path / "p.png")
    assert got.shape == (2, 4, 3)
    assert np.array_equal(got, colors[index])
    im.save(tmp_path / "pt.png", transparency=3)  # palette entry 3 fully transparent
    got = read_image(tmp_path / "pt.png")
    assert got.shape == (2, 4, 4)
    assert np.array_equal(got[..., 3], np.where(index == 3, 0.0, 1.0).astype(np.float32))
    assert np.array_equal(got[..., :3], colors[index])


def test_read_image_16_bit_gray(tmp_path):
    values = (np.arange(12, dtype=np.uint16).reshape(3, 4) * 5957)  # spans 0 .. 65527
    Image.fromarray(values).save(tmp_path / "g16.png")
    got = read_image(tmp_path / "g16.png")
    assert got.shape == (3, 4, 3) and got.dtype == np.float32
    assert np.allclose(got[..., 1], values / 65535.0, atol=1e-7)


def test_read_image_dark_16_bit_gray(tmp_path):
    Image.fromarray(np.full((2, 2), 200, np.uint16)).save(tmp_path / "dark16.png")
    assert np.allclose(read_image(tmp_path / "dark16.png"), 200 / 65535.0, atol=1e-7)


def test_read_image_32_bit_integers_by_their_values(tmp_path):
    """A 32-bit integer image (mode I, a TIFF) has no bit depth to read it by: 0–255 values are
    8-bit (they read 250× too dark as 16-bit, silently), up to 65535 16-bit, others refused."""
    eight = np.array([[0, 51], [204, 255]], np.int32)
    Image.fromarray(eight).save(tmp_path / "i8.tiff")
    assert np.allclose(read_image(tmp_path / "i8.tiff")[..., 0], eight / 255.0, atol=1e-7)
    sixteen = np.array([[0, 300], [40000, 65535]], np.int32)
    Image.fromarray(sixteen).save(tmp_path / "i16.tiff")
    assert np.allclose(read_image(tmp_path / "i16.tiff")[..., 0], sixteen / 65535.0, atol=1e-7)
    for bad in (70000, -1):
        Image.fromarray(np.array([[0, bad]], np.int32)).save(tmp_path / "bad.tiff")
        with pytest.raises(CrfError, match=r"bad\.tiff: 32-bit integer values outside 0–65535 have no range to read them by"):
            read_image(tmp_path / "bad.tiff")


@pytest.mark.parametrize("color_type, channels, out_channels", [(2, 3, 3), (6, 4, 4), (4, 2, 4)])
def test_read_image_16_bit_color(tmp_path, color_type, channels, out_channels):
    values = np.random.default_rng(7).integers(0, 65536, (3, 4, channels)).astype(np.uint16)
    png16(tmp_path / "c16.png", values, color_type)
    got = read_image(tmp_path / "c16.png")
    assert got.shape == (3, 4, out_channels) and got.dtype == np.float32
    expected = values / 65535.0
    if channels == 2:  # gray + alpha -> RGBA
        expected = np.concatenate([np.repeat(expected[..., :1], 3, axis=2), expected[..., 1:]], axis=2)
    assert np.abs(got - expected).max() <= 1 / 255  # Pillow keeps the high byte



def test_a_folder_another_process_swaps_in_meanwhile_is_moved_aside_too(tmp_path, monkeypatch):
    """atomic_folder: another process's folder that lands at the path between this one's two
    renames is moved aside as well, so this one's folder ends up whole in its place; Ctrl-C
    between the renames puts the old folder back."""
    import crfedit.io as io

    out = tmp_path / "f"
    out.mkdir()
    (out / "old").write_text("old")
    real, moves = os.replace, []

    def replace(src, dst):
        real(src, dst)
        moves.append(dst)
        if len(moves) == 1:  # the old folder is aside: the other process's folder arrives
            out.mkdir()
            (out / "theirs").write_text("theirs")

    monkeypatch.setattr(io.os, "replace", replace)
    with io.atomic_folder(out) as tmp:
        (tmp / "mine").write_text("mine")
    assert listing(out) == ["mine"] and listing(tmp_path) == ["f"] and len(moves) == 3

    def interrupted(src, dst):
        if Path(src).name.endswith(".partial"):
            raise KeyboardInterrupt
        real(src, dst)

    monkeypatch.setattr(io.os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt), io.atomic_folder(out) as tmp:
        (tmp / "other").write_text("other")
    assert listing(out) == ["mine"] and listing(tmp_path) == ["f"]


def test_a_folder_replaced_through_a_link_keeps_the_link_and_its_mode(tmp_path):
    """atomic_folder on `latest -> 2026-11-28` replaces the link's folder (the link stays a link;
    it became a plain folder and the frames missed the target), and the replaced folder keeps its
    mode (a group's setgid 2750 came back as 755)."""
    import stat

    import crfedit.io as io

    target = tmp_path / "2026-11-28"
    target.mkdir()
    (target / "old").write_text("old")
    os.chmod(target, 0o2750)
    link = tmp_path / "latest"
    link.symlink_to(target.name)
    with io.atomic_folder(link) as tmp:
        (tmp / "new").write_text("new")
    assert link.is_symlink() and listing(target) == ["new"] and listing(link) == ["new"]
    assert stat.S_IMODE(target.stat().st_mode) == 0o2750 and sorted(p.name for p in tmp_path.iterdir()) == ["2026-11-28", "latest"]


def test_a_long_legal_name_is_written_through_short_hidden_files(tmp_path):
    """A 250-byte file name is legal; the temporary beside it must not overflow 255 bytes."""
    from crfedit.io import atomic_path, hidden_stem, writer_lock

    long = tmp_path / ("b" * 238 + ".safetensors")
    assert len(long.name) == 250 and len(hidden_stem(long)) == 113
    with writer_lock(long), atomic_path(long) as tmp:
        tmp.write_bytes(b"x")
    assert long.read_bytes() == b"x" and sorted(p.name for p in tmp_path.iterdir()) == [long.name]
    assert hidden_stem(tmp_path / "m.safetensors") == "m.safetensors"


def test_an_output_of_another_kind_replaces_only_its_own_kind(tmp_path):
    """Meshes, videos and the bench's CSV and page are not crfedit files, but a typo must not
    put one over a model, a photo or notes (bench --csv MODEL replaced a model with a CSV)."""
    from crfedit.io import check_replaceable

    (tmp_path / "notes.ply").write_text("my notes")
    (tmp_path / "m.csv").write_bytes(b"\x00\x01 a model")
    (tmp_path / "ok.ply").write_text("ply\nformat ascii 1.0\n")
    (tmp_path / "ok.csv").write_text("group,curve,knob\n")
    (tmp_path / "page.md").write_text("# notes\n")
    (tmp_path / "empty.gif").write_bytes(b"")
    for name, suffixes in (("notes.ply", (".ply",)), ("m.csv", (".csv",))):
        with pytest.raises(CrfError, match="holds a file that is not a"):
            check_replaceable(tmp_path / name, "--out", suffixes)
    for name, suffixes in (("ok.ply", (".ply",)), ("ok.csv", (".csv",)), ("page.md", (".md",)), ("empty.gif", (".gif",)), ("new.stl", (".stl",))):
        check_replaceable(tmp_path / name, "--out", suffixes)
    with pytest.raises(CrfError, match="expected a file name ending in .csv"):
        check_replaceable(tmp_path / "model.safetensors", "--csv", (".csv",))
    with pytest.raises(CrfError, match="folder .*nodir does not exist"):
        check_replaceable(tmp_path / "nodir" / "b.csv", "--csv", (".csv",))
    (tmp_path / "d.ply").mkdir()  # a folder of the right suffix: named a folder (it said the suffix was wrong)
    with pytest.raises(CrfError, match=r"d\.ply: is a folder; give a file name ending in \.ply"):
        check_replaceable(tmp_path / "d.ply", "--out", (".ply",))
    (tmp_path / "y.off").write_text("my notes")
    with pytest.raises(CrfError, match="holds a file that is not an OFF file"):
        check_replaceable(tmp_path / "y.off", "--out", (".off",))


def test_images_and_json_read_from_a_pipe(tmp_path):
    """A shell's <(…) or /dev/stdin fed by | is a pipe: read whole once (a second read gets the
    same bytes), not refused as 'not a regular file'; a named pipe nothing writes to reads as
    empty rather than blocking."""
    import threading

    from crfedit.io import piped_input, read_image, read_json

    write_png(tmp_path / "s.png", np.eye(4)[..., None].repeat(3, axis=2))
    for data, reader, expected in ((b'\xef\xbb\xbf{"a": [1, 2]}', read_json, {"a": [1, 2]}),
                                   ((tmp_path / "s.png").read_bytes(), read_image, read_image(tmp_path / "s.png"))):
        r, w = os.pipe()
        feeder = threading.Thread(target=lambda: (os.write(w, data), os.close(w)))
        feeder.start()
        path = f"/dev/fd/{r}"
        try:
            got = reader(path)
            assert (got == expected) if isinstance(expected, dict) else np.array_equal(got, expected)
            assert piped_input(path) == data  # kept: the pipe itself is empty now
        finally:
            feeder.join()
            os.close(r)
    assert piped_input(tmp_path / "s.png") is None  # a regular file is read as one
    os.mkfifo(tmp_path / "fifo")
    with pytest.raises(CrfError, match=r"fifo: the pipe gave nothing \(nothing wrote to it\)$"):
        read_image(tmp_path / "fifo")
