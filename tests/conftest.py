"""Shared test setup.

* torch runs single-threaded for the whole session.  The tests use tiny tensors (16×16 views,
  256-ray batches) on a shared 2-core machine, where OpenMP's second thread mostly spin-waits:
  ``tests/test_cli_train_render.py`` (quickstart deselected), five alternating runs each, took
  12–78 s (median 38 s) with torch's default two threads and 5.6–7.7 s (median 6.3 s) with one
  (docs/robustness.md, "Hostile inputs").  Modules that set one thread themselves and restore
  the previous count afterwards keep working unchanged.  After every test the count is one
  again and the CLI's :class:`~crfedit.cli.common.Session` sets none: ``crfedit.cli.main``
  run in-process sets the machine's default (two threads on an idle 2-core box, one on a busy
  one), and results depend on the thread count in the last float bits, so a later test that
  compares numbers across processes (tests/test_distributed.py) failed now and then.
* ``tiny_chairs``: a 2-chair × 6-view 16×16 synthetic category, written once per session.
* ``tiny_model``: a model of it trained for 30 steps (fast preset, 256 rays, a checkpoint every
  10 steps, seed 0).
* ``trained_category``: trains a model of a synthetic category once per session and argument set
  (the edit and fit-real tests), returning (model file, model, category).

Tests must not modify the session fixtures' files (tests/test_hostile_inputs.py hashes them).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(autouse=True)
def _one_thread_after_each_test():
    yield
    from crfedit.cli.common import Session

    Session.threads = None
    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def tiny_chairs(tmp_path_factory) -> Path:
    """A read-only tiny category: 2 chairs × 6 views at 16×16, no twins."""
    from crfedit.data.synth import SynthConfig, write_synth_category

    root = tmp_path_factory.mktemp("tiny") / "chairs"
    write_synth_category(root, SynthConfig(instances=2, views=6, res=16, seed=0, twins=False))
    return root


@pytest.fixture(scope="session")
def tiny_model(tiny_chairs) -> Path:
    """A read-only model of ``tiny_chairs``: 30 steps of the fast preset, seed 0."""
    from crfedit.config import make_config
    from crfedit.data import load_category
    from crfedit.train import train

    path = tiny_chairs.parent / "model.safetensors"
    cfg = make_config("fast", overrides=dict(steps=30, rays=256, checkpoint_every=10))
    train(load_category(tiny_chairs), cfg, path, torch.device("cpu"), seed=0)
    return path


@pytest.fixture(scope="session")
def trained_category(tmp_path_factory):
    """``trained_category(name, synth, overrides, n_train=None, with_parts=False, with_depth=False)``
    → (model file, model, category): ``synth`` written and the fast preset with ``overrides``
    trained on its first ``n_train`` instances (all by default), seed 0; once per argument set.
    The part head F_part trains only where the category is loaded with parts *and* depth."""
    from crfedit.config import make_config
    from crfedit.data import load_category
    from crfedit.data.loading import Category
    from crfedit.data.synth import write_synth_category
    from crfedit.model import load_model
    from crfedit.train import train

    made: dict = {}

    def make(name: str, synth, overrides: dict, n_train: int | None = None, with_parts: bool = False, with_depth: bool = False):
        key = (name, synth, tuple(sorted(overrides.items())), n_train, with_parts, with_depth)
        if key not in made:
            folder = tmp_path_factory.mktemp(name)
            write_synth_category(folder / "chairs", synth)
            category = load_category(folder / "chairs", with_parts=with_parts, with_depth=with_depth)
            trained_on = Category(category.root, category.instances[:n_train], category.fingerprint)
            path = folder / "model.safetensors"
            _, result = train(trained_on, make_config("fast", overrides=overrides), path, torch.device("cpu"), seed=0)
            model, _ = load_model(path)
            made[key] = (path, model, category, result)
        return made[key]

    return make


@pytest.fixture(scope="session")
def edit_category(trained_category):
    """(model file, model, category with part maps) that the edit and selection tests share:
    3 chairs at 32², ~250 steps, about 15 s on one core."""
    from crfedit.data.synth import SynthConfig

    path, model, category, result = trained_category(
        "edits", SynthConfig(instances=3, views=10, res=32, seed=0, twins=False), dict(
            steps=250, rays=512, lr=1e-2, lr_codes=1e-2, grid_res=16, occ_res=32, width=32, rad_width=32,
            occ_warmup=100, occ_every=8, checkpoint_every=10**9,
        ), with_parts=True)
    assert result.train_psnr > 12, f"the fixture's training failed (PSNR {result.train_psnr:.1f}); the edit tests need a model"
    return path, model, category
