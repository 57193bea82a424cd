"""User input of an edit: scribble masks (PNG or strokes JSON), colours, and the rays they pick.

Masks are bool [H, W] at the edited view's resolution, True where the user scribbled.  Pixel
coordinates are (x, y) = (column, row) with row 0 at the top, as in the images.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..errors import CrfError
from ..io import piped_input, read_image, read_json
from ..masks import as_mask, strokes_mask


def require_on_object(covered: int) -> None:
    """One-line error when no scribbled pixel covers the object (``covered``: how many do, their
    rendered opacity at least the selection's MIN_OPACITY), whichever method edits."""
    if covered == 0:
        raise CrfError("the scribble lies on the background only: no scribbled pixel covers the object in its view")


def _css_colors() -> dict[str, str]:
    """The CSS named colours (all 148, as Pillow's ``ImageColor`` holds them) → ``#rrggbb``."""
    from PIL import ImageColor

    return dict(ImageColor.colormap)


CSS_COLORS = _css_colors()
"""The CSS named colours (red, navy, orange, darkred, gold, ...; grey and gray alike)."""


def parse_color(text: str, label: str = "colour") -> tuple[float, float, float]:
    """``#rgb``, ``#rrggbb``, ``rgb(R, G, B)`` (0–255) or a CSS colour name → RGB in [0, 1].

    ``parse_color("#f80") == parse_color("#ff8800") == (1.0, 0.533…, 0.0)``; ``"red"`` → (1, 0, 0);
    a name may carry spaces, hyphens or capitals (``"Dark Red"`` is ``darkred``).  ``label``
    starts the error line: the CLI passes its option (``--color``), a library caller named none.
    """
    value = str(text).strip().lower()
    value = CSS_COLORS.get(re.sub(r"[\s_-]+", "", value), value)
    m = re.fullmatch(r"rgb\(\s*(\d{1,3})\s*,\s*(\d{1,3})\s*,\s*(\d{1,3})\s*\)", value)
    if m and all(int(c) <= 255 for c in m.groups()):
        return tuple(int(c) / 255.0 for c in m.groups())  # type: ignore[return-value]
    m = re.fullmatch(r"#([0-9a-f]{3}|[0-9a-f]{6})", value)
    if not m:
        raise CrfError(f"{label} {text!r}: expected #rgb, #rrggbb, rgb(R, G, B) with R, G, B from 0 to 255, "
                       "or a CSS colour name (red, navy, darkred, gold, ...)")
    digits = m.group(1)
    if len(digits) == 3:
        digits = "".join(c * 2 for c in digits)
    return tuple(int(digits[i : i + 2], 16) / 255.0 for i in (0, 2, 4))  # type: ignore[return-value]


def as_rgb(color) -> tuple[float, float, float]:
    """An edit's target colour as RGB in [0, 1]: a string :func:`parse_color` reads, or three
    numbers each from 0 to 1 (a 0–255 triple is refused, not trained toward)."""
    if isinstance(color, str):
        return parse_color(color)
    try:
        rgb = tuple(float(c) for c in color)
    except (TypeError, ValueError):
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):  # NaN fails the range test too
        raise CrfError(f"color {color!r}: expected a colour string or three numbers (R, G, B) from 0 to 1")
    return rgb  # type: ignore[return-value]


def default_radius(width: int) -> float:
    return max(1.0, width / 48)


STROKE_REACH = 1e4
"""A stroke point farther than this many view widths from the view is refused (at 10³⁰⁸ the
rasterizer's float arithmetic overflowed into warnings and a false "outside the view")."""


def strokes_json_mask(data, width: int, height: int, where: str) -> np.ndarray:
    """Rasterize strokes JSON at (width, height): ``{"strokes": [[[x, y], …], …], "radius": r}``
    or a bare list of strokes ``[[[x, y], …], …]``; the radius defaults to max(1, width/48) px.
    A stroke may carry its own radius as ``{"points": [[x, y], …], "radius": r}`` (the form
    ``crfedit ui`` writes when strokes were drawn at different sizes)."""
    radius = default_radius(width)
    strokes = data
    if isinstance(data, dict):
        strokes = data.get("strokes")
        if "radius" in data:
            radius = _radius(data["radius"], width, height, where)
    if not isinstance(strokes, list):
        raise CrfError(f"{where}: expected {{\"strokes\": [[[x, y], ...], ...], \"radius\": r}} or a list of strokes")
    mask = np.zeros((height, width), dtype=bool)
    points = []
    for i, stroke in enumerate(strokes):
        r = radius
        if isinstance(stroke, dict):
            r = _radius(stroke.get("radius", radius), width, height, f"{where}: stroke {i}")
            stroke = stroke.get("points")
        ok = isinstance(stroke, list) and len(stroke) > 0 and all(
            isinstance(p, list) and len(p) == 2 and all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in p)
            for p in stroke
        )
        try:
            pts = np.asarray(stroke, dtype=np.float64) if ok else None
        except OverflowError:  # an integer with hundreds of digits: no float holds it
            pts = np.full((1, 2), np.inf)
        if pts is None or np.isnan(pts).any():
            raise CrfError(f"{where}: stroke {i} is not a list of [x, y] pixel positions")
        if not np.isfinite(pts).all() or np.abs(pts).max() > STROKE_REACH * max(width, height):  # far enough to overflow the distance arithmetic
            raise CrfError(f"{where}: stroke {i} has a point more than {STROKE_REACH:g} view widths away from the "
                           f"{width}x{height} view (x from 0 to {width - 1}, y from 0 to {height - 1})")
        mask |= strokes_mask((height, width), [pts], r)
        points.append(pts)
    if min(width, height) >= 8 and all(((p >= 0) & (p <= 1)).all() for p in points) and any((p % 1 != 0).any() for p in points):
        raise CrfError(f"{where}: every point lies between 0 and 1, as fractions of the view would; stroke points are pixels "
                       f"(x from 0 to {width - 1}, y from 0 to {height - 1})")
    if points and not mask.any():  # no strokes at all is an empty mask, which its reader judges
        raise CrfError(f"{where}: every stroke lies outside the {width}x{height} view (x from 0 to {width - 1}, y from 0 to {height - 1})")
    return mask


def _radius(r, width: int, height: int, where: str) -> float:
    if isinstance(r, bool) or not isinstance(r, (int, float)) or not 0 < r <= max(width, height):
        raise CrfError(f"{where}: radius must be a number of pixels above 0 and at most the view's size ({max(width, height)})")
    return float(r)


GRAY_TOLERANCE = 0.05
"""A pixel whose channels differ by at most this much is gray (a white-on-black mask)."""
PAINT_TOLERANCE = 0.1
"""A painted pixel differs from the render of its view by more than this in some channel."""
MAX_COVERAGE = 0.5
"""A scribble over more of the view than this is refused unless forced."""


class Scribble(NamedTuple):
    mask: np.ndarray  # [H, W] bool, True where the user scribbled
    reading: str  # how the image was read, for the user: "white on black", ...


def read_scribble(path: Path, width: int, height: int, what: str, render: Callable[[], np.ndarray] | None = None) -> Scribble:
    """Read a scribble image the way it was drawn, trying in turn:

    1. some pixels transparent: the opaque pixels (coloured or white strokes on a transparent PNG);
    2. every pixel gray: white on black (brightness ≥ 0.5);
    3. at least half the pixels black (every channel ≤ 0.1): coloured strokes on black, the
       pixels that are not black (red strokes on black were refused; a dark green brush of 0.39
       read as no stroke); strokes of two saturated colours (red and blue, as edits.png draws
       the scribble and the keep strokes) are refused: one image is one kind of stroke;
    4. ``render()`` (the view's render, float [H, W, 3]) matches at least half the pixels:
       strokes painted over the render, i.e. the pixels differing from it by more than
       ``PAINT_TOLERANCE``.
    Anything else is a :class:`CrfError` naming the ways.
    """
    image = read_image(path)
    if image.shape[:2] != (height, width):
        raise CrfError(
            f"{path}: {what} mask is {image.shape[1]}x{image.shape[0]} but the view is {width}x{height} (draw it on a render of that view)"
        )
    rgb = image[..., :3]
    if image.shape[2] == 4 and (image[..., 3] < 0.5).any():
        alpha = image[..., 3]
        if 0.0 < float(alpha.max()) <= 1.5 / 255.0:  # a 0/1 mask saved as the alpha channel without scaling
            return Scribble(alpha > 0.0, "0/1 alpha values (a mask saved without scaling to 255)")
        _one_colour(path, what, rgb[alpha >= 0.5])
        return Scribble(alpha >= 0.5, "opaque pixels of a transparent PNG")
    if (rgb.max(axis=-1) - rgb.min(axis=-1) <= GRAY_TOLERANCE).all():
        gray = rgb.mean(axis=-1)
        if float(gray.max()) == 0.0:  # all black: no stroke (read as grey strokes on black, it said "grey strokes" of 0 pixels)
            return Scribble(np.zeros(gray.shape, dtype=bool), "an all-black image: no stroke")
        if 0.0 < float(gray.max()) <= 1.5 / 255.0:  # numpy's 0/1 mask saved as is (Image.fromarray(mask.astype(np.uint8)))
            return Scribble(gray > 0.0, "0/1 values (a mask saved without scaling to 255)")
        if not (gray >= 0.5).any() and (gray <= 0.1).mean() >= 0.5:  # a dark grey brush on black, as a dark coloured one
            return Scribble(gray > 0.1, "grey strokes on black")
        return Scribble(gray >= 0.5, "white on black")
    brightest = rgb.max(axis=-1)
    if (brightest <= 0.1).mean() >= 0.5:  # renders are on white: a black ground is a mask's
        strokes = brightest > 0.1
        _one_colour(path, what, rgb[strokes])
        return Scribble(strokes, "coloured strokes on black")
    if render is not None:
        differs = (np.abs(rgb - np.clip(render(), 0.0, 1.0)) > PAINT_TOLERANCE).any(axis=-1)
        if differs.mean() <= 0.5:
            painted = _painted(rgb, differs)
            if painted is not None and painted.sum() < differs.sum():
                return Scribble(painted, f"strokes painted over the render of the view ({int(painted.sum())} pixels of the brush's "
                                         f"colour; {int((differs & ~painted).sum())} more differ from the render and are left out: "
                                         "drawn over another render, or without the --edit files it shows?)")
            _one_colour(path, what, rgb[differs])
            return Scribble(differs, "strokes painted over the render of the view (pixels that differ from it)")
    raise CrfError(
        f"{path}: cannot tell the {what} strokes from the background: draw white or coloured strokes on black or on a "
        "transparent PNG, or strokes over a render of this very view (crfedit render ... --views VIEW)"
    )


BRUSH_SHARE = 5
"""A brush's flat colour stands out among the pixels that differ from the render when it is at
least this many times as common as the next colour (and covers 4 pixels or more)."""


def _painted(rgb: np.ndarray, differs: np.ndarray) -> np.ndarray | None:
    """[H, W] the pixels of ``differs`` in the brush's colour (within ``PAINT_TOLERANCE``), when
    one flat colour stands out among them (:data:`BRUSH_SHARE`); None when none does (strokes
    of varied colour, a JPEG).  A stroke painted over the render of an edited stack given
    without its ``--edit``, or over the dataset's own image, also differs wherever those
    differ from the render, and every such pixel was read as scribbled: a tester's 21-pixel
    stroke on a seat came with the 557 pixels of arms an earlier edit had turned blue."""
    values, counts = np.unique(np.round(rgb[differs] * 255).astype(np.int64), axis=0, return_counts=True)
    if len(counts) == 0:
        return None
    order = np.argsort(counts)[::-1]
    top, second = counts[order[0]], counts[order[1]] if len(counts) > 1 else 0
    if top < 4 or top < BRUSH_SHARE * second:
        return None
    return differs & (np.abs(rgb - values[order[0]] / 255.0) <= PAINT_TOLERANCE).all(axis=-1)


def _one_colour(path: Path, what: str, strokes: np.ndarray) -> None:
    """Refuse strokes of two saturated hues (``strokes`` [n, 3], whatever the ground: black,
    transparent or the render): red and blue in one image are the scribble and the keep strokes
    of the README's pictures, and read as one mask the keep strokes would be edited.  Hues are
    six 60° sectors; a second one refuses from 5 % of the saturated stroke pixels."""
    saturated = strokes[(strokes.max(axis=-1) - strokes.min(axis=-1)) > 0.3]
    if len(saturated) < 2:
        return
    r, g, b = saturated[:, 0], saturated[:, 1], saturated[:, 2]
    hue = np.degrees(np.arctan2(np.sqrt(3.0) * (g - b), 2.0 * r - g - b)) % 360.0
    sectors = np.bincount(((hue + 30.0) // 60.0).astype(int) % 6, minlength=6) / len(saturated)
    hues = [name for name, share in zip(("red", "yellow", "green", "cyan", "blue", "magenta"), sectors) if share >= 0.05]
    if len(hues) > 1:
        raise CrfError(f"{path}: the {what} holds strokes of two colours ({' and '.join(hues)}): one image is one kind of stroke; "
                       "give the part's strokes as --scribble and what to keep as --keep, each its own image")


def _json_content(path: Path) -> bool:
    """Whether ``path`` holds JSON rather than an image, by its first bytes (a pipe has no suffix,
    nor does every file): ``{`` or ``[`` after a BOM and white space."""
    piped = piped_input(path)
    if piped is not None:
        head = piped[:64]
    else:
        try:
            with open(path, "rb") as f:
                head = f.read(64)
        except OSError:
            return False  # the image reader names the problem
    return head.lstrip(b"\xef\xbb\xbf").lstrip().startswith((b"{", b"["))


def load_mask(
    png: Path | None, strokes: Path | None, width: int, height: int, what: str, render: Callable[[], np.ndarray] | None = None
) -> Scribble | None:
    """The union of a mask image (read by :func:`read_scribble`) and a strokes JSON (either may be
    None) at the view's size; None when neither is given. An "image" whose name ends in ``.json``
    is read as strokes, so ``--scribble strokes.json`` means the same to every command."""
    mask, readings = None, []
    for path, is_png in ((png, True), (strokes, False)):
        if path is None:
            continue
        if is_png and Path(path).suffix.lower() != ".json" and not _json_content(Path(path)):
            drawn, reading = read_scribble(Path(path), width, height, what, render)
        else:
            drawn, reading = strokes_json_mask(read_json(Path(path)), width, height, str(path)), "strokes JSON"
            if not drawn.any():  # (the empty-mask line asks for white strokes on black, a PNG's reading)
                raise CrfError(f"{path}: holds no strokes: an empty {what}")
        mask = drawn if mask is None else mask | drawn
        readings.append(reading)
    return None if mask is None else Scribble(mask, " + ".join(readings))


FEW_SCRIBBLED = 4
"""A scribble of fewer pixels gets a note: one pixel on a seat recoloured a third of it and
tinted the arms (the selection has almost nothing to learn the part from)."""


def few_pixels_note(scribble: np.ndarray) -> str | None:
    """The note for a scribble of fewer than :data:`FEW_SCRIBBLED` pixels (None otherwise)."""
    n = int(np.sum(scribble))
    if n >= FEW_SCRIBBLED or n == 0:
        return None
    return (f"a scribble of {n} pixel{'s' * (n != 1)} says little about the part: the selection may take too little or "
            "too much of it (draw along the part, and check it with select --preview)")


def check_coverage(scribble: np.ndarray, force: bool = False) -> float:
    """The scribbled fraction of the view; above ``MAX_COVERAGE`` a :class:`CrfError` unless ``force``
    (a scribble over most of the view is usually a misread image, e.g. the whole render)."""
    fraction = float(np.mean(scribble))
    if fraction == 1.0:
        raise CrfError("the scribble covers the whole view: nothing is left to keep (scribble only the part to edit)")
    if fraction > MAX_COVERAGE and not force:
        raise CrfError(
            f"the scribble covers {100 * fraction:.1f} % of the view (more than half): scribble only the part to edit, "
            "or pass --force if that is really meant"
        )
    return fraction


KEEP_OVERLAP = 0.25
"""Share of the scribbled pixels the keep strokes may cover before :func:`keep_overlap` warns."""


def keep_overlap(scribble: np.ndarray, keep: np.ndarray | None) -> str | None:
    """A warning when the keep strokes cover much of the scribble (None otherwise): keep
    strokes mark what must *not* change, and over the part they make the selection leave the
    part itself out (a tester's keep drawn as the scribble grown by 3 px: seat IoU 0.87 → 0.32)."""
    if keep is None or not scribble.any():
        return None
    share = float((scribble & keep).sum()) / float(scribble.sum())
    if share <= KEEP_OVERLAP:
        return None
    return (f"the keep strokes cover {share:.0%} of the scribbled pixels: keep strokes mark what must not change, so the "
            "part you scribbled is held back; draw them on the other parts")


def check_masks(scribble, keep, width: int, height: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Validate an edit's masks (any :func:`~crfedit.masks.as_mask` takes); returns the
    scribble and the keep mask minus the scribble (the scribble wins) as bool ndarrays."""
    scribble = as_mask(scribble, "scribble")
    keep = None if keep is None else as_mask(keep, "keep")
    for what, mask in (("scribble", scribble), ("keep", keep)):
        if mask is not None and tuple(mask.shape) != (height, width):
            raise CrfError(f"{what} mask is {mask.shape[1]}x{mask.shape[0]} but the view is {width}x{height}")
    if not scribble.any():
        raise CrfError("the scribble is empty: no pixel is set (white strokes on black, 8-bit PNG)")
    if scribble.all():
        raise CrfError("the scribble covers the whole view: nothing is left to keep (scribble only the part to edit)")
    if keep is None:
        return scribble, None
    if keep.all():
        raise CrfError("the keep mask covers the whole view (an all-white mask?): scribble only what must not change")
    return scribble, keep_outside(scribble, keep)


def keep_outside(scribble: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The keep mask minus the scribble (the scribble wins); one that keeps no pixel is an error
    (an empty PNG given as --keep is a slip, not a request for no keep strokes: that is none)."""
    keep = keep & ~scribble
    if not keep.any():
        raise CrfError("the keep mask has no pixel outside the scribble (empty, or all under the scribble; "
                       "--keep none gives a view without keep strokes)")
    return keep


def pick_pixels(
    scribble: np.ndarray, keep: np.ndarray | None, max_rays: int, generator: torch.Generator, also_random: bool = False
) -> tuple[Tensor, Tensor]:
    """(foreground pixel indices, background pixel indices), flat row-major, for an edit.

    Foreground: the scribble (a random third of ``max_rays`` if it has more pixels).
    Background: the keep mask, else — or also, with ``also_random`` — a seeded random sample of
    the rest of the view twice the size of the foreground; together at most ``max_rays``.
    """
    if max_rays < 2:
        raise CrfError(f"--rays {max_rays}: need at least 2")
    fg = torch.from_numpy(np.flatnonzero(scribble))
    if fg.numel() > max(1, max_rays // 3):
        fg = fg[torch.randperm(fg.numel(), generator=generator)[: max(1, max_rays // 3)]].sort().values
    room = max_rays - fg.numel()
    parts = []
    if keep is not None:
        kept = torch.from_numpy(np.flatnonzero(keep))
        if kept.numel() > room:
            kept = kept[torch.randperm(kept.numel(), generator=generator)[:room]].sort().values
        parts.append(kept)
        room -= kept.numel()
    if keep is None or also_random:
        rest = ~scribble if keep is None else ~(scribble | keep)
        pool = torch.from_numpy(np.flatnonzero(rest))
        n = min(2 * fg.numel(), room)
        parts.append(pool[torch.randperm(pool.numel(), generator=generator)[:n]].sort().values)
    return fg, torch.cat(parts) if parts else torch.zeros(0, dtype=torch.long)
