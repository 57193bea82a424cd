"""Benchmark reports written out: a CSV of every point, one Pillow line plot per group, and the
markdown tables between ``<!-- bench:begin -->`` and ``<!-- bench:end -->`` of a docs page,
stamped with the machine, the date and the git revision (:class:`crfedit.bench.BenchReport`)."""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path
from typing import Sequence

from .bench import BenchReport, BenchRow, BenchSettings
from .errors import CrfError
from .io import atomic_path, atomic_write_text

BEGIN = "<!-- bench:begin -->"
END = "<!-- bench:end -->"
CSV_COLUMNS = ("group", "curve", "knob", "value", "seconds", "psnr", "ssim", "views")
GROUPS = {
    "train": ("Training: held-out PSNR against training time", "training time (s)", "held-out PSNR (dB)"),
    "render": ("Rendering: PSNR against time per view, by samples per ray", "seconds per view", "held-out PSNR (dB)"),
    "edit": ("Editing: PSNR against the ground-truth twin, by edit steps and rays", "edit time (s)", "PSNR vs twin (dB)"),
}
"""group → (title, x label, y label)."""


# ----------------------------------------------------------------------------- CSV


def write_csv(rows: Sequence[BenchRow], path: str | Path) -> Path:
    """One line per point, columns :data:`CSV_COLUMNS`; written atomically."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for r in rows:
        writer.writerow([r.group, r.curve, r.knob, r.value, f"{r.seconds:.6g}", f"{r.psnr:.4f}", f"{r.ssim:.4f}", r.views])
    path = Path(path)
    atomic_write_text(path, buf.getvalue())
    return path


# ----------------------------------------------------------------------------- plots (Pillow)

PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf")
PLOT_SIZE = (900, 600)


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError, AttributeError):  # Pillow without FreeType: the fixed bitmap font
        return ImageFont.load_default()


def nice_ticks(lo: float, hi: float, count: int = 6) -> list[float]:
    """Round tick values (steps of 1, 2, 2.5 or 5 × 10ᵏ) covering [lo, hi]: the first tick ≤ lo,
    the last ≥ hi.  ``nice_ticks(11.3, 23.8)`` → [10, 12.5, 15, 17.5, 20, 22.5, 25]."""
    if not hi > lo:
        lo, hi = lo - 0.5, hi + 0.5
    raw = (hi - lo) / count
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * mag >= raw * (1 - 1e-9))
    first, last = math.floor(lo / step + 1e-9), math.ceil(hi / step - 1e-9)
    return [round(k * step, 12) for k in range(first, last + 1)]


def log_ticks(lo: float, hi: float) -> list[float]:
    """Ticks of a log axis over [lo, hi] (lo > 0): decades, plus 2× and 5× when few decades show."""
    d0, d1 = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    mults = (1.0,) if d1 - d0 > 4 else (1.0, 2.0, 5.0)
    ticks = [m * 10.0**d for d in range(d0, d1 + 1) for m in mults]
    inside = [t for t in ticks if lo * (1 - 1e-9) <= t <= hi * (1 + 1e-9)]
    return inside if len(inside) >= 2 else [10.0**d0, 10.0**d1]


def _tick_label(v: float) -> str:
    if v == 0:
        return "0"
    if abs(v) >= 1e4 or abs(v) < 1e-3:
        return f"{v:.0e}".replace("e+0", "e").replace("e-0", "e-")
    return f"{v:g}"


def plot_curves(
    curves: dict[str, list[tuple[float, float]]], path: str | Path, title: str, xlabel: str, ylabel: str,
    size: tuple[int, int] = PLOT_SIZE,
) -> Path:
    """A line plot, one polyline with markers per curve, legend on the right; PNG written atomically.

    Drawn at twice the size and downsampled (anti-aliased lines and text).  The x axis is
    logarithmic when the positive x values span more than a factor of 30.  Non-finite points
    are left out.
    """
    from PIL import Image, ImageDraw

    curves = {k: sorted((x, y) for x, y in pts if math.isfinite(x) and math.isfinite(y)) for k, pts in curves.items()}
    curves = {k: v for k, v in curves.items() if v}
    if not curves:
        raise CrfError(f"{path}: nothing to plot (no finite points)")
    s = 2  # supersampling
    width, height = size[0] * s, size[1] * s
    img = Image.new("RGB", (width, height), "white")
    draw = ImageDraw.Draw(img)
    font, small, big = _font(14 * s), _font(12 * s), _font(17 * s)
    left, right, top, bottom = 78 * s, width - 230 * s, 48 * s, height - 62 * s

    xs = [x for pts in curves.values() for x, _ in pts]
    ys = [y for pts in curves.values() for _, y in pts]
    log_x = min(xs) > 0 and max(xs) / min(xs) > 30
    if log_x:
        lo, hi = min(xs) / 1.25, max(xs) * 1.25
        xt = log_ticks(lo, hi)
        lo, hi = min(lo, xt[0]), max(hi, xt[-1])
        fx = lambda x: left + (math.log10(x) - math.log10(lo)) / (math.log10(hi) - math.log10(lo)) * (right - left)
    else:
        xt = nice_ticks(min(0.0, min(xs)), max(xs))
        lo, hi = xt[0], xt[-1]
        fx = lambda x: left + (x - lo) / (hi - lo) * (right - left)
    pad = 0.03 * (max(ys) - min(ys))
    yt = nice_ticks(min(ys) - pad, max(ys) + pad)
    ylo, yhi = yt[0], yt[-1]
    fy = lambda y: bottom - (y - ylo) / (yhi - ylo) * (bottom - top)

    for t in xt:
        x = fx(t)
        draw.line([(x, top), (x, bottom)], fill="#e6e6e6", width=s)
        draw.line([(x, bottom), (x, bottom + 5 * s)], fill="black", width=s)
        draw.text((x, bottom + 8 * s), _tick_label(t), fill="black", font=small, anchor="ma")
    for t in yt:
        y = fy(t)
        draw.line([(left, y), (right, y)], fill="#e6e6e6", width=s)
        draw.line([(left - 5 * s, y), (left, y)], fill="black", width=s)
        draw.text((left - 8 * s, y), _tick_label(t), fill="black", font=small, anchor="rm")
    draw.rectangle([left, top, right, bottom], outline="black", width=s)
    draw.text(((left + right) / 2, 16 * s), title, fill="black", font=big, anchor="ma")
    draw.text(((left + right) / 2, height - 24 * s), xlabel + (" (log scale)" if log_x else ""), fill="black", font=font, anchor="ma")
    label = Image.new("RGB", (bottom - top, 22 * s), "white")
    ImageDraw.Draw(label).text(((bottom - top) / 2, 2 * s), ylabel, fill="black", font=font, anchor="ma")
    img.paste(label.rotate(90, expand=True), (8 * s, top))

    ly, r = top + 6 * s, 3.5 * s
    for i, (name, pts) in enumerate(curves.items()):
        color = PALETTE[i % len(PALETTE)]
        xy = [(fx(x), fy(y)) for x, y in pts]
        for a, b in zip(xy, xy[1:]):
            draw.line([a, b], fill=color, width=2 * s)
        for px, py in xy:
            draw.ellipse([px - r, py - r, px + r, py + r], fill=color)
        mid = ly + 8 * s
        draw.line([(right + 14 * s, mid), (right + 40 * s, mid)], fill=color, width=2 * s)
        draw.ellipse([right + 27 * s - r, mid - r, right + 27 * s + r, mid + r], fill=color)
        text = name if len(name) <= 28 else name[:27] + "…"
        draw.text((right + 48 * s, mid), text, fill="black", font=small, anchor="lm")
        ly += 22 * s
    img = img.resize(size, Image.LANCZOS)
    path = Path(path)
    with atomic_path(path) as tmp:
        img.save(tmp, format="PNG")
    return path


def write_plots(rows: Sequence[BenchRow], stem: str | Path) -> dict[str, Path]:
    """One PNG per group present in ``rows``: ``<stem>_<group>.png``; an earlier run's plot of a
    group with nothing to plot now is removed (it stood beside a CSV and page without its rows)."""
    stem = Path(stem)
    out = {}
    for group, (title, xlabel, ylabel) in GROUPS.items():
        curves: dict[str, list[tuple[float, float]]] = {}
        for r in rows:
            if r.group == group:
                curves.setdefault(r.curve, []).append((r.seconds, r.psnr))
        path = stem.with_name(f"{stem.name}_{group}.png")
        if any(math.isfinite(x) and math.isfinite(y) for pts in curves.values() for x, y in pts):
            out[group] = plot_curves(curves, path, title, xlabel, ylabel)
        elif path.is_file():
            path.unlink()
    return out


# ----------------------------------------------------------------------------- markdown


def _settings_line(s: BenchSettings) -> str:
    parts = [
        f"presets {', '.join(s.presets)}", f"{s.minutes:g} min per training curve" + (f" (at most {s.steps} steps)" if s.steps else ""),
        f"{s.checkpoints} points along each run at equal fractions of it, the last at its end", f"held-out scores on {s.eval_views} view(s) of the first {s.eval_instances} instance(s)",
        f"seed {s.seed}",
    ]
    if s.sets:
        parts.append("overrides " + ", ".join(f"`{x}`" for x in s.sets))
    return "; ".join(parts)


def _table(rows: Sequence[BenchRow], knob_header: str) -> list[str]:
    lines = [f"| curve | {knob_header} | seconds | PSNR (dB) | SSIM |", "|---|---|---:|---:|---:|"]
    for r in rows:
        seconds = f"{r.seconds:.3g}" if r.seconds < 100 else f"{r.seconds:.0f}"
        lines.append(f"| {r.curve} | {r.knob} = {r.value} | {seconds} | {r.psnr:.2f} | {r.ssim:.3f} |")
    return lines


def markdown_section(report: BenchReport, csv_path: Path, plots: dict[str, Path], md_path: Path) -> str:
    """The text between the markers: stamp, settings, then per group a plot and a table."""
    m = report.machine
    rel = lambda p: os.path.relpath(Path(p).resolve(), Path(md_path).resolve().parent).replace(os.sep, "/")
    lines = [
        BEGIN,
        "## Speed against error",
        "",
        f"Measured {m['date']} on {m['cpu']} ({m['cores']} cores, {m['threads']} torch thread{'s' * (str(m['threads']) != '1')}, device {m['device']}), "
        f"torch {m['torch']}, Python {m['python']}, crfedit revision `{m['revision']}`.",
        "",
        f"Data: {report.data}. Settings: {_settings_line(report.settings)}. Raw numbers: [{csv_path.name}]({rel(csv_path)}).",
        "",
    ]
    lines += [f"- {note}" for note in report.notes] + ([""] if report.notes else [])
    what = {
        "train": "Points along one run per curve (checkpoints; scoring is not counted in the time).",
        "render": "The same trained model rendered with fewer or more samples per ray.",
        "edit": "Hybrid-strategy edits of a twin's source instance, scored on all of the twin's test views.",
    }
    knob_header = {"train": "point", "render": "sampling", "edit": "edit"}
    for group, (title, _, _) in GROUPS.items():
        rows = [r for r in report.rows if r.group == group]
        if not rows:
            continue
        lines += [f"### {title}", "", what[group], ""]
        if group in plots:
            lines += [f"![{title}]({rel(plots[group])})", ""]
        lines += _table(rows, knob_header[group]) + [""]
    lines.append(END)
    return "\n".join(lines)


def emit_table(lines: Sequence[str], out: str | Path | None = None) -> None:
    """Print a benchmark script's markdown ``lines`` and, when ``out`` is given, write them
    there too (atomically, ending in a newline): the one way the scripts under benchmarks/
    report."""
    text = "\n".join(lines)
    print(text)
    if out is not None:
        atomic_write_text(out, text + "\n")


def update_markdown(path: str | Path, section: str, begin: str = BEGIN, end: str = END) -> Path:
    """Put ``section`` (markers included) between the markers of ``path``, keeping everything
    else; a page without markers gets it appended, a missing page is created."""
    path = Path(path)
    if path.is_file():
        text = path.read_text(encoding="utf-8")
        if begin in text and end in text and text.index(begin) < text.index(end):
            text = text[: text.index(begin)] + section + text[text.index(end) + len(end) :]
        else:
            text = text.rstrip("\n") + "\n\n" + section + "\n"
    else:
        text = "# Benchmarks\n\nWritten by `crfedit bench` (or `python benchmarks/run.py`).\n\n" + section + "\n"
    atomic_write_text(path, text)
    return path


def write_outputs(report: BenchReport, csv_path: str | Path, md_path: str | Path) -> list[Path]:
    """Write the CSV, the PNGs beside it (``<csv stem>_<group>.png``) and the markdown section.
    Folders are created as needed.  Returns the paths written."""
    csv_path, md_path = Path(csv_path), Path(md_path)
    for folder in {csv_path.parent, md_path.parent}:
        folder.mkdir(parents=True, exist_ok=True)
    written = [write_csv(report.rows, csv_path)]
    plots = write_plots(report.rows, csv_path.with_suffix(""))
    written += list(plots.values())
    written.append(update_markdown(md_path, markdown_section(report, csv_path, plots, md_path)))
    return written
