"""Data-parallel training over torch.distributed (gloo, CPU): two real processes on 127.0.0.1.

One spawned pair of ranks (:func:`_two_ranks`, run once per module) does every distributed run,
each rank writing what it saw into files the tests then compare:

* ``eq``: 6 steps fed the same rays as a single process (``train(batches=...)``), with grid
  refreshes at steps 2, 4 and 6;
* ``full``: 16 steps of the real per-rank sampler, refreshes every 4 steps, a checkpoint at 8;
* ``crash``: rank 1 dies at step 12 of 24 (a checkpoint was written at 8); rank 0 must stop
  with a :class:`DistributedError` and leave the step-8 file loadable;
* ``render``/``recon``: the ``full`` model's 5-view orbit (with a GIF) rendered and its views
  scored with the work shared out over the two ranks;
* ``repair``: rank 1's copy of a tensor differs, :meth:`Ranks.same_on_all` restores rank 0's;
* ``mismatch``: rank 1 is started with another seed, both refuse (:meth:`Ranks.agree`).
"""

from __future__ import annotations

import json
import multiprocessing
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from crfedit.cameras import Rays
from crfedit.render_files import render_to_folder
from crfedit.config import make_config
from crfedit.data import load_category
from crfedit.data.loading import training_rays
from crfedit.distributed import SINGLE as SINGLE_RANK
from crfedit.distributed import DistributedError, Ranks, broken, process_group, rank_device, rank_seed, ranks_from_env
from crfedit.errors import CrfError
from crfedit.data.synth import SynthConfig, write_synth_category
from crfedit.edit import EditOptions
from crfedit.evaluation import NERF_BASELINE, NerfBaseline, evaluate_edits, evaluate_recon, load_twin_cases
from crfedit.model import load_model
from crfedit.renderer import render_camera
from crfedit.train import TrainBatch, train

EQ = dict(steps=6, rays=64, occ_warmup=2, occ_every=2, checkpoint_every=100)
FULL = dict(steps=16, rays=64, occ_warmup=4, occ_every=4, checkpoint_every=8)
CRASH = dict(steps=24, rays=64, occ_warmup=4, occ_every=4, checkpoint_every=8)
CPU = torch.device("cpu")
ORBIT = "orbit:5"


class SameRays:
    """Step s's batch of B rays, identical at every world size: rank r of w takes the r-th of w
    contiguous blocks (the split :meth:`Ranks.share` sizes), with its sample offsets."""

    def __init__(self, category, ranks: Ranks):
        self.data, self.ranks, self.step = training_rays(category), ranks, 0

    def __call__(self, n: int, generator: torch.Generator) -> TrainBatch:
        g = torch.Generator().manual_seed(1000 + self.step)
        total = n * self.ranks.world  # 64 rays over 1 or 2 ranks: the shares are equal
        idx = torch.randint(len(self.data.rgb), (total,), generator=g)
        jitter = torch.rand(total, generator=g)
        idx, jitter = idx.tensor_split(self.ranks.world)[self.ranks.rank], jitter.tensor_split(self.ranks.world)[self.ranks.rank]
        self.step += 1
        d = self.data
        return TrainBatch(Rays(d.origins[idx], d.directions[idx]), d.rgb[idx], d.instance[idx], jitter)


def _dump(model, path: Path) -> None:
    save_file({k: v.contiguous() for k, v in model.state().items()}, str(path))


def twin_report(model, twins: Path, ranks: Ranks = SINGLE_RANK) -> dict:
    """``evaluate_edits`` on a tiny twins dataset, timings removed (they differ run to run)."""
    category = load_category(twins)
    cases = load_twin_cases(model, category)
    report = evaluate_edits(model, category, cases, ("hybrid",), EditOptions(steps=2, rays=32), ranks=ranks, paper=False,
                            nerf=NerfBaseline(steps=3))  # shared by source chair, listed after the rest, as one process lists it
    runs = [{k: v for k, v in r.items() if k != "seconds"} for r in report["runs"]]
    return {"runs": runs, "skipped": report["skipped"], "nerf_trained": sorted(report["nerf_train_seconds"])}


def _worker(rank: int, port: int, data: str, out: str) -> None:
    """One rank: the runs the module docstring lists, results as files under ``out``."""
    torch.set_num_threads(1)
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    out_dir, category = Path(out), load_category(Path(data))
    ranks = Ranks(rank, 2, rank)
    with process_group(ranks, CPU, timeout_s=30):
        cfg = make_config("fast", overrides=EQ)
        model, _ = train(category, cfg, out_dir / "eq.safetensors", CPU, seed=0, ranks=ranks, batches=SameRays(category, ranks))
        _dump(model, out_dir / f"eq.rank{rank}.safetensors")
        model, _ = train(category, make_config("fast", overrides=FULL), out_dir / "full.safetensors", CPU, seed=0, ranks=ranks)
        _dump(model, out_dir / f"full.rank{rank}.safetensors")
        full, _ = load_model(out_dir / "full.safetensors")
        render_to_folder(full, 0, ORBIT, out_dir / "render", video=out_dir / "orbit.gif", ranks=ranks)
        score = evaluate_recon(full, category, "train", ranks=ranks)
        (out_dir / f"recon.rank{rank}.json").write_text(json.dumps(score))
        report = twin_report(full, out_dir / "twins", ranks)
        (out_dir / f"edits.rank{rank}.json").write_text(json.dumps(report))

        probe = torch.arange(6.0) + 10 * rank
        same = ranks.same_on_all([probe], "a probe")
        (out_dir / f"repair.rank{rank}.json").write_text(json.dumps({"same": same, "probe": probe.tolist()}))

        # rank 1 started with another seed, then with its images at another size (--res, or
        # another node's copy of the data): both refuse before the first step, naming it
        for name, data_k, seed_k in (("seed", category, rank), ("images", load_category(Path(data), res=8) if rank else category, 0)):
            try:
                train(data_k, make_config("fast", overrides=FULL), out_dir / "mismatch.safetensors", CPU, seed=seed_k, ranks=ranks)
                outcome = ["finished", None]
            except DistributedError as e:
                outcome = [str(e), e.echoed]
            (out_dir / f"mismatch-{name}.rank{rank}.json").write_text(json.dumps(outcome))

        def die(step, *_):
            if rank == 1 and step == 12:
                os._exit(3)  # a rank lost without a word, as on a killed node

        try:
            train(category, make_config("fast", overrides=CRASH), out_dir / "crash.safetensors", CPU, seed=0, ranks=ranks, on_step=die)
            outcome = "finished"
        except DistributedError as e:
            outcome = str(e)
        (out_dir / f"crash.rank{rank}.txt").write_text(outcome)
        (out_dir / f"broken.rank{rank}.txt").write_text(str(broken()))
    if broken():  # as the command line does: no teardown of a group whose peer died (it can abort)
        os._exit(0)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def two_ranks(tiny_chairs, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dist")
    write_synth_category(out / "twins", SynthConfig(instances=2, views=6, res=16, seed=0, twins=True))
    ctx = multiprocessing.get_context("spawn")
    port = _free_port()
    procs = [ctx.Process(target=_worker, args=(r, port, str(tiny_chairs), str(out))) for r in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=240)
    codes = [p.exitcode for p in procs]
    for p in procs:
        if p.is_alive():
            p.kill()
    assert codes[1] == 3, f"rank 1 should have died with code 3, got {codes}"
    assert codes[0] == 0, f"rank 0 failed ({codes})"
    return out


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_ranks_end_bit_identical_with_identical_grids(two_ranks):
    for run in ("eq", "full"):
        r0, r1 = (load_file(str(two_ranks / f"{run}.rank{r}.safetensors")) for r in (0, 1))
        assert _same(r0, r1), run
        hull = r0["field.occupancy"]
        assert 0 < int(hull.sum()) < hull.numel()  # refreshed grids, neither empty nor full
    assert not torch.equal(load_file(str(two_ranks / "eq.rank0.safetensors"))["field.shape_codes"],
                           load_file(str(two_ranks / "full.rank0.safetensors"))["field.shape_codes"])


def test_the_model_file_is_rank_0s_state_and_renders_in_one_process(two_ranks):
    model, state = load_model(two_ranks / "full.safetensors")
    assert model.meta["step"] == "16" and int(state["world"]) == 2
    assert _same({k: v for k, v in model.state().items()}, load_file(str(two_ranks / "full.rank0.safetensors")))
    camera = model.views["test"].cameras(0)[0]
    out = render_camera(model.field, camera, 0)
    assert out.rgb.shape == (camera.height, camera.width, 3) and bool((out.opacity > 0.5).any())


def test_two_ranks_with_half_the_rays_each_match_one_process(two_ranks, tiny_chairs, tmp_path):
    category = load_category(tiny_chairs)
    model, _ = train(category, make_config("fast", overrides=EQ), tmp_path / "one.safetensors", CPU, seed=0,
                     batches=SameRays(category, Ranks()))
    two = load_file(str(two_ranks / "eq.rank0.safetensors"))
    one = model.state()
    assert torch.equal(one["field.occupancy"], two["field.occupancy"])
    worst = max(float((one[k] - two[k]).abs().max()) for k in one if one[k].is_floating_point())
    # Only summation order differs (the ranks' all-reduced gradient against one sum), amplified
    # by 16 Adam steps: 1.07e-4 at most (F_share's grid) on an AVX-512 EPYC, whose GEMM kernels
    # round differently from an AVX2 one; a different run moves the weights by 0.05.
    assert worst < 3e-4
    moved = float((one["field.F_dens.weight"] - load_file(str(two_ranks / "full.rank0.safetensors"))["field.F_dens.weight"]).abs().max())
    assert moved > 100 * worst  # a different run differs by far more than the tolerance


def test_a_dead_rank_stops_the_job_and_the_checkpoint_resumes_in_one_process(two_ranks, tiny_chairs, tmp_path):
    message = (two_ranks / "crash.rank0.txt").read_text()
    assert message.startswith("rank 0 of 2: averaging gradients failed, another rank stopped"), message
    assert (two_ranks / "broken.rank0.txt").read_text() == "True" and not broken()  # flagged there, not here
    path = tmp_path / "crash.safetensors"
    path.write_bytes((two_ranks / "crash.safetensors").read_bytes())
    model, state = load_model(path)
    assert model.meta["step"] == "8" and int(state["step"]) == 8
    resumed, result = train(load_category(tiny_chairs), make_config("fast", overrides=CRASH), path, CPU, seed=0, resume=True)
    assert result.steps == 24 and load_model(path)[0].meta["step"] == "24"
    assert not torch.equal(resumed.field.shape_codes, model.field.shape_codes)


def test_sharded_render_and_scores_equal_one_process(two_ranks, tiny_chairs, tmp_path):
    model, _ = load_model(two_ranks / "full.safetensors")
    render_to_folder(model, 0, ORBIT, tmp_path / "render", video=tmp_path / "orbit.gif")
    files = sorted(p.name for p in (tmp_path / "render").iterdir())
    assert files == sorted(p.name for p in (two_ranks / "render").iterdir())
    assert len([f for f in files if f.endswith(".png")]) == 5 and "views.json" in files
    for name in ["../orbit.gif"] + files:
        assert (tmp_path / "render" / name).read_bytes() == (two_ranks / "render" / name).read_bytes(), name
    one = json.loads(json.dumps(evaluate_recon(model, load_category(tiny_chairs), "train")))
    r0, r1 = (json.loads((two_ranks / f"recon.rank{r}.json").read_text()) for r in (0, 1))
    assert one == r0 == r1 and list(one["instances"]) == ["chair_000", "chair_001"]


def test_ranks_started_with_other_settings_refuse_to_train(two_ranks):
    """A rank started with other arguments than rank 0 (here its seed) trained silently to a
    worse model, or stalled in a collective (another step count): every rank now refuses before
    the first step, with one line naming the setting, and no file is written."""
    seed = [json.loads((two_ranks / f"mismatch-seed.rank{r}.json").read_text()) for r in (0, 1)]
    line = "rank 1 of 2 was started with other settings than rank 0: seed 1 (rank 0: 0); start every rank with the same arguments and data"
    assert seed == [[line, False], [line, True]], seed  # rank 1 keeps quiet: rank 0 prints the line
    images = [json.loads((two_ranks / f"mismatch-images.rank{r}.json").read_text()) for r in (0, 1)]
    assert images[0][0] == images[1][0] and images[0][0].startswith("rank 1 of 2 was started with other settings than rank 0: images "), images
    assert not (two_ranks / "mismatch.safetensors").exists()


def test_same_on_all_restores_rank_0s_tensor(two_ranks):
    r0, r1 = (json.loads((two_ranks / f"repair.rank{r}.json").read_text()) for r in (0, 1))
    assert r0 == r1 == {"same": False, "probe": [float(i) for i in range(6)]}


# ----------------------------------------------------------------------------- no processes


def test_ranks_from_env():
    assert ranks_from_env({}) is None
    assert ranks_from_env({"RANK": "3", "WORLD_SIZE": "4", "LOCAL_RANK": "1"}) == Ranks(3, 4, 1)
    for bad in ({"RANK": "4", "WORLD_SIZE": "4"}, {"RANK": "x", "WORLD_SIZE": "2"}):
        with pytest.raises(CrfError):
            ranks_from_env(bad)


def test_shares_and_shards_cover_everything_once():
    for world in (1, 2, 3, 8):
        ranks = [Ranks(r, world, r) for r in range(world)]
        assert sum(r.share(1001) for r in ranks) == 1001
        assert max(r.share(1001) for r in ranks) - min(r.share(1001) for r in ranks) <= 1
        assert sorted(k for r in ranks for k in r.shard(range(10))) == list(range(10))
    assert len({rank_seed(0, r) for r in range(8)} | {rank_seed(1, 0), rank_seed(0, 0, 1)}) == 10
    assert rank_seed(5, 1, 2) == rank_seed(5, 1, 2) < 2**63


@pytest.mark.skipif(torch.cuda.is_available(), reason="auto picks cuda:LOCAL_RANK there")
def test_rank_device_without_cuda():
    assert rank_device("auto", Ranks(1, 2, 1)) == rank_device("cpu", Ranks(1, 2, 1)) == CPU
    with pytest.raises(CrfError, match="no CUDA device"):
        rank_device("cuda", Ranks(1, 2, 1))


def test_more_ranks_than_instances_is_a_user_error(tiny_chairs, tmp_path):
    with pytest.raises(CrfError, match="3 ranks: at most one rank per instance"):
        train(load_category(tiny_chairs), make_config("fast", overrides=EQ), tmp_path / "m.safetensors", CPU, ranks=Ranks(0, 3, 0))


def test_sharded_edit_evaluation_equals_one_process(two_ranks):
    """``eval edits`` under 2 ranks: every rank returns the same gathered report, equal to one
    process's (timings aside), twins in the same order."""
    r0, r1 = (json.loads((two_ranks / f"edits.rank{r}.json").read_text()) for r in (0, 1))
    assert r0 == r1
    full, _ = load_model(two_ranks / "full.safetensors")
    single = json.loads(json.dumps(twin_report(full, two_ranks / "twins")))
    assert r0 == single and len(r0["runs"]) == 4 * 3  # 4 twins × (unedited, hybrid, the single-instance NeRF)
    assert [r["method"] for r in r0["runs"]][-4:] == [NERF_BASELINE] * 4


def test_a_broken_job_exits_without_teardown():
    """After a failed collective the command line leaves with its exit code and runs no
    interpreter teardown (no atexit handler, no gloo destructor); otherwise it exits normally."""
    script = ("import atexit, sys; import crfedit.distributed as d; d._BROKEN = {b}; "
              "atexit.register(lambda: print('teardown')); from crfedit.cli import main; "
              "sys.argv = ['crfedit', 'info', 'no/such/folder']; main()")
    for flag, teardown in ((True, False), (False, True)):
        r = subprocess.run([sys.executable, "-c", script.format(b=flag)], capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and r.stderr.startswith("error: "), (r.returncode, r.stderr)
        assert ("teardown" in r.stdout) == teardown, (flag, r.stdout)


def test_under_torchrun_one_line_per_job_and_unshared_commands_refused(tiny_model, tmp_path, monkeypatch):
    """Under torchrun (``RANK``/``WORLD_SIZE`` set) a user error found before the process group
    is printed by each node's first process alone (its ranks read the same arguments and files); a command that
    does not share its work over ranks is refused instead of running once per rank."""
    from cli_helpers import assert_user_error, invoke

    render = ["render", tiny_model, "--instance", "nope", "--views", "test", "--out", tmp_path / "r", "--device", "cpu"]
    export = ["model", "strip", tiny_model, "--out", tmp_path / "s.safetensors"]
    for rank in (0, 1):
        monkeypatch.setenv("RANK", str(rank))
        monkeypatch.setenv("LOCAL_RANK", str(rank))
        monkeypatch.setenv("WORLD_SIZE", "2")
        r, s = invoke(*render), invoke(*export)
        if rank == 0:
            assert_user_error(r, "unknown instance 'nope'")
            assert_user_error(s, "does not share its work over torchrun's ranks", "without torchrun")
        else:
            assert (r.exit_code, r.stderr, s.exit_code, s.stderr) == (2, "", 2, "")
    # another node's first process says it (its files may differ from rank 0's: a dataset missing there)
    monkeypatch.setenv("LOCAL_RANK", "0")
    assert_user_error(invoke(*render), "rank 1 of 2: unknown instance 'nope'")
    assert not (tmp_path / "s.safetensors").exists() and not (tmp_path / "r").exists()
    monkeypatch.setenv("WORLD_SIZE", "1")  # torchrun --nproc-per-node 1: nothing to share, the command runs
    monkeypatch.setenv("RANK", "0")
    assert invoke(*export).exit_code == 0 and (tmp_path / "s.safetensors").is_file()


def test_help_under_torchrun_is_printed_once():
    """``torchrun --nproc-per-node N crfedit render --help`` printed the help N times: rank 0
    alone prints it (and --version), the others exit as it does with nothing on stdout."""
    for args in (["render", "--help"], ["--version"]):
        outs = []
        for rank in (0, 1):
            env = {**os.environ, "RANK": str(rank), "LOCAL_RANK": str(rank), "WORLD_SIZE": "2"}
            r = subprocess.run([sys.executable, "-m", "crfedit", *args], capture_output=True, text=True, timeout=120, env=env)
            outs.append((r.returncode, r.stdout, r.stderr))
        assert outs[0][0] == outs[1][0] == 0 and outs[1][1:] == ("", ""), outs
        assert ("Usage:" in outs[0][1]) == (args[0] == "render") and outs[0][1].strip(), outs[0]


def test_timeouts_world_checks_and_clipped_reasons(monkeypatch):
    from crfedit.distributed import _clipped, collective_timeout
    from types import SimpleNamespace

    from crfedit.train import check_trainable

    for bad in ("inf", "1e20", "nan", "0", "-5", "abc"):
        monkeypatch.setenv("CRFEDIT_DIST_TIMEOUT", bad)
        with pytest.raises(CrfError, match="above 0 and at most 604800"):
            collective_timeout()
    monkeypatch.setenv("CRFEDIT_DIST_TIMEOUT", "7.5")
    assert collective_timeout() == 7.5
    one = SimpleNamespace(root="d", instances=[SimpleNamespace(name="a", splits={"train": [0]})])
    with pytest.raises(CrfError, match=r"2 ranks: .*\(1 instance, rays=128\); launch at most 1"):
        check_trainable(one, 2, 128)
    check_trainable(one, 1, 128)
    reason = "Read error [127.0.0.1]:35741: Connection reset by peer. This is typically caused by a remote peer " * 3
    clipped = _clipped(reason)
    assert len(clipped) <= 161 and clipped.endswith("…") and reason.startswith(clipped[:-1]) and not clipped[-2].isspace()
    assert _clipped("short") == "short"


def test_usage_errors_under_torchrun_are_rank_0_s_line(monkeypatch, capsys):
    """Every rank parses the same arguments: a usage error is printed by rank 0 alone."""
    from crfedit.cli import main

    for rank, expected in ((0, 1), (1, 0)):
        monkeypatch.setenv("RANK", str(rank))
        monkeypatch.setenv("WORLD_SIZE", "2")
        monkeypatch.setattr(sys, "argv", ["crfedit", "train", "data", "--out", "m.safetensors", "--bogus"])
        with pytest.raises(SystemExit) as e:
            main()
        err = capsys.readouterr().err
        assert e.value.code == 2 and err.count("No such option: --bogus") == expected, err


def test_sigterm_under_torchrun_says_where_it_may_come_from(monkeypatch, capsys):
    """torchrun passes Ctrl-C on as SIGTERM, as it does when another rank stops first: the
    line says so (it read as a plain SIGTERM, the lost rank never named)."""
    import typer

    from crfedit.cli.common import user_errors
    from crfedit.errors import Terminated

    @user_errors(ranked=True)
    def command():
        raise Terminated("m.safetensors keeps its checkpoint at step 80")

    for world, said in (("2", "terminated (SIGTERM from torchrun: Ctrl-C, or another rank stopped; torchrun's summary names it)"),
                        ("1", "terminated (SIGTERM)")):
        monkeypatch.setenv("RANK", "0")
        monkeypatch.setenv("WORLD_SIZE", world)
        with pytest.raises(typer.Exit) as e:
            command()
        assert e.value.exit_code == 143
        assert capsys.readouterr().err == f"{said}: m.safetensors keeps its checkpoint at step 80\n"


def test_a_rank_prints_a_user_error_met_in_its_own_share_of_the_work(monkeypatch):
    """Rank 1 of a node whose removal twin diverged under `eval edits` exited 2 and printed
    nothing (its group torn down by the time the error reached the command line, so it was
    taken for an argument error rank 0 prints); rank 0 only said torchrun had stopped it.  An
    error met before the group formed stays quiet there (rank 0 met the same)."""
    import crfedit.distributed as d
    from crfedit.cli.common import _says_it

    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("LOCAL_RANK", "1")
    monkeypatch.setattr(d, "_JOINED", False)
    assert not _says_it(CrfError("removal diverged"))
    monkeypatch.setattr(d, "_JOINED", True)
    assert _says_it(CrfError("removal diverged")) and not _says_it(KeyboardInterrupt())


def test_a_line_rank_0_prints_too_is_not_printed_again_on_another_node(monkeypatch):
    """The ranks' settings check raises on every rank; rank 0 prints its line and the others,
    another node's first process too, keep quiet (it was printed once per node)."""
    from crfedit.cli.common import _says_it
    from crfedit.distributed import DistributedError

    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("LOCAL_RANK", "0")
    assert not _says_it(DistributedError("rank 1 of 2 was started with other settings", echoed=True))
    assert _says_it(DistributedError("rank 1 of 2: averaging gradients failed"))
    monkeypatch.setenv("RANK", "0")
    assert _says_it(DistributedError("rank 1 of 2 was started with other settings", echoed=False))
