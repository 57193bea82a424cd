"""The edits' Adam (:class:`crfedit.optim.FusedAdam`): torch.optim's fused Adam to the bit,
and an edit in a fresh process that never imports torch._dynamo (torch.optim's first use
does, 0.75 s on this project's CPU)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from crfedit.optim import FusedAdam


CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=CUDA)])
@pytest.mark.parametrize("eps", [1e-8, 1e-15])
def test_fused_adam_equals_torch_adam_to_the_bit(eps, device):
    g = torch.Generator().manual_seed(0)
    start = [torch.randn(7, 5, generator=g), torch.randn(5, generator=g), torch.randn(3, generator=g)]
    start = [t.to(device) for t in start]
    ours = [t.clone().requires_grad_() for t in start]
    theirs = [t.clone().requires_grad_() for t in start]
    opt_ours, opt_theirs = FusedAdam(ours, lr=0.03, eps=eps), torch.optim.Adam(theirs, lr=0.03, eps=eps, fused=True)
    x = torch.randn(11, 7, generator=g).to(device)
    for step in range(6):
        for params, opt in ((ours, opt_ours), (theirs, opt_theirs)):
            opt.zero_grad(set_to_none=True)
            w, b, c = params
            loss = ((x @ w + b).tanh() ** 2).mean()
            if step % 2:  # the third tensor gets no gradient on odd steps: skipped, its step count held
                loss = loss + (c**3).sum()
            loss.backward()
            opt.step()
        for a, t in zip(ours, theirs):
            assert torch.equal(a, t), f"step {step}: {(a - t).abs().max()}"
    assert [float(s[2]) for s in opt_ours.state.values()] == [6.0, 6.0, 3.0]


def test_fused_adam_groups_equal_torch_adam_groups_to_the_bit():
    """Parameter groups with their own learning rates (fit-real's codes and weights)."""
    g = torch.Generator().manual_seed(1)
    start = [torch.randn(4, 3, generator=g), torch.randn(3, generator=g), torch.randn(6, generator=g)]
    ours, theirs = [[t.clone().requires_grad_() for t in start] for _ in range(2)]
    opt_ours = FusedAdam([{"params": ours[:2], "lr": 0.05}, {"params": ours[2:], "lr": 1e-3}])
    opt_theirs = torch.optim.Adam([{"params": theirs[:2], "lr": 0.05}, {"params": theirs[2:], "lr": 1e-3}], fused=True)
    x = torch.randn(5, 4, generator=g)
    for step in range(5):
        for (w, b, c), opt in ((ours, opt_ours), (theirs, opt_theirs)):
            opt.zero_grad(set_to_none=True)
            (((x @ w + b).tanh() ** 2).mean() + (c.sin() ** 2).sum()).backward()
            opt.step()
    assert all(torch.equal(a, t) for a, t in zip(ours, theirs))
    assert not torch.equal(ours[2], start[2]) and (ours[2] - start[2]).abs().max() < 0.01  # the small lr moved it a little


def test_an_edit_does_not_import_the_compiler(edit_category):
    """A colour edit and a removal in a fresh interpreter leave torch._dynamo unimported."""
    path, _, category = edit_category
    probe = "import sys, torch; print('torch._dynamo' in sys.modules)"
    if subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True).stdout.strip() != "False":
        pytest.skip("this torch imports torch._dynamo with torch itself")
    script = f"""
import sys, json
from crfedit.model import load_model
from crfedit.data.loading import load_category
from crfedit.edit import EditOptions, edit_color, remove
model, _ = load_model({str(path)!r})
category = load_category({str(category.root)!r}, with_parts=True)
view = category.instances[0].splits["train"][0]
fg = view.parts == view.parts.max()
opts = EditOptions(steps=3)
edit_color(model, 0, view.camera, fg, "red", None, opts)
remove(model, 0, view.camera, fg, None, options=opts)
print(json.dumps('torch._dynamo' in sys.modules))
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "false"


def test_a_loss_that_ends_far_above_its_start_is_divergence():
    """check_descent: the last tenth's mean against RISE_LIMIT × the first loss; fewer than 10
    steps are not judged (one step's random rays may cost more than the first's)."""
    from crfedit.errors import NonFiniteError
    from crfedit.optim import RISE_LIMIT, check_descent

    with pytest.raises(NonFiniteError, match=r"^edit diverged: its loss rose from 2 to 50 over 10 steps \(a learning rate too large, or too few steps for a rise to settle: a lower --lr or more --steps\); nothing"):
        check_descent([2.0] + [1.0] * 8 + [50.0], "edit", "nothing was written")  # the last tenth: the last step
    check_descent([2.0] + [9.0] * 8 + [1.0], "edit", "x")  # high in the middle, low at the end: a fit that got there
    check_descent([2.0] * 9, "edit", "x")  # 9 steps: not judged
    check_descent([1.0] * 19 + [RISE_LIMIT, RISE_LIMIT], "edit", "x")  # at the limit: kept
    with pytest.raises(NonFiniteError):
        check_descent([1.0] * 18 + [RISE_LIMIT + 0.01, RISE_LIMIT + 0.01], "edit", "x")


def test_run_adam_refuses_a_rise_only_when_asked():
    """A quadratic from x = 1 at a learning rate that overshoots keeps its loss finite and rising
    (Adam's steps are about lr long): refused with refuse_rise, returned without it."""
    from crfedit.errors import NonFiniteError
    from crfedit.optim import FusedAdam, run_adam

    for refuse in (False, True):
        x = torch.tensor([1.0], requires_grad=True)
        opt = FusedAdam([x], lr=10.0)
        run = lambda: run_adam(opt, lambda: (x * x).sum(), 20, "fit", refuse_rise=refuse)
        if refuse:
            with pytest.raises(NonFiniteError, match="fit diverged: its loss rose from 1 to"):
                run()
        else:
            assert run() > 1.5
    x = torch.tensor([1.0], requires_grad=True)
    assert run_adam(FusedAdam([x], lr=0.1), lambda: (x * x).sum(), 20, "fit", refuse_rise=True) < 1.0
