"""Chairs from Sweet Home 3D furniture catalogs (``.sh3f``), ready for ``dataset from-meshes``.

A ``.sh3f`` file is a zip holding a ``PluginFurnitureCatalog.properties`` (Java properties,
ISO-8859-1 with ``\\uHHHH`` escapes) and one folder per model (OBJ + MTL + textures, often a
license file).  Model ``N`` is described by keys ``name#N``, ``category#N``, ``creator#N``,
``model#N`` (path inside the zip), ``width#N`` / ``depth#N`` / ``height#N`` (cm) and an optional
``modelRotation#N`` (a row-major 3×3 matrix that turns the file's axes into Sweet Home 3D's
Y-up frame); the catalog-wide ``license`` key holds the license.  Debian ships five such
catalogs in ``sweethome3d-furniture`` (``/usr/share/sweethome3d/furniture/*.sh3f``).

:func:`extract_model` writes ``<stem>/<stem>.obj`` with its MTL, textures and license file, plus
the sidecar ``<stem>/<stem>.meta.json`` that ``dataset from-meshes`` reads: the attribution
(name, title, creator, license, license URL, source) and the rotation.
"""

from __future__ import annotations

import posixpath
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path

from ..errors import DataError
from ..io import write_json

CATALOG_PROPERTIES = "PluginFurnitureCatalog.properties"
DEBIAN_CATALOG_DIR = Path("/usr/share/sweethome3d/furniture")

_CHAIR_NAME = re.compile(r"(?i)\b(arm)?chairs?\b")
_MODEL_FILE_SUFFIXES = (".obj", ".mtl", ".png", ".jpg", ".jpeg", ".bmp", ".gif", ".tga")
CATALOG_LICENSE = "LICENSE.TXT"
_SOURCE_URL = re.compile(r"https?://[^\s\"'<>]+")
_LICENSE_URL = re.compile(r"https?://creativecommons\.org/[^\s\"'<>]+")
_BLEND_TITLE = re.compile(r"Blend #\d+: ([^<]+)<|downloading \"([^\"]+)\"")  # Blend Swap license files


@dataclass(frozen=True)
class CatalogModel:
    """One furniture model of a catalog (key index ``index``: ``name#index`` and so on)."""

    catalog: Path  # the .sh3f file
    index: int
    id: str
    name: str
    category: str
    creator: str
    license: str  # the catalog's license line
    model: str  # path of the OBJ inside the zip, no leading "/"
    size: tuple[float, float, float]  # width (x), depth (z), height (y) in cm, Sweet Home 3D axes
    rotation: tuple[tuple[float, float, float], ...] | None  # row-major 3×3, file → Y-up


def read_properties(text: str) -> dict[str, str]:
    """Parse Java ``.properties`` text: comments, ``\\`` line continuations, ``=``/``:``/space
    separators and backslash escapes (``\\uHHHH``, ``\\n``, ``\\t``, ``\\=`` …).

    >>> read_properties("a=1\\nb : two \\\\\\n   words\\n# c=3\\nd=caf\\\\u00e9")
    {'a': '1', 'b': 'two words', 'd': 'café'}
    """
    logical: list[str] = []
    pending = ""
    for raw in text.splitlines():
        line = raw.lstrip() if not pending else raw.lstrip(" \t\f")
        if not pending and (not line or line[0] in "#!"):
            continue
        trailing = len(line) - len(line.rstrip("\\"))
        if trailing % 2 == 1:  # an odd number of backslashes continues the line
            pending += line[:-1]
            continue
        logical.append(pending + line)
        pending = ""
    if pending:
        logical.append(pending)

    out: dict[str, str] = {}
    for line in logical:
        key_end, i = len(line), 0
        while i < len(line):
            c = line[i]
            if c == "\\":
                i += 2
                continue
            if c in "=: \t\f":
                key_end = i
                break
            i += 1
        rest = line[key_end:].lstrip(" \t\f")
        if rest[:1] in ("=", ":"):
            rest = rest[1:].lstrip(" \t\f")
        out[_unescape(line[:key_end])] = _unescape(rest)
    return out


def _unescape(s: str) -> str:
    simple = {"t": "\t", "n": "\n", "r": "\r", "f": "\f"}

    def sub(m: re.Match) -> str:
        e = m.group(1)
        if e.startswith("u"):
            return chr(int(e[1:], 16))
        return simple.get(e, e)

    return re.sub(r"\\(u[0-9a-fA-F]{4}|.)", sub, s)


def list_models(catalog: str | Path) -> list[CatalogModel]:
    """All models of one ``.sh3f`` catalog, in key order."""
    catalog = Path(catalog)
    try:
        with zipfile.ZipFile(catalog) as z:
            text = z.read(CATALOG_PROPERTIES).decode("latin-1")
    except FileNotFoundError:
        raise DataError(f"{catalog}: file not found") from None
    except KeyError:
        raise DataError(f"{catalog}: no {CATALOG_PROPERTIES} inside (not a furniture catalog)") from None
    except (zipfile.BadZipFile, OSError) as e:
        raise DataError(f"{catalog}: not a readable .sh3f zip ({e.__class__.__name__})") from None
    props = read_properties(text)
    indices = sorted(int(k.split("#", 1)[1]) for k in props if re.fullmatch(r"name#\d+", k))
    models = []
    for n in indices:
        model = props.get(f"model#{n}", "").lstrip("/")
        if not model.lower().endswith(".obj"):
            continue  # Sweet Home 3D also accepts .3ds/.dae/.zip models; from-meshes reads OBJ here
        try:
            size = tuple(float(props.get(f"{k}#{n}", "nan")) for k in ("width", "depth", "height"))
            rotation = _rotation(props.get(f"modelRotation#{n}"))
        except ValueError:
            raise DataError(f"{catalog}: model #{n} has a malformed size or modelRotation") from None
        models.append(
            CatalogModel(
                catalog=catalog,
                index=n,
                id=props.get(f"id#{n}", f"#{n}"),
                name=props[f"name#{n}"].strip(),
                category=props.get(f"category#{n}", "").strip(),
                creator=props.get(f"creator#{n}", "").strip(),
                license=" ".join(props.get("license", "").split()),
                model=model,
                size=size,  # type: ignore[arg-type]
                rotation=rotation,
            )
        )
    return models


def _rotation(value: str | None) -> tuple[tuple[float, float, float], ...] | None:
    if value is None:
        return None
    v = [float(x) for x in value.split()]
    if len(v) != 9:
        raise ValueError(value)
    return (tuple(v[0:3]), tuple(v[3:6]), tuple(v[6:9]))  # type: ignore[return-value]


def is_chair(model: CatalogModel, min_height_ratio: float = 0.7) -> bool:
    """A chair: the name says chair or armchair (not wheelchair), and it stands at least
    ``min_height_ratio`` × its larger footprint side tall — which leaves out deck chairs, pool
    loungers and ottomans, whose catalog names also say "chair".

    >>> m = CatalogModel(Path("c.sh3f"), 1, "x", "Deck chair", "", "", "", "a.obj", (71, 125, 82), None)
    >>> is_chair(m), is_chair(m.__class__(**{**m.__dict__, "size": (45, 50, 90)}))
    (False, True)
    """
    width, depth, height = model.size
    if not _CHAIR_NAME.search(model.name):
        return False
    return height >= min_height_ratio * max(width, depth)


def find_chairs(catalogs: list[Path]) -> list[CatalogModel]:
    """The chairs of ``catalogs`` (in the given order, then key order)."""
    return [m for c in catalogs for m in list_models(c) if is_chair(m)]


def material_count(model: CatalogModel) -> int:
    """Distinct ``usemtl`` materials of the model's OBJ: the parts ``from-meshes`` will find."""
    try:
        with zipfile.ZipFile(model.catalog) as z:
            text = z.read(model.model).decode("latin-1")
    except (KeyError, zipfile.BadZipFile, OSError) as e:
        raise DataError(f"{model.catalog}: cannot read {model.model} ({e.__class__.__name__})") from None
    return len(set(re.findall(r"(?m)^\s*usemtl\s+(.*?)\s*$", text))) or 1


def pick_chairs(catalogs: list[Path], count: int | None = None, min_parts: int = 2) -> list[CatalogModel]:
    """The chairs of ``catalogs`` with at least ``min_parts`` materials; ``count`` of them
    spread evenly over that list (so every catalog contributes), or all when ``count`` is None."""
    chairs = [m for m in find_chairs(catalogs) if material_count(m) >= min_parts]
    if count is None or count >= len(chairs):
        return chairs
    return [chairs[(k * len(chairs)) // count] for k in range(count)]


def debian_catalogs(folder: Path = DEBIAN_CATALOG_DIR) -> list[Path]:
    """The ``.sh3f`` catalogs of Debian's ``sweethome3d-furniture``, sorted by name."""
    catalogs = sorted(Path(folder).glob("*.sh3f"))
    if not catalogs:
        raise DataError(f"{folder}: no .sh3f catalogs (apt-get install sweethome3d-furniture)")
    return catalogs


def model_stem(model: CatalogModel) -> str:
    """A file-safe, catalog-unique instance name: ``<catalog>_<model file stem>``, lower case
    (``BlendSwap-CC-0.sh3f`` + ``oakChair.obj`` → ``blendswap_cc_0_oak_chair``)."""
    file_stem = posixpath.splitext(posixpath.basename(model.model))[0]
    file_stem = re.sub(r"([a-z0-9])([A-Z])", r"\1_\2", file_stem)  # oakChair -> oak_Chair
    return re.sub(r"[^a-z0-9]+", "_", f"{model.catalog.stem}_{file_stem}".lower()).strip("_")


def extract_model(model: CatalogModel, out_dir: str | Path) -> Path:
    """Extract ``model``'s folder into ``out_dir/<stem>/`` and return the path of its OBJ.

    The OBJ is renamed ``<stem>.obj`` (its ``mtllib`` line still names the MTL, which keeps its
    name); textures and the model's own license file come along; ``<stem>.meta.json`` carries
    the attribution and ``modelRotation``.  The source is the model's Blend Swap page (and the
    title its license file gives it) when the model folder has such a file, else the catalog
    entry; the license URL comes from the catalog's ``LICENSE.TXT``.
    """
    stem = model_stem(model)
    folder = Path(out_dir) / stem
    folder.mkdir(parents=True, exist_ok=True)
    model_dir = posixpath.dirname(model.model)
    source = f"Sweet Home 3D furniture catalog {model.catalog.name}, model {model.id}"
    title = license_url = None
    try:
        with zipfile.ZipFile(model.catalog) as z:
            if CATALOG_LICENSE in z.namelist():
                urls = _LICENSE_URL.findall(z.read(CATALOG_LICENSE).decode("latin-1"))
                license_url = urls[0] if urls else None
            members = [
                i for i in z.infolist()
                if not i.is_dir() and posixpath.dirname(i.filename) == model_dir
            ]
            if model.model not in {i.filename for i in members}:
                raise DataError(f"{model.catalog}: {model.model} is listed but not in the zip")
            for info in members:
                base = posixpath.basename(info.filename)
                data = z.read(info)
                if info.filename == model.model:
                    (folder / f"{stem}.obj").write_bytes(data)
                elif base.lower().endswith(_MODEL_FILE_SUFFIXES):
                    (folder / base).write_bytes(data)
                else:  # a license file: keep it, and take the model's web page and title from it
                    (folder / base).write_bytes(data)
                    text = data.decode("latin-1")
                    urls = [u for u in _SOURCE_URL.findall(text) if "/blends/view/" in u]
                    if urls:
                        source = urls[0]
                    found = _BLEND_TITLE.search(text)
                    if found:
                        title = " ".join(next(g for g in found.groups() if g).split())
    except (zipfile.BadZipFile, OSError) as e:
        raise DataError(f"{model.catalog}: cannot extract {model.model} ({e.__class__.__name__})") from None
    meta = {"name": model.name, "title": title, "creator": model.creator, "license": model.license,
            "license_url": license_url, "source": source}
    meta = {k: v for k, v in meta.items() if v}
    if model.rotation is not None:
        meta["rotation"] = [list(r) for r in model.rotation]
    write_json(folder / f"{stem}.meta.json", meta)
    return folder / f"{stem}.obj"
