"""benchmarks/heldout_twins.py: the folds' part labels and the pooled means it reports."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from crfedit.config import hidden_part_labels
from crfedit.data.loading import read_twin_specs
from crfedit.data.synth import SynthConfig, write_synth_category

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "heldout_twins.py"


@pytest.fixture(scope="module")
def script():
    spec = importlib.util.spec_from_file_location("heldout_twins", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    import sys

    sys.path.insert(0, str(SCRIPT.parent))  # it imports its neighbour edit_models
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(SCRIPT.parent))
    return module


def test_folds_hide_the_benchmark_s_sources_and_split_the_others(script, tmp_path):
    """Each fold hides the benchmark's twin sources (``twins``) and every K-th other source of
    the larger dataset; together the folds hide each other source exactly once."""
    bench, held = tmp_path / "bench", tmp_path / "held"
    write_synth_category(bench, SynthConfig(instances=6, views=3, res=16, seed=0, twin_sources=1))
    write_synth_category(held, SynthConfig(instances=6, views=3, res=16, seed=0, twin_sources=6))
    own = {t.source for t in read_twin_specs(bench)}
    others = {t.source for t in read_twin_specs(held)} - own
    assert own and len(others) >= 2
    folds = [hidden_part_labels(labels) for labels in script.fold_labels(bench, held, 2)]
    assert all(f[0] == "twins" for f in folds)
    hidden = [name for f in folds for name in f[1:]]
    assert sorted(hidden) == sorted(others) and abs(len(folds[0]) - len(folds[1])) <= 1


def test_pooled_means_weigh_each_file_by_its_twins(script):
    a = {"n": 1, "gap": 1.0, "outside": -1.0, "iou": 0.5, "below": 1}
    b = {"n": 3, "gap": 0.6, "outside": 0.2, "iou": 0.9, "below": 0}
    pooled = script.pool([a, None, b])
    assert pooled["n"] == 4 and pooled["below"] == 1
    assert pooled["gap"] == pytest.approx(0.7) and pooled["outside"] == pytest.approx(-0.1) and pooled["iou"] == pytest.approx(0.8)
    assert script.pool([None]) is None
