"""The selection-supervised edits on a CUDA device agree with the CPU's (skipped without CUDA).

A recolour once crashed on CUDA while every CPU test passed (the scribbled pixels' colours stayed
on the CPU): these tests run the library's edit paths on the GPU and compare them with the same
calls on the CPU.  Float kernels differ between the devices, so the comparisons are tolerances,
not bit-identity; the delta written on the GPU must load and render on the CPU.
"""

from __future__ import annotations

import copy

import pytest
import torch

from crfedit.delta import apply_edit_files
from crfedit.edit import EditOptions, edit_color, remove
from crfedit.edit.selection import ScribbleView, select
from crfedit.metrics import psnr
from crfedit.renderer import render_camera

from test_selection import part_view

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@pytest.fixture(scope="module")
def both(edit_category):
    _, model, category = edit_category
    gpu = copy.deepcopy(model).to("cuda")
    return model, gpu, category


def test_cuda_model_has_the_cpu_fingerprint_and_renders_alike(both):
    cpu, gpu, category = both
    assert gpu.device.type == "cuda" and gpu.fingerprint() == cpu.fingerprint()
    v = category.instances[2].splits["test"][0]
    a, b = render_camera(cpu.field_for(2), v.camera, 2), render_camera(gpu.field_for(2), v.camera, 2)
    assert b.rgb.device.type == "cuda"
    assert float(psnr(b.rgb.cpu(), a.rgb)) > 45


def test_cuda_selection_matches_the_cpu_selection(both):
    cpu, gpu, category = both
    view, fg, keep, _ = part_view(category, 2, "seat")
    a = select(cpu, 2, [ScribbleView(view.camera, fg, keep)])
    b = select(gpu, 2, [ScribbleView(view.camera, fg, keep)])
    inter = int((a.mask & b.mask.cpu()).sum())
    union = int((a.mask | b.mask.cpu()).sum())
    assert union > 0 and inter / union > 0.97, inter / union
    b.check_for(cpu, 2)  # a selection made on the GPU serves the same model on the CPU


@pytest.mark.parametrize("kind", ["color", "remove"])
def test_cuda_edit_matches_the_cpu_edit_and_its_delta_loads_on_the_cpu(both, tmp_path, kind):
    cpu, gpu, category = both
    view, fg, keep, _ = part_view(category, 2, "seat")
    sel = select(cpu, 2, [ScribbleView(view.camera, fg, keep)])
    opts = EditOptions(steps=40)
    if kind == "color":
        a, b = (edit_color(m, 2, view.camera, fg, (0.9, 0.1, 0.1), keep, options=opts, selection=sel) for m in (cpu, gpu))
    else:
        a, b = (remove(m, 2, view.camera, fg, keep, options=opts, selection=sel) for m in (cpu, gpu))
    assert all(bool(torch.isfinite(t.float()).all()) for t in b.tensors.values())  # (a delta's tensors live on the CPU)
    path = tmp_path / "gpu.safetensors"
    b.save(path)
    from_gpu = apply_edit_files(cpu, [path])
    for v in category.instances[2].splits["test"][:3]:
        ra = render_camera(a.model.field_for(2), v.camera, 2).rgb
        rb = render_camera(from_gpu.field_for(2), v.camera, 2).rgb
        before = render_camera(cpu.field_for(2), v.camera, 2).rgb
        # the GPU's edit is the CPU's edit: far closer to it than the edit is to no edit
        assert float(psnr(rb, ra)) > max(35.0, float(psnr(before, ra)) + 10), (float(psnr(rb, ra)), float(psnr(before, ra)))
