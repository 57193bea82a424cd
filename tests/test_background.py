"""Training over a random background (``Config.random_background``): the recompositing in
closed form, the sampler's targets, and what it buys: the coverage a model learns holds over
any background, not only the white one it was trained on."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from crfedit.config import Config, make_config
from crfedit.data import load_category
from crfedit.data.loading import training_rays
from crfedit.metrics import psnr
from crfedit.model import load_model
from crfedit.renderer import render_camera
from crfedit.train import BatchSampler, over_background, train


def test_over_background_closed_form():
    # an opaque pixel keeps its colour, an empty one becomes the background, and a half-covered
    # grey 0.5 (0.75 over white) becomes 0.25 over black and 0.5 + 0.5·0.2 over 0.2
    rgb_white = torch.tensor([[0.3, 0.6, 0.9], [1.0, 1.0, 1.0], [0.75, 0.75, 0.75], [0.75, 0.75, 0.75]])
    alpha = torch.tensor([1.0, 0.0, 0.5, 0.5])
    bg = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.2, 0.3], [0.0, 0.0, 0.0], [0.2, 0.2, 0.2]])
    out = over_background(rgb_white, alpha, bg)
    expected = torch.tensor([[0.3, 0.6, 0.9], [0.1, 0.2, 0.3], [0.25, 0.25, 0.25], [0.35, 0.35, 0.35]])
    torch.testing.assert_close(out, expected)
    torch.testing.assert_close(over_background(rgb_white, alpha, torch.ones(4, 3)), rgb_white)  # white: unchanged


def test_sampler_targets_sit_over_their_background(tiny_chairs):
    data = training_rays(load_category(tiny_chairs), "train")
    plain = BatchSampler(data, torch.device("cpu"))
    mixed = BatchSampler(data, torch.device("cpu"), random_background=True)
    a, b = plain(256, torch.Generator().manual_seed(3)), mixed(256, torch.Generator().manual_seed(3))
    assert a.background is None and b.background.shape == (256, 3)
    assert torch.equal(a.rays.origins, b.rays.origins) and torch.equal(a.jitter, b.jitter)  # same rays, colour drawn after
    empty = (b.rgb - b.background).abs().max(dim=-1).values < 1e-6
    assert empty.sum() == round(256 * 0.25)  # the background rays' targets are their background
    assert not torch.allclose(a.rgb, b.rgb)
    again = mixed(256, torch.Generator().manual_seed(3))
    assert torch.equal(again.rgb, b.rgb) and torch.equal(again.background, b.background)  # deterministic


def test_old_model_files_read_as_trained_over_white():
    """The fast preset trains over random backgrounds; a file written before the key existed
    was trained over white, and says so when read."""
    assert make_config("fast").random_background and not make_config("paper").random_background
    data = json.loads(Config().to_json())
    del data["random_background"]
    assert Config.from_json(json.dumps(data)).random_background is False


@pytest.fixture(scope="module")
def two_models(tiny_chairs, tmp_path_factory):
    """The same 300 steps over white and over random backgrounds (seed 0)."""
    category = load_category(tiny_chairs)
    out = {}
    for rb in (False, True):
        cfg = make_config("fast", overrides=dict(steps=300, rays=512, grid_res=16, occ_res=16, occ_warmup=100,
                                                 checkpoint_every=10**9, random_background=rb))
        path = tmp_path_factory.mktemp(f"bg{int(rb)}") / "model.safetensors"
        train(category, cfg, path, torch.device("cpu"), seed=0)
        out[rb] = load_model(path)[0]
    return category, out


def over(view, background: float) -> np.ndarray:
    return view.rgb + (background - 1.0) * (1.0 - view.alpha[..., None])


def test_random_background_learns_the_coverage(two_models):
    """Over black, the white-trained model shows the white it put where the object is not
    (floaters, half-covered surfaces); the random-background model does not, and over white
    the two score alike."""
    category, models = two_models
    scores = {}
    for rb, model in models.items():
        for bg in (0.0, 1.0):
            s = []
            for inst in category.instances:
                k = model.instance_index(inst.name)
                for v in inst.splits["train"]:
                    rgb = render_camera(model.field_for(k), v.camera, k, background=bg).rgb.numpy()
                    s.append(float(psnr(torch.from_numpy(rgb), torch.from_numpy(over(v, bg)))))
            scores[rb, bg] = float(np.mean(s))
    assert scores[True, 0.0] > scores[False, 0.0] + 2.0, scores
    assert abs(scores[True, 1.0] - scores[False, 1.0]) < 2.5, scores


def test_instances_far_apart_in_rays_are_drawn_equally():
    """BALANCE_RATIO: instance 1 with 8× instance 0's rays (3 training views among 40) got 1/9
    of the batch, and its chair fitted its own views 11 dB worse; drawn instance first, each
    gets half.  Within the ratio the draw is the plain one, bit for bit."""
    from crfedit.data.loading import TrainingRays
    from crfedit.train import BALANCE_RATIO

    def rays(counts):
        n = sum(counts)
        inst = torch.cat([torch.full((c,), k) for k, c in enumerate(counts)])
        alpha = (torch.arange(n) % 4 != 0).float()  # a quarter background, in every instance
        return TrainingRays(torch.zeros(n, 3), torch.ones(n, 3) / 3**0.5, torch.rand(n, 3), alpha, inst)

    uneven = BatchSampler(rays([100, 800]), torch.device("cpu"))
    assert uneven.balanced and 800 > BALANCE_RATIO * 100
    batch = uneven(4000, torch.Generator().manual_seed(0))
    share = float((batch.instance == 0).float().mean())
    assert 0.45 < share < 0.55, share  # uniform over rays it would be 1/9
    even = rays([300, 400])
    sampler = BatchSampler(even, torch.device("cpu"))
    assert not sampler.balanced
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    fg, bg = (even.alpha > 0).nonzero().squeeze(-1), (even.alpha <= 0).nonzero().squeeze(-1)
    plain = torch.cat([fg[torch.randint(len(fg), (48,), generator=g2)], bg[torch.randint(len(bg), (16,), generator=g2)]])
    assert torch.equal(sampler(64, g1).instance, even.instance[plain])  # the plain draw, as before
