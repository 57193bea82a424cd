"""Procedural chairs rendered by exact analytic ray casting, with ground-truth edit twins.

A chair is a union of primitives — oriented boxes and cylinders — each tagged with a part
(seat, back, legs, arms, stretchers, slats, base, wheels).  Rays are intersected exactly
(slab test for boxes, quadratic + caps for cylinders), the nearest hit wins, and the hit is
shaded view-independently, ``albedo * (0.35 + 0.65 max(0, n·L))``, so a radiance field can fit
the images exactly.  World is Z-up; every chair is centered and scaled so its largest extent is
1 (it fits in [-0.5, 0.5]^3) and stands upright.
"""

from __future__ import annotations

import colorsys
import itertools
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..cameras import Camera, focal_from_angle, look_at, spherical_eye
from ..errors import CrfError
from ..io import atomic_folder, check_folder_target, write_png
from ..masks import dilate, erode, strokes_mask
from .format import Frame, TwinSpec, carry_extras, supersampled_frame, write_instances_txt, write_parts, write_split, write_twins_json
from .raycast import Primitive, box, camera_rays, cast_rays, cylinder, primitive_bounds, shade

CAMERA_RADIUS = 2.0
CAMERA_ANGLE_X = 0.6911
ELEVATION_RANGE = (10.0, 60.0)
PALETTE = (
    "#8b5a2b", "#c19a6b", "#d8c3a5", "#2f2f2f", "#e6e1d3", "#2a7f7f", "#d4a017", "#a23b2a",
    "#1f3a5f", "#8a9a5b", "#d8a7a7", "#5a6e7f", "#6b3e75", "#c46a2b", "#9c9c9c", "#3f6b3f",
)  # walnut, oak, beige, charcoal, cream, teal, mustard, brick, navy, sage, blush, slate, plum, rust, grey, forest
REMOVABLE_PARTS = ("arms", "stretchers", "slats")
RECOLORABLE_PARTS = ("seat", "back")


# ----------------------------------------------------------------------------- chairs


@dataclass(frozen=True)
class Part:
    id: int
    name: str
    color: str  # "#rrggbb"


@dataclass(frozen=True, eq=False)
class Chair:
    primitives: tuple[Primitive, ...]
    parts: tuple[Part, ...]

    def part(self, name: str) -> Part | None:
        return next((p for p in self.parts if p.name == name), None)

    def recolored(self, name: str, color: str) -> "Chair":
        return replace(self, parts=tuple(replace(p, color=color) if p.name == name else p for p in self.parts))

    def without(self, name: str) -> "Chair":
        gone = self.part(name).id
        return Chair(tuple(p for p in self.primitives if p.part != gone), tuple(p for p in self.parts if p.id != gone))

    def albedo_table(self) -> np.ndarray:
        """Linear-in-[0,1] rgb per part id (row 0 unused).  [max_id + 1, 3]"""
        table = np.ones((max(p.id for p in self.parts) + 1, 3))
        for p in self.parts:
            table[p.id] = hex_to_rgb(p.color)
        return table


def hex_to_rgb(color: str) -> np.ndarray:
    return np.array([int(color[i : i + 2], 16) for i in (1, 3, 5)]) / 255.0


def rgb_to_hex(rgb) -> str:
    return "#" + "".join(f"{int(round(float(np.clip(c, 0, 1)) * 255)):02x}" for c in rgb)


def _jitter(rng: np.random.Generator, color: str) -> str:
    h, s, v = colorsys.rgb_to_hsv(*hex_to_rgb(color))
    h = (h + rng.uniform(-0.02, 0.02)) % 1.0
    s = min(1.0, s * rng.uniform(0.85, 1.15))
    v = min(1.0, v * rng.uniform(0.9, 1.1))
    return rgb_to_hex(colorsys.hsv_to_rgb(h, s, v))


def contrasting_color(colors: list[str]) -> str:
    """The palette color farthest (max-min rgb distance) from every color in ``colors``."""
    used = np.stack([hex_to_rgb(c) for c in colors])
    scores = [np.linalg.norm(used - hex_to_rgb(c), axis=-1).min() for c in PALETTE]
    return PALETTE[int(np.argmax(scores))]


class _Builder:
    """Collects primitives and part ids while a chair is assembled."""

    def __init__(self):
        self.prims: list[Primitive] = []
        self.parts: list[Part] = []

    def part(self, name: str, color: str) -> int:
        existing = next((p for p in self.parts if p.name == name), None)
        if existing:
            return existing.id
        self.parts.append(Part(len(self.parts) + 1, name, color))
        return len(self.parts)

    def add(self, *prims: Primitive) -> None:
        self.prims.extend(prims)


def _post(b: _Builder, rounded: bool, x: float, y: float, z0: float, z1: float, thick: float, part: int) -> None:
    """A vertical leg/post from z0 to z1, square or round."""
    center = (x, y, 0.5 * (z0 + z1))
    if rounded:
        b.add(cylinder(center, 0.5 * thick, 0.5 * (z1 - z0), part))
    else:
        b.add(box(center, (0.5 * thick, 0.5 * thick, 0.5 * (z1 - z0)), part))


def _rail(b: _Builder, rounded: bool, center, length: float, thick: float, along_y: bool, part: int) -> None:
    """A horizontal rail along x or y, square or round."""
    if rounded:
        b.add(cylinder(center, 0.5 * thick, 0.5 * length, part, horizontal_yaw=0.5 * math.pi if along_y else 0.0))
    else:
        half = (0.5 * thick, 0.5 * length, 0.5 * thick) if along_y else (0.5 * length, 0.5 * thick, 0.5 * thick)
        b.add(box(center, half, part))


def make_chair(rng: np.random.Generator, arms: bool | None = None) -> Chair:
    """A random chair: seat, back, legs or base, optional arms/stretchers/slats; normalized.

    ``arms`` forces arms on (as chunky side panels, so they cover pixels) or off; None = random.
    """
    colors = [_jitter(rng, PALETTE[i]) for i in rng.permutation(len(PALETTE))]
    style = rng.choice(["four_leg", "office", "pedestal"], p=[0.6, 0.25, 0.15])
    b = _Builder()
    w, dp = rng.uniform(0.42, 0.6), rng.uniform(0.4, 0.56)
    round_seat = rng.random() < 0.2
    if round_seat:
        dp = w
    seat_top = rng.uniform(0.4, 0.52)
    st = rng.uniform(0.06, 0.1) if style == "office" else rng.uniform(0.035, 0.09)
    seat_bottom = seat_top - st
    seat = b.part("seat", colors[0])
    if round_seat:
        b.add(cylinder((0, 0, seat_top - 0.5 * st), 0.5 * w, 0.5 * st, seat))
    else:
        b.add(box((0, 0, seat_top - 0.5 * st), (0.5 * w, 0.5 * dp, 0.5 * st), seat))

    back = b.part("back", colors[0] if rng.random() < 0.3 else colors[1])
    bh, bt = rng.uniform(0.32, 0.6), rng.uniform(0.03, 0.07)
    bw = w * (rng.uniform(0.6, 0.85) if round_seat else rng.uniform(0.75, 1.0))
    yb = 0.5 * dp - 0.5 * bt
    gap = rng.uniform(0.03, 0.08) if style == "office" else 0.0
    if style != "office" and rng.random() < 0.45:
        pw, rh = rng.uniform(0.03, 0.05), rng.uniform(0.05, 0.1)
        x_post = 0.5 * bw - 0.5 * pw
        b.add(
            box((x_post, yb, seat_top + 0.5 * bh), (0.5 * pw, 0.5 * bt, 0.5 * bh), back),
            box((-x_post, yb, seat_top + 0.5 * bh), (0.5 * pw, 0.5 * bt, 0.5 * bh), back),
            box((0, yb, seat_top + bh - 0.5 * rh), (0.5 * bw, 0.5 * bt, 0.5 * rh), back),
        )
        slats = b.part("slats", colors[1] if rng.random() < 0.5 else colors[5])
        inner, z_low, z_high = x_post - 0.5 * pw, seat_top, seat_top + bh - rh
        if rng.random() < 0.6:
            n, sw = int(rng.integers(2, 6)), rng.uniform(0.02, 0.045)
            for k in range(n):
                x = -inner + (k + 1) * 2 * inner / (n + 1)
                b.add(box((x, yb, 0.5 * (z_low + z_high)), (0.5 * sw, 0.3 * bt, 0.5 * (z_high - z_low)), slats))
        else:
            n, sh = int(rng.integers(2, 4)), rng.uniform(0.03, 0.05)
            for k in range(n):
                z = z_low + (k + 1) * (z_high - z_low) / (n + 1)
                b.add(box((0, yb, z), (inner, 0.3 * bt, 0.5 * sh), slats))
    else:
        b.add(box((0, yb, seat_top + gap + 0.5 * bh), (0.5 * bw, 0.5 * bt, 0.5 * bh), back))
        if gap > 0:  # office backrest on a support bar
            z0, z1 = seat_bottom, seat_top + gap + 0.4 * bh
            b.add(box((0, yb + 0.5 * bt + 0.012, 0.5 * (z0 + z1)), (0.035, 0.012, 0.5 * (z1 - z0)), back))

    if style == "four_leg":
        legs = b.part("legs", colors[2])
        lt, inset, round_legs = rng.uniform(0.03, 0.06), rng.uniform(0.0, 0.04), rng.random() < 0.4
        if round_seat:
            lx = ly = (0.5 * w - 0.5 * lt - inset) * math.sqrt(0.5)
        else:
            lx, ly = 0.5 * w - 0.5 * lt - inset, 0.5 * dp - 0.5 * lt - inset
        for sx in (-1, 1):
            for sy in (-1, 1):
                _post(b, round_legs, sx * lx, sy * ly, 0.0, seat_bottom, lt, legs)
        if rng.random() < 0.45:
            stretch = b.part("stretchers", colors[2] if rng.random() < 0.8 else colors[4])
            zs, s_t = rng.uniform(0.08, 0.2), lt * rng.uniform(0.5, 0.8)
            for sx in (-1, 1):
                _rail(b, round_legs, (sx * lx, 0, zs), 2 * ly, s_t, True, stretch)
            if rng.random() < 0.5:  # H pattern
                _rail(b, round_legs, (0, 0, zs), 2 * lx, s_t, False, stretch)
            else:  # box pattern
                for sy in (-1, 1):
                    _rail(b, round_legs, (0, sy * ly, zs), 2 * lx, s_t, False, stretch)
    elif style == "office":
        base, wheels = b.part("base", colors[2]), b.part("wheels", colors[6])
        rw, th = rng.uniform(0.025, 0.035), rng.uniform(0.035, 0.05)
        reach, yaw0 = rng.uniform(0.24, 0.32), rng.uniform(0, 2 * math.pi / 5)
        z_star = 2 * rw + 0.5 * th - 0.005
        for k in range(5):
            yaw = yaw0 + 2 * math.pi * k / 5
            cx, cy = reach * math.cos(yaw), reach * math.sin(yaw)
            b.add(box((0.5 * cx, 0.5 * cy, z_star), (0.5 * reach, rng.uniform(0.02, 0.03), 0.5 * th), base, yaw))
            b.add(cylinder((cx, cy, rw), rw, rng.uniform(0.012, 0.02), wheels, horizontal_yaw=yaw + 0.5 * math.pi))
        b.add(cylinder((0, 0, z_star), 0.06, 0.5 * th + 0.005, base))
        _post(b, True, 0, 0, z_star, seat_bottom, 2 * rng.uniform(0.022, 0.035), base)
    else:
        base = b.part("base", colors[2])
        disk_h = rng.uniform(0.01, 0.025)
        b.add(cylinder((0, 0, disk_h), rng.uniform(0.2, 0.28), disk_h, base))
        _post(b, True, 0, 0, 2 * disk_h, seat_bottom, 2 * rng.uniform(0.03, 0.05), base)

    has_arms = rng.random() < 0.35 if arms is None else arms
    if has_arms:
        arm = b.part("arms", colors[3])
        al, ah = dp * rng.uniform(0.8, 1.0), rng.uniform(0.18, 0.26)
        y_mid = -0.5 * dp + 0.5 * al
        if arms or rng.random() < 0.5:  # side panels
            at = rng.uniform(0.05, 0.09)
            for sx in (-1, 1):
                center = (sx * (0.5 * w + 0.5 * at), y_mid, 0.5 * (seat_bottom + seat_top + ah))
                b.add(box(center, (0.5 * at, 0.5 * al, 0.5 * (ah + st)), arm))
        else:  # armrest on a front post
            aw, ath = rng.uniform(0.05, 0.08), rng.uniform(0.03, 0.05)
            for sx in (-1, 1):
                x = sx * (0.5 * w - 0.5 * aw)
                b.add(box((x, y_mid, seat_top + ah), (0.5 * aw, 0.5 * al, 0.5 * ath), arm))
                _post(b, True, x, -0.5 * dp + 0.1 * al, seat_top, seat_top + ah, 0.7 * aw, arm)
    return normalized(Chair(tuple(b.prims), tuple(b.parts)))


def normalized(chair: Chair) -> Chair:
    """Center the chair's bounding box at the origin and scale its largest extent to 1."""
    bounds = [primitive_bounds(p) for p in chair.primitives]
    lo = np.min([b[0] for b in bounds], axis=0)
    hi = np.max([b[1] for b in bounds], axis=0)
    mid, scale = 0.5 * (lo + hi), 1.0 / float(np.max(hi - lo))
    prims = tuple(replace(p, center=(p.center - mid) * scale, size=p.size * scale) for p in chair.primitives)
    return Chair(prims, chair.parts)


def render_chair(chair: Chair, camera: Camera, aa: int = 1, chunk: int = 1 << 15) -> Frame:
    """Exact render: rgba (white background), ray-distance depth (inf = miss), part ids.

    ``aa`` > 1 supersamples each pixel on an aa×aa grid and box-filters (alpha = coverage), as a
    real camera or Blender does; depth and part ids come from the pixel-center ray.
    """
    albedo = chair.albedo_table()

    def cast(offset: tuple[float, float]):
        origins, dirs = camera_rays(camera, offset)
        n = len(dirs)
        t, part, rgb = np.full(n, np.inf), np.zeros(n, np.int64), np.ones((n, 3))
        for s in range(0, n, chunk):
            hits = cast_rays(list(chair.primitives), origins[s : s + chunk], dirs[s : s + chunk])
            hit = hits.part > 0
            t[s : s + chunk], part[s : s + chunk] = hits.t, hits.part
            rgb[s : s + chunk][hit] = shade(hits.normal[hit], albedo[hits.part[hit]])
        return t, part, rgb, part > 0

    return supersampled_frame(camera, aa, cast)


# ----------------------------------------------------------------------------- views


def split_counts(views: int) -> tuple[int, int, int]:
    """(train, val, test) — 40/5/5 for 50 views, at least one val and test from 3 views on."""
    if views < 3:
        return views, 0, 0
    n = max(1, round(0.1 * views))
    return views - 2 * n, n, n


def sample_cameras(rng: np.random.Generator, views: int, res: int) -> dict[str, list[Camera]]:
    """Upper-hemisphere cameras at radius 2 looking at the origin; test azimuths evenly spaced."""
    focal = focal_from_angle(CAMERA_ANGLE_X, res)
    counts = dict(zip(("train", "val", "test"), split_counts(views)))
    cams = {}
    for split, n in counts.items():
        if n == 0:
            continue
        az = np.arange(n) * 360.0 / n if split == "test" else rng.uniform(0.0, 360.0, n)
        el = rng.uniform(*ELEVATION_RANGE, n)
        cams[split] = [Camera(look_at(spherical_eye(a, e, CAMERA_RADIUS)), focal, res, res) for a, e in zip(az, el)]
    return cams


# ----------------------------------------------------------------------------- scribbles


def random_strokes(rng: np.random.Generator, region: np.ndarray, count: int, step: float, radius: float) -> np.ndarray:
    """``count`` thick polylines wandering through ``region``, clipped to it."""
    ys, xs = np.nonzero(region)
    out = np.zeros_like(region)
    if len(xs) == 0:
        return out
    candidates = np.stack([xs, ys], -1).astype(float)
    strokes = []
    for _ in range(count):
        pts = [candidates[rng.integers(len(candidates))]]
        for _ in range(int(rng.integers(1, 4))):
            dist = np.linalg.norm(candidates - pts[-1], axis=-1)
            near = np.nonzero((dist >= 0.5 * step) & (dist <= step))[0]
            if len(near) == 0:
                break
            pts.append(candidates[near[rng.integers(len(near))]])
        strokes.append(np.stack(pts))
    return strokes_mask(region.shape, strokes, radius) & region


def min_scribble_pixels(res: int) -> int:
    """Interior pixels a part needs in its best view to be scribbled on: 16 at 64×64, ∝ area."""
    return max(4, round(16 * (res / 64) ** 2))


def stroke_region(part: np.ndarray, need: int) -> np.ndarray:
    """Where strokes on a part mask [H, W] go: the part eroded by 2 px, else by 1, else the
    part itself, whichever first keeps ``need`` pixels.  A thin part (a leg, a tube) gets
    strokes along it rather than a speck in its one pixel that survives erosion."""
    for radius in (2, 1):
        inside = erode(part, radius)
        if inside.sum() >= need:
            return inside
    return part


def scribbles(rng: np.random.Generator, parts: np.ndarray, part_id: int) -> tuple[np.ndarray, np.ndarray]:
    """(foreground, keep) masks for editing part ``part_id`` in a part map [H, W].

    Foreground strokes lie in the part's :func:`stroke_region`; keep strokes lie on other parts
    and the background, off the part dilated by 3 px.
    """
    part = parts == part_id
    size = parts.shape[1]
    inside = stroke_region(part, min_scribble_pixels(size))
    step, radius = max(3.0, size / 10), max(1.0, size / 48)
    fg = random_strokes(rng, inside, 3, step, radius)
    away = ~dilate(part, 3)
    keep = random_strokes(rng, away & (parts > 0), 2, step, radius) | random_strokes(rng, away & (parts == 0), 3, step, radius)
    return fg, keep


# ----------------------------------------------------------------------------- the dataset


TWIN_SOURCES = 4
"""Chairs that get twins by default: the benchmark twins every documented score is measured on."""


@dataclass(frozen=True)
class SynthConfig:
    instances: int = 24
    """Number of chairs."""
    views: int = 50
    """Views per chair, split 80/10/10 into train/val/test."""
    res: int = 64
    """Image width and height in pixels."""
    seed: int = 0
    """Same seed → byte-identical files."""
    aa: int = 3
    """Supersamples per pixel side (aa×aa rays, box-filtered); 1 = one ray per pixel center."""
    twins: bool = True
    """Also write ground-truth color and removal twins."""
    twin_sources: int = TWIN_SOURCES
    """Chairs that get twins (:func:`twin_sources`); more than the default only adds twins."""


@dataclass(frozen=True)
class SynthResult:
    names: list[str]
    twins: list[TwinSpec]
    seconds: float
    kept: list[str] = field(default_factory=list)  # the user's entries of the dataset it replaced, carried over


def _spread(instances: int, count: int) -> list[int]:
    n = min(count, instances)
    return sorted({round(k * instances / n) for k in range(n)}) if n > 0 else []


def twin_sources(instances: int, count: int = TWIN_SOURCES) -> list[int]:
    """Indices of the chairs that get twins: up to ``count``, spread over the category.

    The default's :data:`TWIN_SOURCES` sources are always among them (a bigger benchmark only
    adds twins: the default ones, and so every score measured on them, stay as they were),
    the rest are spread over the category as well."""
    base = _spread(instances, min(count, TWIN_SOURCES))
    need, taken, extra = max(0, min(count, instances) - len(base)), set(base), []
    for i in itertools.chain(_spread(instances, count), range(instances)):  # lazily: memory as the sources, not the chairs
        if len(extra) >= need:
            break
        if i not in taken:
            taken.add(i)
            extra.append(i)
    return sorted(base + extra)


def synth_steps(config: SynthConfig) -> int:
    """Progress steps :func:`write_synth_category` reports: one per chair, one per twin source."""
    return config.instances + (len(twin_sources(config.instances, config.twin_sources)) if config.twins else 0)


def check_synth_args(out: Path, config: SynthConfig) -> None:
    """Raise a one-line CrfError for a bad config or an output folder we must not write into."""
    if config.instances < 1:
        raise CrfError(f"--instances {config.instances}: need at least 1")
    if config.seed < 0:
        raise CrfError(f"--seed {config.seed}: must be 0 or more")
    if config.views < 1:
        raise CrfError(f"--views {config.views}: need at least 1")
    if config.twin_sources < 1:
        raise CrfError(f"--twin-sources {config.twin_sources}: need at least 1 (or --no-twins)")
    if config.twins and config.views < 3:
        raise CrfError(f"--views {config.views}: twins need a test split, i.e. at least 3 views (or --no-twins)")
    if not 8 <= config.res <= 4096:
        raise CrfError(f"--res {config.res}: must be between 8 and 4096")
    if not 1 <= config.aa <= 8:
        raise CrfError(f"--aa {config.aa}: must be between 1 and 8")
    out = Path(out)
    check_folder_target(out)
    if out.is_dir() and any(out.iterdir()) and not (out / "instances.txt").is_file():
        raise CrfError(f"{out}: folder is not empty and not a dataset; pick a new folder")


def _write_instance(folder: Path, chair: Chair, cams: dict[str, list[Camera]], aa: int = 1) -> dict[str, list[Frame]]:
    frames = {split: [render_chair(chair, cam, aa) for cam in cams_] for split, cams_ in cams.items()}
    for split, fs in frames.items():
        write_split(folder, split, fs)
    write_parts(folder, [{"id": p.id, "name": p.name, "color": p.color} for p in chair.parts])
    return frames


def best_view(frames: list[Frame], part_id: int, region=lambda mask: mask) -> tuple[int, int]:
    """(index, pixel count) of the frame where ``region`` of the part's mask (by default the
    mask itself) holds the most pixels."""
    counts = [int(region(f.parts == part_id).sum()) for f in frames]
    return int(np.argmax(counts)), max(counts)


def _write_twin(
    out: Path, source: str, kind: str, chair: Chair, part: Part, color: str | None, frames: dict[str, list[Frame]],
    rng: np.random.Generator, aa: int = 1,
) -> TwinSpec:
    """Render the edited ``chair`` at the source's test poses; scribble ``part`` in its best train view."""
    view, _ = best_view(frames["train"], part.id)
    name = f"{source}_{kind}"
    folder = Path("twins") / name
    twin = chair.recolored(part.name, color) if kind == "color" else chair.without(part.name)
    _write_instance(out / folder, twin, {"test": [f.camera for f in frames["test"]]}, aa)
    fg, keep = scribbles(rng, frames["train"][view].parts, part.id)
    write_png(out / folder / "scribble.png", fg.astype(np.uint8) * 255)
    write_png(out / folder / "keep.png", keep.astype(np.uint8) * 255)
    scribble, keep_path = str(folder / "scribble.png"), str(folder / "keep.png")
    return TwinSpec(name, kind, source, f"train:{view}", part.name, color, scribble, keep_path, str(folder))


def _twins_of(
    out: Path, name: str, chair: Chair, frames: dict[str, list[Frame]], order: int, seed: list[int], aa: int = 1
) -> list[TwinSpec]:
    """A color twin (seat or back, alternating with ``order``) and a removal twin (arms, else stretchers/slats)."""
    wanted = RECOLORABLE_PARTS[order % 2], RECOLORABLE_PARTS[1 - order % 2]
    first, second = (chair.part(n) for n in wanted)
    recolor = first if best_view(frames["train"], first.id)[1] >= 25 else second  # 25 px: room for strokes
    target = contrasting_color([p.color for p in chair.parts])
    specs = [_write_twin(out, name, "color", chair, recolor, target, frames, np.random.default_rng([*seed, 2]), aa)]
    removable = next((chair.part(n) for n in REMOVABLE_PARTS if chair.part(n)), None)
    if removable is not None:
        specs.append(_write_twin(out, name, "remove", chair, removable, None, frames, np.random.default_rng([*seed, 3]), aa))
    return specs


def write_synth_category(
    out: Path, config: SynthConfig = SynthConfig(), progress: Callable[[str], None] | None = None
) -> SynthResult:
    """Generate and write the procedural chair category to ``out``; ``progress(label)`` after each step.

    The category is built in a hidden folder beside ``out`` and renamed onto it at the end, so an
    interrupted run leaves no partial dataset (and a previous one at ``out`` untouched).
    """
    check_synth_args(out, config)
    out = Path(out)
    start = time.perf_counter()
    sources = twin_sources(config.instances, config.twin_sources) if config.twins else []
    # the default sources get arms, whatever the count, so a bigger benchmark renders the same chairs
    armed = [i for i in twin_sources(config.instances) if i in sources]
    order = armed + [i for i in sources if i not in armed]  # seat or back alternates along it
    names, twins = [], []
    with atomic_folder(out) as tmp:
        for index in range(config.instances):
            name = f"chair_{index:03d}"
            # twin sources get arms, so their removal twin removes a part that covers pixels
            chair = make_chair(np.random.default_rng([config.seed, index, 0]), arms=True if index in armed else None)
            cams = sample_cameras(np.random.default_rng([config.seed, index, 1]), config.views, config.res)
            frames = _write_instance(tmp / name, chair, cams, config.aa)
            names.append(name)
            if progress:
                progress(name)
            if index in sources:
                twins += _twins_of(tmp, name, chair, frames, order.index(index), [config.seed, index], config.aa)
                if progress:
                    progress(f"{name} twins")
        write_instances_txt(tmp, names)
        if twins:
            write_twins_json(tmp, twins)
        kept = carry_extras(out, tmp)  # a user's notes and scribbles in an earlier build: not lost with it
    return SynthResult(names, twins, time.perf_counter() - start, kept)
