"""File I/O that never leaves a half-written file and never executes code.

Every write goes to a temporary file in the destination folder, is fsync'ed, then renamed over
the target (atomic on POSIX).  Images are read with Pillow, depth with OpenEXR, tensors with
safetensors — no pickle anywhere.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import stat
import tempfile
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .errors import CrfError


MAX_PIPED_BYTES = 1 << 28
"""At most this much is read from a pipe (256 MB: a scribble, strokes or a photo)."""
_PIPED: dict[tuple[int, int], bytes] = {}  # by the pipe's (device, inode): /dev/fd/N names another pipe once N is reused


def piped_input(path: str | os.PathLike) -> bytes | None:
    """The whole content of ``path`` when it is a pipe (a shell's ``<(…)``, ``/dev/stdin`` fed
    by ``|``), read once per process and kept, since a command may read an input twice; None for
    anything else.  Opened without blocking: a named pipe nothing writes to reads as empty
    instead of waiting for ever.  Images and JSON inputs (scribbles, strokes, photos, camera
    files) read pipes; models and edits, which are read in parts, do not."""
    import select

    try:
        st = os.stat(path)
        if not stat.S_ISFIFO(st.st_mode):
            return None
        key = (st.st_dev, st.st_ino)
        if key in _PIPED:
            return _PIPED[key]
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError:
        return None
    chunks, total = [], 0
    try:
        while True:
            try:
                chunk = os.read(fd, 1 << 16)
            except BlockingIOError:  # a writer that has not written yet
                select.select([fd], [], [], 1.0)
                continue
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
            if total > MAX_PIPED_BYTES:
                raise CrfError(f"{path}: the pipe gives more than {MAX_PIPED_BYTES >> 20} MB")
    finally:
        os.close(fd)
    data = b"".join(chunks)
    if not data:
        raise CrfError(f"{path}: the pipe gave nothing (nothing wrote to it)")
    _PIPED[key] = data
    return data


def not_a_file(path: Path, missing: str = "file not found") -> str:
    """Why ``path`` (not a regular file) cannot be read, for an error line: a folder, a device
    or pipe, a symbolic link that leads nowhere, or ``missing``."""
    if path.is_dir():
        return "is a folder, not a file"
    if path.is_fifo():
        return "is a pipe, which crfedit reads only for images and JSON (write it to a file first)"
    if path.exists():
        return "is not a regular file (a device or pipe)"
    if path.is_symlink():
        return "is a symbolic link that leads nowhere (a loop, or its target is missing)"
    return missing


def hidden_stem(path: Path) -> str:
    """``path``'s name for the hidden files written beside it (temporaries, locks): the name
    itself, or for a long one (a legal 255-byte name would overflow with the extra parts) its
    first 100 characters and a hash of the rest, so the error of a failed write never names a
    file the user did not type."""
    name = path.name
    if len(name.encode("utf-8", "surrogateescape")) <= 150:
        return name
    import hashlib

    return f"{name[:100]}~{hashlib.sha1(name.encode('utf-8', 'surrogateescape')).hexdigest()[:12]}"


@contextlib.contextmanager
def writer_lock(path: str | os.PathLike, held: bool = True) -> Iterator[None]:
    """Hold an exclusive lock on writing ``path`` for the duration (``held`` False: no lock, a
    rank that does not write), ``path``'s missing folders created for it and removed again if
    they are still empty at the end (a run that failed early leaves no empty folder).  A second
    crfedit process asking for the same path is refused at once, in one line, instead of both
    running and the later silently replacing the earlier's file.  The lock is an advisory
    ``flock`` on a hidden ``.NAME.lock`` beside ``path``, removed on release; the system drops
    the lock of a process that dies.  Without ``fcntl`` (Windows) nothing is locked."""
    try:
        import fcntl
    except ImportError:
        fcntl = None
    path = Path(path)
    made = [p for p in reversed(path.parents) if not p.exists()]
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        if not held or fcntl is None:
            yield
            return
        with _flocked(path, fcntl):
            yield
    finally:
        for folder in reversed(made):  # deepest first; one that holds anything stays
            try:
                folder.rmdir()
            except OSError:
                break


def stale_partials(path: str | os.PathLike) -> list[Path]:
    """The temporary files :func:`atomic_path` made for ``path`` and never renamed (a process
    killed with SIGKILL while writing: nothing ran to remove them), by their exact name pattern.
    Remove them only while holding :func:`writer_lock` on ``path``: then no crfedit run that
    locks is writing one (``train --resume`` after a killed torchrun job left a 17 MB one)."""
    import re

    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    pattern = re.compile(rf"\.{re.escape(hidden_stem(path))}\.[A-Za-z0-9_]{{8}}{re.escape(path.suffix)}\.tmp")
    try:
        return sorted(p for p in folder.iterdir() if pattern.fullmatch(p.name) and p.is_file())
    except OSError:
        return []


@contextlib.contextmanager
def _flocked(path: Path, fcntl) -> Iterator[None]:
    """:func:`writer_lock`'s lock proper."""
    lock = path.with_name(f".{hidden_stem(path)}.lock")
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
            raise CrfError(f"{path}: another crfedit process is writing it{f' (pid {holder})' if holder.isdigit() else ''}; "
                           "wait for it to finish, or pick another name") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        try:
            yield
        finally:
            lock.unlink(missing_ok=True)  # while still held: the next writer makes a fresh lock file
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success fsync and rename it onto ``path``.

    On any exception the temporary file is removed and ``path`` is left as it was; an OS error
    (a full disk) names ``path``, not the hidden temporary file.  An existing ``path`` that is
    not a regular file (a folder, a device such as /dev/full, a pipe) is refused: the rename
    would replace it.  ``suffix`` defaults to the target's own suffix (some writers pick the
    format from it).
    """
    path = Path(path)
    if path.exists() and not path.is_file():
        raise CrfError(f"{path}: exists and is not a regular file (a folder, device or pipe); give a file name")
    folder = path.parent if str(path.parent) else Path(".")
    if folder.exists() and not folder.is_dir():
        raise CrfError(f"{path}: {folder} is a file, not a folder")
    if not folder.is_dir():
        raise CrfError(f"{path}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK):
        raise CrfError(f"{path}: folder {folder} is not writable")
    fd, tmp = tempfile.mkstemp(prefix=f".{hidden_stem(path)}.", suffix=(path.suffix if suffix is None else suffix) + ".tmp", dir=folder)
    os.close(fd)
    tmp_path = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual mode
    try:
        yield tmp_path
        with open(tmp_path, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp_path, path)
        with contextlib.suppress(OSError):  # make the rename itself durable
            dfd = os.open(folder, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
    except BaseException as e:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        if isinstance(e, OSError) and e.errno is not None and e.filename in (None, str(tmp_path)) and e.filename2 is None:
            raise OSError(e.errno, e.strerror, str(path)) from None
        raise


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a new hidden folder beside ``path`` to build in; on success it replaces ``path``.

    An existing ``path`` is moved aside first and deleted once the new folder is in place, so
    an interrupted build (Ctrl-C, a full disk) leaves ``path`` as it was and no partial folder;
    two processes building the same ``path`` at once leave one whole folder (the later's).
    """
    import errno
    import shutil

    path = Path(path)
    named = path
    if path.is_symlink():  # `runs/latest -> runs/2026-11-28`: the link stays, its folder is the one replaced
        path = Path(os.path.realpath(path))
    parent = path.parent if str(path.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{hidden_stem(path)}.", suffix=".partial", dir=parent))
    except OSError as e:  # name the user's folder, not the hidden one
        raise OSError(e.errno, e.strerror, str(named)) from None
    if path.is_dir():  # the folder replaced keeps its mode (a group's setgid 2750 came back as 755)
        os.chmod(tmp, stat.S_IMODE(path.stat().st_mode))
    else:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp creates 0700; give the folder the usual mode
    old = None
    try:
        yield tmp
        old = Path(tempfile.mkdtemp(prefix=f".{hidden_stem(path)}.", suffix=".old", dir=parent))
        for turn in range(100):  # another process may put its folder in between: move that aside too
            aside = old / str(turn)
            try:
                with contextlib.suppress(FileNotFoundError):
                    os.replace(path, aside)
                os.replace(tmp, path)
                break
            except BaseException as e:
                if os.path.lexists(aside) and not os.path.lexists(path):  # interrupted between the renames
                    os.replace(aside, path)
                if not (isinstance(e, OSError) and e.errno in (errno.ENOTEMPTY, errno.EEXIST)):
                    raise
        else:
            raise OSError(errno.EBUSY, "other processes keep replacing it", str(named))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


def carry_into(entries: list[Path], into: Path) -> list[str]:
    """Link (or copy, where the file system has no links) ``entries`` (files, symbolic links,
    folders) into the folder ``into`` built to replace theirs, but for names already there; the
    names carried.  What a folder replaced whole (:func:`atomic_folder`) keeps of the user's."""
    import shutil

    def link_or_copy(src, dst):
        try:
            os.link(src, dst)
        except OSError:
            shutil.copy2(src, dst)

    carried = []
    for f in entries:
        target = Path(into) / f.name
        if os.path.lexists(target):
            continue
        try:
            if f.is_symlink():
                os.symlink(os.readlink(f), target)
            elif f.is_dir():
                shutil.copytree(f, target, symlinks=True, copy_function=link_or_copy)
            else:
                link_or_copy(f, target)
        except FileNotFoundError:  # gone since it was listed (another process)
            continue
        carried.append(f.name)
    return carried


SIGNATURES = {
    ".ply": (b"ply",), ".glb": (b"glTF",), ".off": (b"OFF", b"COFF", b"NOFF"), ".gif": (b"GIF87a", b"GIF89a"),
    ".csv": (b"step,", b"group,", b"kind,", b"preset,"), ".png": (b"\x89PNG",),
}
"""How a file of each kind another command's output replaces begins (``.obj``, ``.stl``,
``.md`` and ``.mp4``: see :func:`check_replaceable`)."""


def check_replaceable(out: Path, option: str, suffixes: tuple[str, ...]) -> None:
    """An output file that is not crfedit's own kind (a mesh, a video, a CSV or page of the
    bench): its name ends in one of ``suffixes``, its folder exists, and a file already there
    is one of that kind, not a model, an edit, a photo or notes lost to a typo (as
    :func:`check_out_file` guards crfedit's files).  Called before any work."""
    suffix = out.suffix.lower()
    if out.is_dir():  # named as such: the suffix may be right (a folder called d.ply)
        raise CrfError(f"{option} {out}: is a folder; give a file name ending in {', '.join(suffixes)}")
    if suffix not in suffixes:
        raise CrfError(f"{option} {out}: expected a file name ending in {', '.join(suffixes)}")
    folder = out.parent if str(out.parent) else Path(".")
    if not folder.is_dir():
        raise CrfError(f"{option} {out}: folder {folder} does not exist (make it first: mkdir -p {folder})")
    if not out.exists() or (out.is_file() and out.stat().st_size == 0):
        return
    if not out.is_file():
        raise CrfError(f"{option} {out}: is not a regular file")
    with open(out, "rb") as f:
        head = f.read(512)
    if suffix in SIGNATURES:
        ok = head.startswith(SIGNATURES[suffix])
    elif suffix == ".mp4":
        ok = head[4:8] == b"ftyp"
    elif suffix == ".stl":
        ok = head.startswith(b"solid") or (len(head) >= 84 and out.stat().st_size == 84 + 50 * int.from_bytes(head[80:84], "little"))
    else:  # .obj and .md: text crfedit can have written (a mesh's vertices, a page with the bench's markers)
        try:
            text = out.read_text("utf-8")
        except (UnicodeDecodeError, OSError):
            text = None
        ok = text is not None and (suffix != ".obj" or text.lstrip().startswith(("#", "v ", "o ", "mtllib")))
    if not ok:
        kind = suffix[1:].upper()
        article = "an" if kind[0] in "AEFHILMNORSX" else "a"  # said as letters: an OFF, an STL, an MP4; a PLY, a GIF
        raise CrfError(f"{option} {out}: holds a file that is not {article} {kind} file, which this would replace; pick another name")


def check_folder_target(path: str | os.PathLike, what: str = "") -> None:
    """``path`` is a folder or can be made one: it is not a file and no existing ancestor is.

    Called before long work, so a bad output path fails in a second rather than at the end.
    """
    p = Path(path)
    label = f"{what} {p}".strip()
    if p.exists():
        if not p.is_dir():
            raise CrfError(f"{label}: exists and is not a folder")
        _writable(p, label)
        return
    for parent in p.parents:
        if parent.exists():
            if not parent.is_dir():
                raise CrfError(f"{label}: {parent} is a file, not a folder")
            _writable(parent, label)
            return


def _writable(folder: Path, label: str) -> None:
    """A :class:`CrfError` when nothing can be written in ``folder`` (a read-only file system, or
    no permission): found before the work, not after it."""
    if not os.access(folder, os.W_OK | os.X_OK):
        raise CrfError(f"{label}: cannot write in {folder} (a read-only file system, or no permission)")


def probe_folder(folder: str | os.PathLike, label: str) -> None:
    """A :class:`CrfError` unless a file can be made (and is removed again) in the existing
    ``folder``: ``os.access`` says yes to root everywhere, /proc too, where a benchmark's
    ``--csv`` failed after its sweep.  For a script about to spend minutes before it writes."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".crfedit-probe-", dir=folder)
    except OSError as e:
        raise CrfError(f"{label}: cannot write in {folder} ({e.strerror or e.__class__.__name__})") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2) + "\n")


def read_json(path: str | os.PathLike):
    """Parse a JSON file; a missing or malformed file is a one-line :class:`CrfError`."""
    path = Path(path)
    piped = piped_input(path)
    if piped is None and not path.is_file():  # a device would block the read for ever
        raise CrfError(f"{path}: {not_a_file(path)}")
    try:
        text = piped.decode("utf-8-sig") if piped is not None else path.read_text(encoding="utf-8-sig")  # a leading BOM (Windows editors) is not JSON
    except FileNotFoundError:
        raise CrfError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise CrfError(f"{path}: cannot read ({e.__class__.__name__})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise CrfError(f"{path}: malformed JSON ({e.msg} at line {e.lineno})") from None
    except (RecursionError, ValueError) as e:  # nested past Python's stack, or an integer past 4300 digits
        raise CrfError(f"{path}: malformed JSON ({'nested too deeply' if isinstance(e, RecursionError) else 'a number too long'})") from None


def _write_with(path: str | os.PathLike, writer: Callable[[Path], None]) -> None:
    with atomic_path(path) as tmp:
        writer(tmp)


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write a float [H, W, C] image in [0, 1] (C = 1, 3 or 4) or a uint8 array as 8-bit PNG."""
    from PIL import Image

    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        arr = np.clip(np.round(np.nan_to_num(arr.astype(np.float64)) * 255.0), 0, 255).astype(np.uint8)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    _write_with(path, lambda tmp: Image.fromarray(np.ascontiguousarray(arr)).save(tmp, format="PNG"))


def _integer_range(path: Path, im, arr: np.ndarray) -> float:
    """The full-scale value of a 16- or 32-bit integer image: 65535 for 16-bit modes (and a
    PNG's ``I``, which older Pillows give 16-bit PNGs); a 32-bit ``I`` image (TIFF) is judged
    by its values, 255 when none exceeds it (an 8-bit image saved as 32-bit integers read
    250× too dark as 16-bit), 65535 up to that, else refused."""
    if im.mode != "I" or im.format == "PNG":
        return 65535.0
    low, top = (float(arr.min()), float(arr.max())) if arr.size else (0.0, 0.0)
    if low < 0 or top > 65535:
        raise CrfError(f"{path}: 32-bit integer values outside 0–65535 have no range to read them by: save it as an 8- or 16-bit PNG")
    return 255.0 if top <= 255 else 65535.0


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an 8-bit image as float32 [H, W, C] in [0, 1] with C = 3 (RGB) or 4 (RGBA).

    Grayscale, palette and 16-bit images are converted; anything Pillow cannot decode is a
    one-line :class:`CrfError`.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    piped = piped_input(path)
    if piped is None and not path.is_file():  # a device would block the read for ever
        raise CrfError(f"{path}: {not_a_file(path)}")
    try:
        with Image.open(io.BytesIO(piped) if piped is not None else path) as im:
            im.load()
            if im.mode == "F":  # floats: no range to read them by (NaN, 0/1, 0/255 all occur)
                raise CrfError(f"{path}: image mode F (32-bit float) is not supported: save it as an 8- or 16-bit PNG")
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                arr = np.asarray(im, dtype=np.float64)
                arr = arr / _integer_range(path, im, arr)
                return np.repeat(arr[..., None], 3, axis=2).astype(np.float32)
            has_alpha = im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info)
            im = im.convert("RGBA" if has_alpha else "RGB")
            return np.asarray(im, dtype=np.float32) / 255.0
    except FileNotFoundError:
        raise CrfError(f"{path}: file not found") from None
    except Image.DecompressionBombError as e:  # before its pixels are decoded
        raise CrfError(f"{path}: image too large to read ({' '.join(str(e).split()[:4])})") from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        raise CrfError(f"{path}: not a readable image ({e.__class__.__name__})") from None


def write_exr(path: str | os.PathLike, channels: dict[str, np.ndarray]) -> None:
    """Write float32 [H, W] channels (e.g. ``{"Z": depth}``) to a ZIP-compressed scanline EXR.

    Arrays are made contiguous float32 first: OpenEXR silently writes a non-contiguous array
    wrong and rejects float64.
    """
    import OpenEXR

    data = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    _write_with(path, lambda tmp: OpenEXR.File(header, data).write(str(tmp)))


def read_exr(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read every channel of an EXR file as float32 [H, W] arrays."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise CrfError(f"{path}: file not found")
    try:
        with OpenEXR.File(str(path)) as f:
            out = {}
            for name, channel in f.channels().items():
                pixels = np.array(channel.pixels, dtype=np.float32)
                if pixels.ndim == 3:  # OpenEXR 3 groups R, G, B(, A) into one "RGB(A)" channel
                    for i, c in enumerate(name if len(name) == pixels.shape[2] else "RGBA"[: pixels.shape[2]]):
                        out[c] = np.ascontiguousarray(pixels[..., i])
                else:
                    out[name] = pixels
            return out
    except Exception as e:  # OpenEXR raises bare exceptions for corrupt files
        raise CrfError(f"{path}: not a readable EXR file ({e.__class__.__name__})") from None
