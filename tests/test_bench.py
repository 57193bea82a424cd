"""``crfedit bench``: the tiny sweep end to end (CSV, PNGs, markdown section), and the pieces it
is written with (ticks, plots, the markdown markers, the machine stamp)."""

from __future__ import annotations

import csv
import math

import pytest
import torch
from PIL import Image

from crfedit.bench import BenchSettings
from crfedit.machine import machine_info
from crfedit.report import BEGIN, CSV_COLUMNS, END, PLOT_SIZE, emit_table, log_ticks, nice_ticks, plot_curves, update_markdown
from crfedit.errors import CrfError

from cli_helpers import assert_user_error, invoke


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """The ``--tiny`` sweep on its own generated 2-chair category, into a docs page that already
    has other sections."""
    folder = tmp_path_factory.mktemp("bench")
    md = folder / "docs" / "benchmarks.md"
    md.parent.mkdir()
    md.write_text(f"# Benchmarks\n\nIntro kept.\n\n{BEGIN}\nold numbers\n{END}\n\n## Other section\n\nKept too.\n")
    csv_path = folder / "docs" / "benchmarks" / "bench.csv"
    assert_user_error(invoke("bench", "--tiny", "--csv", csv_path, "--md", md, "--device", "cpu"), "benchmarks does not exist")  # a typo's folder
    csv_path.parent.mkdir()  # as in the repository
    result = invoke("bench", "--tiny", "--csv", csv_path, "--md", md, "--device", "cpu")
    assert result.exit_code == 0, result.output
    return result, csv_path, md


def test_tiny_bench_writes_a_csv_with_a_header_and_rows_of_every_group(tiny_run):
    result, csv_path, _ = tiny_run
    assert f"wrote {csv_path}" in result.stdout
    with open(csv_path, newline="") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == CSV_COLUMNS
    body = [dict(zip(CSV_COLUMNS, r)) for r in rows[1:]]
    groups = {r["group"] for r in body}
    assert groups == {"train", "render", "edit"}
    train = [r for r in body if r["group"] == "train"]
    assert len(train) >= 2 and [int(r["value"]) for r in train] == sorted(int(r["value"]) for r in train)
    assert int(train[-1]["value"]) == BenchSettings.tiny().steps  # the end of training is the last point
    seconds = [float(r["seconds"]) for r in train]
    assert seconds == sorted(seconds) and seconds[0] > 0
    assert {r["value"] for r in body if r["group"] == "render"} == {"1", "2"}
    assert {r["curve"] for r in body if r["group"] == "edit"} == {
        "color, 64 rays", "remove, 64 rays", "color, 64 rays, no cache", "remove, 64 rays, no cache"}
    for r in body:
        assert math.isfinite(float(r["psnr"])) and -1 <= float(r["ssim"]) <= 1 and int(r["views"]) >= 1


def test_tiny_bench_writes_one_readable_png_per_group(tiny_run):
    _, csv_path, _ = tiny_run
    for group in ("train", "render", "edit"):
        path = csv_path.with_name(f"bench_{group}.png")
        with Image.open(path) as im:
            im.load()
            assert im.format == "PNG" and im.size == PLOT_SIZE and im.mode == "RGB"
            colors = im.getcolors(maxcolors=1 << 20)
        assert len(colors) > 10  # axes, text and curves, not a blank canvas


def test_tiny_bench_rewrites_only_its_markdown_section(tiny_run):
    _, _, md = tiny_run
    text = md.read_text()
    assert text.startswith("# Benchmarks\n\nIntro kept.\n\n") and text.endswith("## Other section\n\nKept too.\n")
    assert "old numbers" not in text and text.count(BEGIN) == 1 and text.count(END) == 1
    section = text[text.index(BEGIN) : text.index(END)]
    assert "## Speed against error" in section and "torch " in section and "revision `" in section
    assert "](benchmarks/bench_train.png)" in section and "](benchmarks/bench.csv)" in section
    assert "| curve |" in section and "| fast | step = 24 |" in section
    # the data it ran on is named as what it was, not as a temporary folder gone by now
    assert "Data: the `--tiny` category, made in a temporary folder (2 instances, " in section and "crfedit-tiny-" not in section
    assert "2 points along each run at equal fractions of it, the last at its end" in section


def test_emit_table_prints_and_writes_the_lines(tmp_path, capsys):
    """The benchmark scripts' one report: the lines printed, and written to --out with a final newline."""
    emit_table(["| a |", "|---|"], tmp_path / "t.md")
    assert capsys.readouterr().out == "| a |\n|---|\n"
    assert (tmp_path / "t.md").read_text() == "| a |\n|---|\n" and list(tmp_path.iterdir()) == [tmp_path / "t.md"]
    emit_table(["x"])
    assert capsys.readouterr().out == "x\n"


def test_update_markdown_creates_appends_and_replaces(tmp_path):
    page = tmp_path / "b.md"
    update_markdown(page, f"{BEGIN}\none\n{END}")
    assert page.read_text().startswith("# Benchmarks") and f"{BEGIN}\none\n{END}" in page.read_text()
    update_markdown(page, f"{BEGIN}\ntwo\n{END}")
    assert "one" not in page.read_text() and page.read_text().count(BEGIN) == 1
    plain = tmp_path / "plain.md"
    plain.write_text("# Title\n\nText.\n")
    update_markdown(plain, f"{BEGIN}\nthree\n{END}")
    assert plain.read_text() == f"# Title\n\nText.\n\n{BEGIN}\nthree\n{END}\n"


def test_bench_needs_data_or_tiny(tmp_path):
    result = invoke("bench", "--csv", tmp_path / "b.csv", "--md", tmp_path / "b.md")
    assert result.exit_code == 2 and result.stderr.startswith("error: give a DATA folder"), result.output
    result = invoke("bench", "--tiny", "--edit-steps", "3,x", "--csv", tmp_path / "b.csv")
    assert result.exit_code == 2 and "--edit-steps 3,x" in result.stderr
    result = invoke("bench", "--tiny", "--presets", "fast,slow", "--csv", tmp_path / "b.csv")
    assert_user_error(result, "--presets fast,slow: slow is not a preset (expected fast, paper")  # the option as bench spells it
    assert not (tmp_path / "b.csv").exists()


def test_nice_ticks_are_round_and_cover_the_range():
    assert nice_ticks(11.3, 23.8) == [10.0, 12.5, 15.0, 17.5, 20.0, 22.5, 25.0]
    assert nice_ticks(0.0, 600.0) == [0.0, 100.0, 200.0, 300.0, 400.0, 500.0, 600.0]
    ticks = nice_ticks(5.0, 5.0)  # a flat curve still gets an axis
    assert ticks[0] < 5.0 < ticks[-1]


def test_log_ticks_show_decades_and_their_2_and_5_multiples():
    assert log_ticks(0.08, 18.75) == [0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0]
    assert log_ticks(1e-3, 1e3) == [1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0, 1000.0]


def test_plots_of_groups_without_rows_are_removed(tmp_path):
    from crfedit.bench import BenchRow
    from crfedit.report import write_plots

    stale = tmp_path / "b_edit.png"
    stale.write_bytes(b"an earlier run's edit plot")
    plots = write_plots([BenchRow("train", "fast", "step", "10", 1.0, 20.0, 0.9, 1)], tmp_path / "b")
    assert set(plots) == {"train"} and plots["train"].is_file() and not stale.exists()


def test_plot_leaves_out_non_finite_points_and_refuses_an_empty_plot(tmp_path):
    path = plot_curves({"a": [(1.0, 20.0), (2.0, float("nan")), (3.0, 22.0)], "b": [(2.0, float("inf"))]}, tmp_path / "p.png", "t", "x", "y")
    with Image.open(path) as im:
        assert im.size == PLOT_SIZE
    with pytest.raises(CrfError, match="nothing to plot"):
        plot_curves({"b": [(1.0, float("nan"))]}, tmp_path / "q.png", "t", "x", "y")


def test_machine_stamp_names_cpu_cores_torch_threads_date_and_revision():
    info = machine_info("cpu")
    assert {"cpu", "cores", "torch", "threads", "device", "date", "revision"} <= set(info)
    assert info["torch"] == torch.__version__ and info["threads"] == str(torch.get_num_threads())
    assert info["cpu"] and info["revision"] and info["date"].endswith("UTC")


def test_edit_curves_make_the_edit_eval_makes_and_leave_out_a_diverged_point(monkeypatch):
    """The edit curves score the edit ``eval edits`` makes (a recolour targets the colour the part
    should appear, from the twin's selection made once, not timed): they targeted the twin's
    albedo, so bench and eval disagreed on one model.  A point whose edit diverges is left out
    with a note; it ended the whole sweep with nothing written."""
    import dataclasses
    from types import SimpleNamespace

    import crfedit.bench as bench
    from crfedit.errors import NonFiniteError

    case = SimpleNamespace(spec=SimpleNamespace(kind="color", name="chair_000_color"), instance=0, views=[])
    monkeypatch.setattr(bench, "load_twin_cases", lambda model, category: [case])
    monkeypatch.setattr(bench, "twin_appearance", lambda category, c: (0.5, 0.2, 0.1))
    monkeypatch.setattr(bench, "twin_selection", lambda model, c: "the selection")
    calls = []

    def edit(model, c, options, appear=None, selection=None):
        calls.append((options.steps, appear, selection))
        if options.steps == 30:
            raise NonFiniteError("colour edit diverged: its loss rose")
        return SimpleNamespace(model=model, seconds=0.25)

    monkeypatch.setattr(bench, "apply_twin_edit", edit)
    monkeypatch.setattr(bench, "score_instance", lambda model, k, views: {"psnr": 20.0, "ssim": 0.9, "n": 1})
    settings = dataclasses.replace(BenchSettings.tiny(), edit_steps=(10, 30, 100), edit_rays=(64,), edit_uncached=False)
    notes: list[str] = []
    rows = bench.edit_curves(None, None, settings, lambda message: None, notes)
    assert calls[1:] == [(n, (0.5, 0.2, 0.1), "the selection") for n in (10, 30, 100)]  # after the untimed warm-up
    assert [(r.curve, r.value, r.seconds) for r in rows] == [("color, 64 rays", "10", 0.25), ("color, 64 rays", "100", 0.25)]
    assert notes == ["edit color, 64 rays, 30 steps left out: colour edit diverged: its loss rose"]

    def refused(model, c):
        raise CrfError("the scribble lies on the background only: no scribbled pixel covers the object in its view")

    monkeypatch.setattr(bench, "twin_selection", refused)  # a model that collapsed no longer shows the part
    notes.clear()
    assert bench.edit_curves(None, None, settings, lambda message: None, notes) == []
    assert notes == [f"edit curves of {case.spec.name} left out: the scribble lies on the background only: no scribbled pixel covers "
                     "the object in its view; does the model render the chair? its training may have collapsed (see the train curve)"]
