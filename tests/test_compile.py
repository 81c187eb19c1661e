"""--compile: the compiled planner against the eager one (the same pairs), the rasterizer compiled
against the dense reference (forward, a random cotangent, gradcheck in float64), the fallback to
eager, the auto rule, the time plan leaving compile time out of the speed, and --profile."""

from __future__ import annotations

import json
import os
import time

import pytest
import torch

import splatcli.render.composite as composite
from splatcli.cli.train_config import make_config
from splatcli.render import kernels, rasterize
from splatcli.render.projection import project
from splatcli.render.reference import rasterize_reference
from splatcli.train import compiling
from splatcli.train.loop import train
from splatcli.train.plan import TimePlan
from support.scenes import test_scene as make_scene
from support.tiny_project import make_tiny_project

CPU = torch.device("cpu")
needs_compiler = pytest.mark.skipif(kernels.compiler() is None, reason="no C++ compiler for torch.compile")


@pytest.fixture
def compiled(tmp_path_factory, monkeypatch):
    """Compiling on for one test, with kernels cached where the whole session shares them."""
    monkeypatch.setenv("SPLATCLI_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "cache"))
    monkeypatch.setattr(kernels, "_status", kernels.Status())  # nothing chosen yet
    monkeypatch.setattr(kernels, "TRIALS", 10_000)  # no choice: every other call compiled
    kernels.set_mode("on")
    yield kernels.status()
    kernels.set_mode("off")


@pytest.fixture
def fresh(monkeypatch):
    """A fresh compile state with a C++ compiler found, and compiling off again afterwards."""
    monkeypatch.setattr(kernels, "_status", kernels.Status())
    monkeypatch.setattr(kernels, "compiler", lambda: "g++")
    yield
    kernels.set_mode("off")


def _as(args, dtype, grad=False):
    return [a.to(dtype).detach().requires_grad_(grad) for a in args]


@pytest.mark.slow
@needs_compiler
def test_compiled_planner_gives_the_eager_plan(compiled):
    W, H = 93, 61
    cases = []
    for seed, n in ((0, 2000), (1, 40)):
        args = make_scene(n, W, H, sh_degree=0, seed=seed, dtype=torch.float32)
        cases += [(project(*args, W, H, 0).footprint, block) for block in (4, 8, 16)]
    kernels.set_mode("off")
    eager = [composite.make_plan(fp, W, H, block) for fp, block in cases]
    st = kernels.set_mode("on")
    for (fp, block), want in zip(cases, eager):
        got = composite.make_plan(fp, W, H, block)
        assert torch.equal(got.pair_gid, want.pair_gid) and torch.equal(got.block_count, want.block_count)
        assert [len(b) for b, _ in got.chunks] == [len(b) for b, _ in want.chunks]
    assert st.failed is None and st.graphs >= 2 and st.compile_s > 0


@pytest.mark.slow
@needs_compiler
def test_compiled_rasterizer_matches_the_reference(compiled):
    """The same bounds as tests/test_rasterize.py's eager checks: 1e-4 in float32 forward, and
    float64 gradients through a random cotangent equal to rounding."""
    W, H = 61, 47
    args = make_scene(1200, W, H, sh_degree=2)
    out = rasterize(*_as(args, torch.float32), W, H)
    with torch.no_grad():
        ref = rasterize_reference(*args, W, H)
    assert out.alpha.mean() > 0.3
    torch.testing.assert_close(out.image, ref.image.float(), atol=1e-4, rtol=0)  # issue 7's float32 bound
    g = torch.Generator().manual_seed(2)
    v = torch.randn(H, W, 3, generator=g, dtype=torch.float64)

    def grads(fn):
        xs = _as(args, torch.float64, grad=True)
        (fn(*xs, W, H).image * v).sum().backward()
        return [x.grad for x in xs]

    for a, b in zip(grads(rasterize), grads(rasterize_reference)):
        # float64 both ways: only rounding differs (relative to the gradient's scale)
        torch.testing.assert_close(a, b, atol=1e-9 * float(b.abs().max()), rtol=1e-7)
    assert compiled.failed is None and kernels._graphs() >= 2  # (compiled here or by an earlier test)


@pytest.mark.slow
@needs_compiler
def test_gradcheck_float64_compiled(compiled):
    W, H = 12, 10
    args = make_scene(6, W, H, sh_degree=1, seed=5)
    args[2] = args[2] + 1.5  # a few px wide: every Gaussian touches several pixels
    xs = _as(args[:5], torch.float64, grad=True)
    viewmat, K = args[5], args[6]

    def f(means, quats, log_scales, logits, sh):
        o = rasterize(means, quats, log_scales, logits, sh, viewmat, K, W, H)
        return o.image, o.alpha

    # tolerances as test_rasterize.py's gradcheck: central differences of exp() over eps = 1e-6
    assert torch.autograd.gradcheck(f, xs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)
    assert compiled.failed is None and kernels._graphs() >= 2


def test_without_a_compiler_every_call_is_eager(fresh, monkeypatch):
    monkeypatch.setattr(kernels, "compiler", lambda: None)
    called = []
    monkeypatch.setattr(torch, "compile", lambda *a, **k: called.append(1))
    st = kernels.set_mode("on")
    assert st.failed and "no C++ compiler" in st.failed and not kernels.active()
    args = make_scene(300, 40, 30, dtype=torch.float32)
    out = rasterize(*args, 40, 30)
    kernels.set_mode("off")
    torch.testing.assert_close(out.image, rasterize(*args, 40, 30).image, atol=0, rtol=0)
    assert called == []


def test_kernels_go_to_our_cache_unless_the_user_chose_a_folder(fresh, tmp_path, monkeypatch):
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    monkeypatch.setenv("SPLATCLI_CACHE_DIR", str(tmp_path))
    for before in (None, default_cache_dir()):  # unset, or torch's default as a launcher passes it on
        if before is None:
            monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
        else:
            monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", before)
        kernels.set_mode("on")
        assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "inductor")
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "mine"))
    kernels.set_mode("on")
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "mine")


def test_a_compile_that_fails_falls_back_once_with_the_same_picture(fresh, monkeypatch):
    def broken(fn, **_):
        def run(*a, **k):
            raise RuntimeError("C++ compile error: cannot find Python.h")
        return run

    monkeypatch.setattr(torch, "compile", broken)
    rows_fast = kernels.fast(composite._block_rows, lambda m, *_: m.device)
    monkeypatch.setattr(composite, "_block_rows_fast", rows_fast)
    args = make_scene(300, 40, 30, dtype=torch.float32)
    want = rasterize(*args, 40, 30).image
    kernels.set_mode("on")
    got = rasterize(*args, 40, 30).image
    assert kernels.status().failed and "Python.h" in kernels.status().failed and not kernels.active()
    torch.testing.assert_close(got, want, atol=0, rtol=0)


def test_the_faster_form_is_kept_after_taking_turns(fresh, monkeypatch):
    """Each function runs eager and compiled by turns for TRIALS calls each (after the call that
    compiles), then keeps the faster for the rest of the process."""
    ran = []

    def slow_compiled(fn, **_):
        def run(*a):
            ran.append("compiled")
            time.sleep(0.002)
            return fn(*a)
        return run

    monkeypatch.setattr(torch, "compile", slow_compiled)

    def double(x):
        ran.append("eager") if not ran or ran[-1] != "compiled" else None
        return 2 * x

    f = kernels.fast(double, lambda x: x.device)
    kernels.set_mode("on")
    x = torch.ones(3)
    for _ in range(2 * kernels.TRIALS + 5):
        assert torch.equal(f(x), 2 * x)
    kept = kernels.status().chosen["double"]
    assert kept["kept"] == "eager" and kept["compiled_ms"] > kept["eager_ms"]
    n = ran.count("compiled")
    f(x)
    assert ran.count("compiled") == n  # eager from now on


@pytest.mark.parametrize("budget, warm, steps, mode", [(300.0, False, None, "off"), (600.0, False, None, "off"),
                                                        (3600.0, False, None, "on"), (1200.0, True, None, "on"),
                                                        (300.0, True, None, "off"), (None, False, 30_000, "on"),
                                                        (None, False, 7000, "off")])
def test_auto_compiles_runs_long_enough_to_repay_it(tmp_path, monkeypatch, budget, warm, steps, mode):
    monkeypatch.setenv("SPLATCLI_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(kernels, "compiler", lambda: "g++")
    if warm:
        (tmp_path / "inductor").mkdir()
        (tmp_path / "inductor" / "fxgraph").mkdir()
    given = {"time_budget": budget} if budget else {"iterations": steps}
    got, why = compiling.compile_mode(make_config(**given), CPU)
    assert got == mode and why
    assert compiling.compile_mode(make_config(**given, compile="off"), CPU)[0] == "off"
    assert compiling.compile_mode(make_config(**given), torch.device("meta"))[0] == "off"  # not the CPU: never
    monkeypatch.setattr(kernels, "compiler", lambda: None)
    assert compiling.compile_mode(make_config(**given), CPU) == ("off", "no C++ compiler found")


def test_a_plan_spends_compile_time_from_the_budget_but_not_from_the_speed():
    cfg = make_config("fast", time_budget=300.0, coarse_scale=1.0)
    plan = TimePlan.start(cfg)
    start = plan.scaled(cfg, 7000)
    # the first plan waits for probe_s seconds of steps, whatever the compile took
    assert plan.probe_s == 5.0 and not plan.due(6.0, stalled=4.0) and plan.due(9.0, stalled=4.0) and plan.due(5.0)
    # 50 views in 20 s, 15 of them compiling: 10 views/s, and 280 s left
    n = plan.replan(start, 50, 20.0, stalled=15.0).iterations
    assert abs(n - (50 + 10 * 280)) <= 1
    assert plan.history[-1]["stalled_s"] == 15.0
    n2 = TimePlan.start(cfg).replan(start, 50, 20.0).iterations  # counted as steps: 2.5 views/s
    assert n2 < n / 3


def test_profile_writes_where_the_time_went(tmp_path):
    proj = make_tiny_project(tmp_path / "p", trained=False)
    train(proj.root, make_config(iterations=12, init_random_points=200, eval_every=6, profile=True), CPU)
    r = json.loads(proj.profile_json_path.read_text())
    assert r["steps"] == 12 and r["pairs_per_step"] > 0 and r["ms_per_step"] > 0 and r["cpu"]
    for stage in ("data", "projection", "planning", "compositing", "loss", "compositing backward",
                  "projection backward", "optimiser", "densification"):
        assert stage in r["stages"] and r["stages"][stage]["ms_per_step"] >= 0
    assert r["stages"]["compositing backward"]["ms_per_step"] > 0
    # the render's own stages are of the steps' renders alone: held-out evaluation's are not in them
    assert r["stages"]["render, other"]["ms_per_step"] >= 0 and r["stages"]["backward, other"]["ms_per_step"] >= 0
    assert abs(sum(s["share"] for s in r["stages"].values()) - 1) < 1e-3
    assert "| compositing backward |" in proj.profile_md_path.read_text()
    sl = r["slots"]  # the compositor's dense slots, split by what became of them
    assert sl["per_step"] > 0 and all(0 <= sl[k] <= 1 for k in ("below", "ended", "padding", "blended"))
    assert sl["below"] > 0 and sl["blended"] > 0 and abs(sl["below"] + sl["ended"] + sl["padding"] + sl["blended"] - 1) < 1e-3
    assert "below alpha 1/255" in proj.profile_md_path.read_text()
    plain = make_tiny_project(tmp_path / "q", trained=False)
    train(plain.root, make_config(iterations=3, init_random_points=200, eval_every=0), CPU)
    assert not plain.profile_json_path.exists()


def test_the_compile_note_says_loading_from_a_warm_cache_and_compiling_from_an_empty_one(fresh, tmp_path,
                                                                                       monkeypatch):
    from splatcli.train.loop import _compile

    monkeypatch.setenv("SPLATCLI_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "mine"))  # set_mode leaves a user's folder alone
    cfg = make_config(compile="on")
    notes: list[str] = []
    _compile(cfg, CPU, lambda e: notes.append(e.message))
    (tmp_path / "inductor").mkdir()
    (tmp_path / "inductor" / "kernel").write_text("x")
    _compile(cfg, CPU, lambda e: notes.append(e.message))
    assert notes[0].startswith("compiling the rasterizer's planner") and "first run" in notes[0]
    assert notes[1].startswith("loading the rasterizer's compiled planner") and "first run" not in notes[1]
