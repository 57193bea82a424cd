"""Image metrics against closed forms and a plain NumPy reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from crfedit import metrics
from crfedit.errors import CrfError
from crfedit.metrics import (
    LPIPS_ENV,
    load_lpips_weights,
    lpips,
    lpips_available,
    lpips_from_weights,
    lpips_tensor_names,
    lpips_unavailable_reason,
    mse_to_psnr,
    psnr,
    score_images,
    ssim,
    ssim_window_size,
)

C1 = 0.01**2
C2 = 0.03**2


def rand_image(seed: int, h: int = 16, w: int = 16, c: int = 3) -> np.ndarray:
    return np.random.default_rng(seed).random((h, w, c))


# ---------------------------------------------------------------------------------------- PSNR


def test_psnr_identical_is_inf():
    x = rand_image(0)
    assert psnr(x, x).item() == math.inf
    assert mse_to_psnr(0.0) == math.inf


def test_psnr_constant_offset_is_20_db():
    x = rand_image(1) * 0.8
    assert psnr(x + 0.1, x).item() == pytest.approx(20.0, abs=1e-9)
    assert psnr(x, x - 0.1).item() == pytest.approx(20.0, abs=1e-9)


def test_psnr_max_val_and_mse_to_psnr():
    assert mse_to_psnr(0.01) == pytest.approx(20.0, abs=1e-12)
    assert mse_to_psnr(1e-4) == pytest.approx(40.0, abs=1e-12)
    assert mse_to_psnr(1.0, max_val=255.0) == pytest.approx(20 * math.log10(255.0), abs=1e-12)
    t = mse_to_psnr(torch.tensor([0.01, 0.001], dtype=torch.float32))
    assert t.dtype == torch.float32
    assert torch.allclose(t, torch.tensor([20.0, 30.0]))
    x = rand_image(2) * 200
    assert psnr(x + 2.0, x, max_val=200.0).item() == pytest.approx(40.0, abs=1e-9)


def test_psnr_is_per_image_over_leading_dims():
    a = np.stack([rand_image(3), rand_image(4)])
    b = np.stack([rand_image(3), np.clip(rand_image(4) + 0.05, 0, 1)])
    out = psnr(torch.from_numpy(a), torch.from_numpy(b))
    assert out.shape == (2,) and out.dtype == torch.float64
    assert out[0].item() == math.inf
    assert out[1].item() == pytest.approx(psnr(a[1], b[1]).item())


def test_psnr_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="shapes differ"):
        psnr(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))


# ---------------------------------------------------------------------------------------- SSIM


def gaussian_window_2d_numpy(size: int, sigma: float = 1.5) -> np.ndarray:
    r = size // 2
    ii, jj = np.mgrid[-r : r + 1, -r : r + 1].astype(np.float64)
    w = np.exp(-(ii**2 + jj**2) / (2 * sigma**2))
    return w / w.sum()


def ssim_numpy(x: np.ndarray, y: np.ndarray, size: int) -> float:
    """Wang et al. 2004, written out: every valid window, every channel, float64."""
    w = gaussian_window_2d_numpy(size)
    h, wd, c = x.shape
    values = []
    for ch in range(c):
        for i in range(h - size + 1):
            for j in range(wd - size + 1):
                px = x[i : i + size, j : j + size, ch]
                py = y[i : i + size, j : j + size, ch]
                mx, my = (w * px).sum(), (w * py).sum()
                vx = (w * (px - mx) ** 2).sum()
                vy = (w * (py - my) ** 2).sum()
                cxy = (w * (px - mx) * (py - my)).sum()
                values.append(((2 * mx * my + C1) * (2 * cxy + C2)) / ((mx**2 + my**2 + C1) * (vx + vy + C2)))
    return float(np.mean(values))


def test_ssim_of_image_with_itself_is_one():
    x = rand_image(5, 20, 17)
    assert ssim(x, x).item() == pytest.approx(1.0, abs=1e-6)


def test_ssim_is_symmetric():
    x, y = rand_image(6), rand_image(7)
    assert ssim(x, y).item() == pytest.approx(ssim(y, x).item(), abs=1e-15)


@pytest.mark.parametrize("a, b", [(0.2, 0.7), (0.5, 0.5), (0.0, 1.0), (0.9, 0.85)])
def test_ssim_of_constant_images_has_closed_form(a, b):
    # Variances and covariance are zero, so SSIM = (2ab + C1) / (a² + b² + C1).
    x = np.full((14, 12, 3), a)
    y = np.full((14, 12, 3), b)
    expected = (2 * a * b + C1) / (a**2 + b**2 + C1)
    assert ssim(x, y).item() == pytest.approx(expected, abs=1e-12)


def test_ssim_matches_numpy_reference_13x13():
    x = rand_image(8, 13, 13)
    y = np.clip(x + np.random.default_rng(9).normal(0, 0.1, x.shape), 0, 1)
    assert ssim(x, y).item() == pytest.approx(ssim_numpy(x, y, 11), abs=1e-12)


@pytest.mark.parametrize("h, w, size", [(7, 9, 7), (10, 10, 9), (2, 5, 1), (1, 1, 1), (11, 30, 11)])
def test_ssim_small_images_use_largest_odd_window(h, w, size):
    assert ssim_window_size(h, w) == size
    x = rand_image(10, h, w)
    y = rand_image(11, h, w)
    assert ssim(x, y).item() == pytest.approx(ssim_numpy(x, y, size), abs=1e-12)


def test_ssim_single_pixel_window_is_luminance_term():
    x, y = rand_image(12, 2, 2), rand_image(13, 2, 2)
    expected = np.mean((2 * x * y + C1) / (x**2 + y**2 + C1))
    assert ssim(x, y).item() == pytest.approx(expected, abs=1e-12)


def test_ssim_decreases_with_noise():
    x = rand_image(14, 32, 32) * 0.6 + 0.2
    rng = np.random.default_rng(15)
    noise = rng.normal(0, 1, x.shape)
    scores = [ssim(x, x + s * noise).item() for s in (0.0, 0.01, 0.05, 0.2)]
    assert scores[0] == pytest.approx(1.0, abs=1e-12)
    assert all(a > b for a, b in zip(scores, scores[1:]))


def test_ssim_batches_and_dtypes():
    a = np.stack([rand_image(16), rand_image(17)]).astype(np.float32)
    b = np.stack([rand_image(18), rand_image(19)]).astype(np.float32)
    out = ssim(torch.from_numpy(a), torch.from_numpy(b))
    assert out.shape == (2,) and out.dtype == torch.float64
    assert out[1].item() == pytest.approx(ssim(a[1], b[1]).item(), abs=1e-15)
    assert ssim(a[None], b[None]).shape == (1, 2)


# --------------------------------------------------------------------------------------- LPIPS


def alexnet_features_twin() -> torch.nn.Sequential:
    """torchvision's ``alexnet().features`` up to relu5, layer by layer (what LPIPS slices)."""
    nn = torch.nn
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2), nn.ReLU(),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(64, 192, kernel_size=5, padding=2), nn.ReLU(),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(192, 384, kernel_size=3, padding=1), nn.ReLU(),
        nn.Conv2d(384, 256, kernel_size=3, padding=1), nn.ReLU(),
        nn.Conv2d(256, 256, kernel_size=3, padding=1), nn.ReLU(),
    )  # fmt: skip


def random_lpips_state(seed: int = 0, torchvision_names: bool = False) -> tuple[dict, torch.nn.Sequential, list]:
    torch.manual_seed(seed)
    features = alexnet_features_twin()
    lins = [torch.rand(1, c, 1, 1) * 0.1 for c in (64, 192, 384, 256, 256)]
    slices = {0: 1, 3: 2, 6: 3, 8: 4, 10: 5}
    state = {}
    for key, value in features.state_dict().items():
        idx, kind = key.split(".")
        name = f"features.{idx}.{kind}" if torchvision_names else f"net.slice{slices[int(idx)]}.{idx}.{kind}"
        state[name] = value.clone()
    for k, lin in enumerate(lins):
        state[f"lins.{k}.model.1.weight" if torchvision_names else f"lin{k}.model.1.weight"] = lin
    state["scaling_layer.shift"] = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    state["scaling_layer.scale"] = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)
    return state, features, lins


def lpips_twin(x: np.ndarray, y: np.ndarray, features: torch.nn.Sequential, lins: list) -> float:
    """LPIPS v0.1 written with nn modules: relu outputs at torchvision indices 1, 4, 7, 9, 11."""
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)

    def taps(img):
        h = (torch.from_numpy(img).float().permute(2, 0, 1)[None] * 2 - 1 - shift) / scale
        out = []
        for i, layer in enumerate(features):
            h = layer(h)
            if i in (1, 4, 7, 9, 11):
                out.append(h / (h.pow(2).sum(1, keepdim=True).sqrt() + 1e-10))
        return out

    with torch.no_grad():
        return float(sum(((a - b) ** 2 * lin).sum(1).mean() for a, b, lin in zip(taps(x), taps(y), lins)))


@pytest.fixture
def no_lpips_env(monkeypatch):
    monkeypatch.delenv(LPIPS_ENV, raising=False)


def test_lpips_returns_none_without_weights(no_lpips_env):
    x = rand_image(20, 40, 40)
    assert lpips(x, x) is None
    assert not lpips_available()
    assert lpips_unavailable_reason().startswith("no weights")
    scores = score_images([x], [x])
    assert scores["lpips"] is None and scores["lpips_note"].startswith("no weights")


def test_lpips_configured_but_missing_file(tmp_path, monkeypatch):
    missing = tmp_path / "nope.safetensors"
    assert not lpips_available(missing)
    with pytest.raises(CrfError, match="nope.safetensors: file not found"):
        lpips(rand_image(0, 32, 32), rand_image(1, 32, 32), weights_path=missing)
    monkeypatch.setenv(LPIPS_ENV, str(missing))
    assert not lpips_available()
    assert LPIPS_ENV in lpips_unavailable_reason()
    with pytest.raises(CrfError, match=LPIPS_ENV):
        lpips(rand_image(0, 32, 32), rand_image(1, 32, 32))


def test_lpips_rejects_wrong_tensor_names(tmp_path):
    path = tmp_path / "fake.safetensors"
    save_file({"conv1.weight": torch.zeros(64, 3, 11, 11), "lin.weight": torch.zeros(1, 64, 1, 1)}, str(path))
    assert lpips_available(path)  # exists; contents are checked on load
    with pytest.raises(CrfError) as e:
        lpips(rand_image(0, 32, 32), rand_image(1, 32, 32), weights_path=path)
    msg = str(e.value)
    assert "\n" not in msg and str(path.name) in msg and "net.slice1.0.weight" in msg


def test_lpips_rejects_wrong_shape_and_garbage(tmp_path):
    state, _, _ = random_lpips_state()
    state["lin2.model.1.weight"] = torch.zeros(1, 383, 1, 1)
    bad_shape = tmp_path / "shape.safetensors"
    save_file(state, str(bad_shape))
    with pytest.raises(CrfError, match=r"lin2\.model\.1\.weight has shape \[1, 383, 1, 1\], expected \[1, 384, 1, 1\]"):
        load_lpips_weights(bad_shape)
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(b"\x00\x01 this is not safetensors")
    with pytest.raises(CrfError, match="garbage.safetensors: not a readable safetensors file"):
        load_lpips_weights(garbage)
    state, _, _ = random_lpips_state()
    state["net.slice3.6.bias"][0] = float("nan")
    nan_file = tmp_path / "nan.safetensors"
    save_file(state, str(nan_file))
    with pytest.raises(CrfError, match="not finite"):
        load_lpips_weights(nan_file)


def test_lpips_matches_module_twin(tmp_path, monkeypatch):
    state, features, lins = random_lpips_state(seed=3)
    path = tmp_path / "alex.safetensors"
    save_file(state, str(path))
    x = rand_image(21, 64, 48).astype(np.float32)
    y = np.clip(x + np.random.default_rng(22).normal(0, 0.1, x.shape), 0, 1).astype(np.float32)
    expected = lpips_twin(x, y, features, lins)
    got = lpips(x, y, weights_path=path)
    assert got.shape == () and got.dtype == torch.float32
    assert got.item() == pytest.approx(expected, rel=1e-4)
    assert got.item() > 0
    assert lpips(x, x, weights_path=path).item() == 0.0
    assert lpips(y, x, weights_path=path).item() == pytest.approx(got.item(), rel=1e-5)
    batch = lpips(np.stack([x, x]), np.stack([y, x]), weights_path=path)
    assert batch.shape == (2,) and batch[1].item() == 0.0
    assert batch[0].item() == pytest.approx(got.item(), rel=1e-4)
    monkeypatch.setenv(LPIPS_ENV, str(path))
    assert lpips_available()
    scores = score_images([x, x], [y, x])
    assert scores["n"] == 2 and scores["lpips_note"] is None
    assert scores["lpips"] == pytest.approx(got.item() / 2, rel=1e-4)
    assert scores["psnr"] == math.inf


def test_lpips_accepts_alias_names(tmp_path):
    state, _, _ = random_lpips_state(seed=4)
    tv_state, _, _ = random_lpips_state(seed=4, torchvision_names=True)
    assert "features.10.weight" in tv_state and "lins.4.model.1.weight" in tv_state
    a, b = tmp_path / "lpips.safetensors", tmp_path / "tv.safetensors"
    save_file(state, str(a))
    save_file(tv_state, str(b))
    x, y = rand_image(23, 40, 40), rand_image(24, 40, 40)
    assert lpips(x, y, weights_path=a).item() == lpips(x, y, weights_path=b).item()


def test_lpips_too_small_images(tmp_path):
    state, _, _ = random_lpips_state()
    path = tmp_path / "alex.safetensors"
    save_file(state, str(path))
    x = rand_image(25, 30, 64)
    with pytest.raises(CrfError, match="at least 31"):
        lpips(x, x, weights_path=path)
    scores = score_images([x], [x], lpips_weights=path)
    assert scores["lpips"] is None and "smaller than 31" in scores["lpips_note"]
    assert lpips_from_weights(rand_image(26, 31, 31), rand_image(27, 31, 31), load_lpips_weights(path)).item() > 0


def test_lpips_tensor_names_are_documented():
    names = lpips_tensor_names()
    assert len(names) == 15
    for name in names:
        assert name in metrics.lpips_tensor_names.__doc__


# -------------------------------------------------------------------------------------- tables


def test_score_images_averages_per_image(no_lpips_env):
    x = rand_image(28, 20, 20) * 0.8
    preds = [x + 0.1, x + 0.01]  # 20 dB and 40 dB
    scores = score_images(preds, [x, x])
    assert scores["n"] == 2
    assert scores["psnr"] == pytest.approx(30.0, abs=1e-9)
    assert scores["ssim"] == pytest.approx((ssim(preds[0], x).item() + ssim(preds[1], x).item()) / 2, abs=1e-15)
    stacked = score_images(np.stack(preds), np.stack([x, x]))
    assert stacked["psnr"] == pytest.approx(scores["psnr"], abs=1e-12)
    with pytest.raises(ValueError):
        score_images(preds, [x])
