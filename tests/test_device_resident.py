"""The device-resident training step (issue 15): fixed-capacity packing, the fixed-shape march
against the reference march (forward, gradients, training steps), no host read inside a step
(profiler counts), the deferred non-finite guard, the compiled field, per-device defaults.

CUDA-only checks skip without a GPU; everything else runs the same code with ``device="cpu"``.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import shutil

import pytest
import torch

import crfedit.train
from crfedit.cameras import Rays
from crfedit.config import DEVICE_DEFAULTS, Config, make_config
from crfedit.data import load_category
from crfedit.data.loading import training_rays
from crfedit.errors import NonFiniteError
from crfedit.field import ConditionalRadianceField
from crfedit.model import load_model
from crfedit.opcount import count_events, profile_training
from crfedit.optim import run_adam
from crfedit.renderer import FixedMarch, render_rays
from crfedit.sampling import pack_mask
from crfedit.train import BatchSampler, batch_mean, batch_mse, make_optimizer, train

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
HAS_COMPILER = shutil.which("g++") is not None or shutil.which("c++") is not None


def test_pack_mask_hand_case():
    keep = torch.tensor([[True, False, True], [False, True, False]])
    p = pack_mask(keep, 4)
    assert p.ray.tolist() == [0, 0, 1, 1] and p.col.tolist() == [0, 2, 1, 0]
    assert p.valid.tolist() == [True, True, True, False] and p.first.tolist() == [0, 2]
    assert p.fits.tolist() == [True, True] and int(p.count) == 3


@pytest.mark.parametrize("capacity", [1, 40, 97, 400])
def test_pack_mask_is_nonzero_up_to_the_capacity(capacity):
    keep = torch.rand(23, 9, generator=torch.Generator().manual_seed(3)) < 0.45
    ray, col = keep.nonzero(as_tuple=True)
    p = pack_mask(keep, capacity)
    m = min(capacity, ray.numel())
    assert torch.equal(p.ray[:m], ray[:m]) and torch.equal(p.col[:m], col[:m])
    assert int(p.valid.sum()) == m and int(p.count) == ray.numel()
    end = torch.cumsum(keep.sum(1), 0)
    assert torch.equal(p.fits, end <= capacity)
    assert (p.ray[m:] == 22).all()  # padding sits on the last ray, keeping the slots sorted


def field_with_surfaces(seed: int = 0) -> ConditionalRadianceField:
    """A small fast-preset field whose density is high enough that many rays terminate early,
    and a random occupancy grid per instance."""
    cfg = dataclasses.replace(  # 32 cells: 57 marching steps, two segments
        Config(), code_dim=4, code_embed=4, width=16, rad_width=16, grid_res=4, grid_features=2, occ_res=32
    ).validated()
    torch.manual_seed(seed)
    field = ConditionalRadianceField(cfg, 2)
    with torch.no_grad():
        field.shape_codes.normal_()
        field.color_codes.normal_()
        field.F_dens.bias.fill_(-1.0)  # about half the rays end in the first segment, the rest go on
        field.occupancy.copy_(torch.rand(field.occupancy.shape) < 0.35)
    return field


def ray_batch(n: int = 300, seed: int = 1) -> tuple[Rays, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * 2.0
    targets = (torch.rand(n, 3, generator=g) - 0.5) * 0.8
    dirs = torch.nn.functional.normalize(targets - origins, dim=-1)
    return Rays(origins, dirs), torch.randint(2, (n,), generator=g), torch.rand(n, generator=g)


def render_and_grads(field, march, rays, inst, jitter):
    field.zero_grad(set_to_none=True)
    out = render_rays(field, rays, inst, early_stop=1e-3, jitter=jitter, march=march)
    weights = torch.linspace(0.5, 1.5, 3)
    ((out.rgb * weights).sum() + out.depth.sum() + out.opacity.sum()).backward()
    return out, {n: p.grad.clone() for n, p in field.named_parameters() if p.grad is not None}


def test_fixed_march_equals_the_reference_forward_and_gradients():
    field = field_with_surfaces()
    rays, inst, jitter = ray_batch()
    ref, ref_grads = render_and_grads(field, None, rays, inst, jitter)
    march = FixedMarch(field)
    out, grads = render_and_grads(field, march, rays, inst, jitter)
    assert out.complete.all() and int(out.n_samples) == ref.n_samples
    assert len(march.segments) == 2 and march.needed[1] > 0  # some rays lived on into the second segment …
    early = render_rays(field, rays, inst, early_stop=None, jitter=jitter)
    assert ref.n_samples < early.n_samples  # … and some ended in the first
    for name in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=0, atol=1e-5)
    assert grads.keys() == ref_grads.keys()
    for name, g in grads.items():
        torch.testing.assert_close(g, ref_grads[name], rtol=1e-4, atol=1e-5, msg=name)


def test_overflowing_rays_are_flagged_and_the_buffer_grows():
    field = field_with_surfaces()
    rays, inst, jitter = ray_batch()
    ref = render_rays(field, rays, inst, early_stop=1e-3, jitter=jitter)
    march = FixedMarch(field)
    march.capacity = [64] * len(march.segments)  # far too small for 300 rays
    out = render_rays(field, rays, inst, early_stop=1e-3, jitter=jitter, march=march)
    ok = out.complete
    assert 0 < int(ok.sum()) < 300
    torch.testing.assert_close(out.rgb[ok], ref.rgb[ok], rtol=0, atol=1e-5)  # the complete rays are exact
    assert march.resize() == 300 - int(ok.sum())  # dropped rays reported at the read-out
    assert all(c > 64 for c in march.capacity)
    assert render_rays(field, rays, inst, early_stop=1e-3, jitter=jitter, march=march).complete.all()


def test_fixed_march_distortion_equals_the_reference():
    field = field_with_surfaces()
    rays, inst, jitter = ray_batch()
    ref = render_rays(field, rays, inst, early_stop=1e-3, jitter=jitter, distortion=True)
    out = render_rays(field, rays, inst, early_stop=1e-3, jitter=jitter, march=FixedMarch(field), distortion=True)
    assert float(ref.distortion.detach().max()) > 0
    torch.testing.assert_close(out.distortion, ref.distortion, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("distortion", [0.0, 0.05])
def test_training_steps_equal_the_reference(tiny_chairs, distortion):
    """Five Adam steps on the same batches (each ray over its own random background colour),
    fixed-shape march against the reference march; with the distortion loss too."""
    category = load_category(tiny_chairs)
    cfg = make_config("fast", overrides=dict(rays=128, occ_res=16, grid_res=16, distortion=distortion))
    torch.manual_seed(0)
    fields = [ConditionalRadianceField(cfg, 2, crfedit.train.scene_box(category))]
    fields.append(copy.deepcopy(fields[0]))
    marches = [None, FixedMarch(fields[1])]
    sampler = BatchSampler(training_rays(category, "train"), torch.device("cpu"), random_background=True)
    opts = [make_optimizer(f, cfg) for f in fields]
    gens = [torch.Generator().manual_seed(7) for _ in fields]
    for _ in range(5):
        for field, march, opt, gen in zip(fields, marches, opts, gens):
            batch = sampler(cfg.rays, gen)
            out = render_rays(field, batch.rays, batch.instance, generator=gen, early_stop=cfg.train_early_stop,
                              jitter=batch.jitter, march=march, background=batch.background, distortion=distortion > 0)
            opt.zero_grad()
            loss = batch_mse(out.rgb, batch.rgb, out.complete)
            if distortion > 0:
                loss = loss + distortion * batch_mean(out.distortion, out.complete)
            loss.backward()
            opt.step()
    for (name, a), b in zip(fields[0].named_parameters(), fields[1].parameters()):
        torch.testing.assert_close(b, a, rtol=1e-4, atol=2e-5, msg=name)


def test_a_training_step_reads_nothing_back(tiny_chairs):
    """Between read-outs (every 8 steps here) a step makes no host read and no nonzero, an
    occupancy refresh included (every 4 steps from step 4).  (The read-out's ``.tolist()`` is no
    aten op on a CPU, so the profiler cannot see it there; on CUDA it is a synchronization.)"""
    category = load_category(tiny_chairs)
    cfg = make_config("fast", overrides=dict(rays=128, occ_res=16, grid_res=16, occ_warmup=4, occ_every=4))
    quiet = profile_training(category, cfg, torch.device("cpu"), first=8, count=7, read_every=8, fixed_shapes=True)
    assert quiet.host_reads == 0 and quiet.item == 0 and quiet.nonzero == 0, quiet
    assert quiet.top_level_ops > 50  # the profiler did see the steps
    exact = profile_training(category, cfg, torch.device("cpu"), first=8, count=7, read_every=8, fixed_shapes=False)
    assert exact.nonzero > 0  # the CPU's default march sizes its samples exactly: reads, free on a CPU


def test_the_reference_march_does_read_back():
    """The counter catches what the device-resident step avoids: the reference march's reads."""
    field = field_with_surfaces()
    rays, inst, jitter = ray_batch()
    with torch.profiler.profile() as prof:
        render_rays(field, rays, inst, early_stop=1e-3, jitter=jitter)
    reference = count_events(prof.events(), 1)
    march = FixedMarch(field)
    counts = []
    for _ in range(2):
        with torch.profiler.profile() as prof:
            render_rays(field, rays, inst, early_stop=1e-3, jitter=jitter, march=march)
        counts.append(count_events(prof.events(), 1))
    assert reference.host_reads >= 2 and reference.nonzero >= 1, reference
    sized = sum(300 * count > march.DENSE_SLOTS for _, count in march.segments)  # the others hold every step
    assert sized == 1 and counts[0].host_reads == sized and counts[0].nonzero == 0  # the first batch sizes its buffer
    assert counts[1].host_reads == 0 and counts[1].nonzero == 0, counts[1]


def test_count_events_finds_host_reads():
    with torch.profiler.profile() as prof:
        x = torch.arange(5.0)
        float(x.sum())
        (x > 2).nonzero()
        x[x > 2]
    counts = count_events(prof.events(), steps=1)
    assert counts.host_reads == 1 and counts.item == 1 and counts.nonzero == 2


def test_count_events_leaves_out_the_profilers_own_synchronization():
    """Measured on an H200: the profiler issues one cudaDeviceSynchronize, under no op, when it
    stops; a step's read syncs inside an op (here aten::copy_), and one issued by no op between
    the steps' ops is the steps' too."""
    from types import SimpleNamespace as E

    span = lambda a, b: E(start=a, end=b)
    copy = E(name="aten::copy_", cpu_parent=None, time_range=span(0, 10))
    add = E(name="aten::add", cpu_parent=None, time_range=span(20, 30))
    events = [
        copy, add,
        E(name="cudaStreamSynchronize", cpu_parent=copy, time_range=span(5, 6)),  # a read: the steps'
        E(name="cudaDeviceSynchronize", cpu_parent=None, time_range=span(12, 13)),  # between ops: the steps'
        E(name="cudaLaunchKernel", cpu_parent=add, time_range=span(21, 22)),
        E(name="cudaDeviceSynchronize", cpu_parent=None, time_range=span(40, 41)),  # the profiler's stop
    ]
    counts = count_events(events, steps=2, cuda=True)
    assert counts.synchronizations == 1.0 and counts.kernel_launches == 0.5 and counts.aten_ops == 1.0
    assert count_events(events, steps=2).synchronizations is None


def sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_nan_between_read_outs_never_reaches_a_checkpoint(tiny_chairs, tmp_path, monkeypatch):
    """Reads every 16 steps, checkpoints every 5: NaN at step 7 is noticed by the step-10
    checkpoint's read, which raises naming step 7 and leaves the step-5 file byte for byte."""
    out = tmp_path / "m.safetensors"
    real, calls = crfedit.train.render_rays, [0]

    def poisoned(*args, **kwargs):
        calls[0] += 1
        r = real(*args, **kwargs)
        return dataclasses.replace(r, rgb=r.rgb * float("nan")) if calls[0] == 8 else r

    monkeypatch.setattr(crfedit.train, "render_rays", poisoned)
    hashes = {}

    def on_step(step, *_):
        if out.exists():
            hashes[step] = sha(out)

    cfg = make_config("fast", overrides=dict(steps=30, rays=64, checkpoint_every=5))
    with pytest.raises(NonFiniteError, match="training diverged at step 7 .*keeps its last checkpoint"):
        train(load_category(tiny_chairs), cfg, out, torch.device("cpu"), on_step=on_step, read_every=16, fixed_shapes=True)
    assert calls[0] == 10 and sha(out) == hashes[6] == hashes[9]


def test_fixed_shape_resume_is_bit_identical(tiny_chairs, tmp_path):
    """Ctrl-C at step 11 and --resume reach the uninterrupted run's weights and state exactly:
    the march's buffer sizes and running counts (resized every 4 steps) are in the checkpoint."""
    category = load_category(tiny_chairs)
    cfg = make_config("fast", overrides=dict(steps=20, rays=512, occ_res=16, grid_res=16, occ_warmup=3, occ_every=3,
                                             checkpoint_every=10**9))
    run = dict(seed=3, read_every=4, fixed_shapes=True)
    full, part = tmp_path / "full.safetensors", tmp_path / "part.safetensors"
    train(category, cfg, full, torch.device("cpu"), **run)

    def stop(step, *_):
        if step == 11:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(category, cfg, part, torch.device("cpu"), on_step=stop, **run)
    assert load_model(part)[1]["march.capacity"].min() > 0  # the buffers were sized, not dense
    train(category, cfg, part, torch.device("cpu"), resume=True, **run)
    (a, state_a), (b, state_b) = load_model(full), load_model(part)
    assert all(torch.equal(v, b.state()[k]) for k, v in a.state().items())
    assert all(torch.equal(v, state_b[k]) for k, v in state_a.items() if k != "elapsed")


def test_run_adam_reads_once_and_names_the_first_nan_step():
    w = torch.nn.Parameter(torch.ones(3))
    opt = torch.optim.Adam([w], lr=0.1, fused=True)
    with torch.profiler.profile() as prof:
        run_adam(opt, lambda: ((w - 2.0) ** 2).sum(), 10, "edit")
    assert count_events(prof.events(), 1).host_reads <= 2  # the loss log and the weight check, at the end
    losses = iter([1.0, 2.0, float("nan"), 1.0])
    with pytest.raises(NonFiniteError, match="edit diverged at step 2 "):
        run_adam(opt, lambda: (w * 0).sum() + next(losses), 4, "edit")


def test_device_defaults_sit_between_preset_and_overrides(monkeypatch):
    assert make_config("fast") == make_config("fast", device_type="cpu") == Config()  # CPU defaults unchanged
    monkeypatch.setitem(DEVICE_DEFAULTS, ("fast", "cuda"), {"rays": 4096, "lr": 5e-3})
    cfg = make_config("fast", device_type="cuda")
    assert (cfg.rays, cfg.lr, cfg.preset) == (4096, 5e-3, "fast")
    assert make_config("fast", overrides={"rays": 512}, device_type="cuda").rays == 512
    assert make_config("fast", sets=["lr=0.02"], device_type="cuda").lr == 0.02
    assert make_config("paper", device_type="cuda") == make_config("paper")


@pytest.mark.skipif(not HAS_COMPILER, reason="torch.compile (inductor) needs a C++ compiler")
def test_compiled_field_equals_eager_forward_gradients_and_training(tiny_chairs, tmp_path):
    field = field_with_surfaces()
    rays, inst, jitter = ray_batch(n=200)
    eager, eager_grads = render_and_grads(field, FixedMarch(field), rays, inst, jitter)
    fused, fused_grads = render_and_grads(field, FixedMarch(field, compile=True), rays, inst, jitter)
    torch.testing.assert_close(fused.rgb, eager.rgb, rtol=0, atol=1e-5)
    for name, g in eager_grads.items():
        torch.testing.assert_close(fused_grads[name], g, rtol=1e-4, atol=1e-5, msg=name)
    category = load_category(tiny_chairs)
    cfg = make_config("fast", overrides=dict(steps=4, rays=64, occ_res=16, grid_res=16))
    models = [train(category, cfg, tmp_path / f"{c}.safetensors", torch.device("cpu"), compile=c, fixed_shapes=True)[0]
              for c in (False, True)]
    for (name, a), b in zip(models[0].field.named_parameters(), models[1].field.parameters()):
        torch.testing.assert_close(b, a, rtol=1e-4, atol=2e-5, msg=name)


@CUDA
def test_cuda_march_equals_cpu():
    field = field_with_surfaces()
    rays, inst, jitter = ray_batch()
    cpu = render_rays(field, rays, inst, early_stop=1e-3, jitter=jitter, march=FixedMarch(field))
    gpu_field = copy.deepcopy(field).to("cuda")
    gpu_rays = Rays(rays.origins.to("cuda"), rays.directions.to("cuda"))
    gpu = render_rays(gpu_field, gpu_rays, inst.to("cuda"), early_stop=1e-3, jitter=jitter.to("cuda"), march=FixedMarch(gpu_field))
    torch.testing.assert_close(gpu.rgb.cpu(), cpu.rgb, rtol=0, atol=1e-4)


@CUDA
def test_cuda_training_step_does_not_synchronize(tiny_chairs):
    category = load_category(tiny_chairs)
    cfg = make_config("fast", overrides=dict(rays=128, occ_res=16, grid_res=16, occ_warmup=4, occ_every=4))
    counts = profile_training(category, cfg, torch.device("cuda"), first=8, count=7, read_every=8)
    assert counts.host_reads == 0 and counts.nonzero == 0 and counts.synchronizations == 0, counts
