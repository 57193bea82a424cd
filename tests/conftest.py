"""Shared test setup.

* torch runs single-threaded for the whole session.  The tests use tiny tensors (16×16 views,
  256-ray batches) on a shared 2-core machine, where OpenMP's second thread mostly spin-waits:
  ``tests/test_cli_train_render.py`` (quickstart deselected) took 78 s with torch's default
  2 threads and 32 s with one (docs/robustness.md, "Hostile inputs").  Modules that set one
  thread themselves and restore the count afterwards keep working unchanged.
* ``tiny_chairs``: a 2-chair × 6-view 16×16 synthetic category, written once per session, for
  tests that need a dataset and do not modify it.
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


def tiny_config(**overrides):
    """The fast preset cut down for tests: 30 steps of 256 rays, a checkpoint every 10 steps."""
    from crfedit.config import make_config

    return make_config("fast", overrides=dict(steps=30, rays=256, checkpoint_every=10, **overrides))


@pytest.fixture(scope="session")
def tiny_model(tiny_chairs) -> Path:
    """A model of ``tiny_chairs`` trained for 30 steps (seed 0); tests must not modify the file."""
    from crfedit.data import load_category
    from crfedit.train import train

    path = tiny_chairs.parent / "model.safetensors"
    train(load_category(tiny_chairs), tiny_config(), path, torch.device("cpu"), seed=0)
    return path
