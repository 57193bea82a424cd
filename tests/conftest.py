"""Shared test setup.

* torch runs single-threaded for the whole session.  The tests use tiny tensors (16×16 views,
  256-ray batches) on a shared 2-core machine, where OpenMP's second thread mostly spin-waits:
  ``tests/test_cli_train_render.py`` (quickstart deselected), five alternating runs each, took
  12–78 s (median 38 s) with torch's default two threads and 5.6–7.7 s (median 6.3 s) with one
  (docs/robustness.md, "Hostile inputs").  Modules that set one thread themselves and restore
  the previous count afterwards keep working unchanged.
* ``tiny_chairs``: a 2-chair × 6-view 16×16 synthetic category, written once per session.
* ``tiny_model``: a model of it trained for 30 steps (fast preset, 256 rays, a checkpoint every
  10 steps, seed 0).

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
