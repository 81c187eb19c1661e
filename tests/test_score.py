"""The rules written once and used by train and eval alike: scoring a render
(eval/score.py), painting masked pixels, the hold-out split, and top-k by weight."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from splatcli.eval.budgets import prune_to
from splatcli.eval.score import load_target, quantise, score_image
from splatcli.gaussians import kept_count, top_by_weight
from splatcli.inputs.images import composite, paint_masked
from splatcli.project import holdout_split
from splatcli.strategy.base import Splats, StepInfo
from splatcli.strategy.compact import CompactConfig, CompactState, CompactStep
from splatcli.train.data import load_train_data
from splatcli.views.sources import dataset_views
from support.context import context
from support.tiny_project import make_tiny_project, tiny_gaussians

CPU = torch.device("cpu")


def _pair(seed: int, h: int = 24, w: int = 30) -> tuple[torch.Tensor, torch.Tensor]:
    """A float32 render (a little outside [0, 1], off the 8-bit grid) and an 8-bit photograph."""
    g = torch.Generator().manual_seed(seed)
    photo = torch.randint(0, 256, (h, w, 3), generator=g, dtype=torch.uint8)
    render = photo.to(torch.float32) / 255 + torch.randn(h, w, 3, generator=g) * 0.03
    return render, photo


def _reference(render: torch.Tensor, photo: torch.Tensor, eight_bit: bool) -> tuple[float, float]:
    """numpy / scikit-image, independently of metrics.py."""
    pred = np.clip(render.numpy().astype(np.float64), 0, 1)
    if eight_bit:
        pred = np.round(np.clip(render.numpy(), 0, 1) * 255).astype(np.float64) / 255
    gt = photo.numpy().astype(np.float64) / 255
    p = 10 * np.log10(1 / np.mean((pred - gt) ** 2))
    s = structural_similarity(pred, gt, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                              data_range=1.0, channel_axis=-1)
    return float(p), float(s)


@pytest.mark.parametrize("quantisation", ["8-bit", "none"])
def test_score_image_against_numpy(quantisation: str) -> None:
    render, photo = _pair(1)
    s = score_image(render, photo, quantisation=quantisation)
    p, ss = _reference(render, photo, quantisation == "8-bit")
    assert s.psnr == pytest.approx(p, abs=1e-9) and s.ssim == pytest.approx(ss, abs=1e-6)
    assert s.lpips is None and s.psnr_color_fit is None
    # a float photograph in [0, 1] scores exactly as its uint8 values do
    assert score_image(render, photo.to(torch.float64) / 255, quantisation=quantisation) == s


def test_quantisations_differ_and_8_bit_is_idempotent() -> None:
    render, photo = _pair(2)
    eight, none = (score_image(render, photo, quantisation=q) for q in ("8-bit", "none"))
    assert eight.psnr != none.psnr and abs(eight.psnr - none.psnr) < 0.05  # 0.03 noise: 8-bit adds a little
    q = quantise(render, "8-bit")
    assert torch.equal(quantise(q, "8-bit"), q) and torch.equal(quantise(q, "none"), q)
    assert torch.equal((q * 255).round(), q * 255) and float(q.min()) >= 0 and float(q.max()) <= 1
    with pytest.raises(ValueError, match="quantisation"):
        score_image(render, photo, quantisation="16-bit")


def test_score_image_masks_and_extras() -> None:
    render, photo = _pair(3)
    keep = torch.zeros(photo.shape[:2], dtype=torch.bool)
    keep[:, 12:] = True
    spoilt = render.clone()
    spoilt[~keep] = 1 - spoilt[~keep]  # masked pixels count for nothing
    seen = []

    def lpips(pred: torch.Tensor, gt: torch.Tensor) -> float:
        seen.append(pred)
        return 0.25

    a = score_image(render, photo, keep, quantisation="8-bit", color_fit=True, lpips=lpips)
    b = score_image(spoilt, photo, keep, quantisation="8-bit", color_fit=True, lpips=lpips)
    assert a == b and a.lpips == 0.25 and a.psnr_color_fit >= a.psnr
    # LPIPS sees the photograph's own pixels where masked, the render's where kept
    assert torch.equal(seen[1][~keep], photo[~keep].to(torch.float64) / 255)
    assert torch.equal(seen[1][keep], quantise(render, "8-bit")[keep])
    full = score_image(render, photo, quantisation="8-bit")
    assert a.psnr != full.psnr


def test_compensated_scores_fit_the_light_on_the_left_half_and_judge_the_right() -> None:
    """The photo-collection protocol (metrics.half_fit): a render that is the photo under another
    light (an affine colour change, what --appearance exposure learns) scores near perfectly once
    compensated, far below raw; an error in the right half is all it sees, one in the left half
    only spoils the fit. The colour fit on the whole view (psnr_color_fit) sees the pixels it is
    judged on."""
    g = torch.Generator().manual_seed(0)
    photo = torch.rand(40, 64, 3, generator=g, dtype=torch.float64) * 0.6 + 0.2  # [H, W, 3]
    m = torch.tensor([[0.8, 0.1, 0.0], [0.0, 0.9, 0.05], [0.1, 0.0, 0.7]], dtype=torch.float64)
    lit = (photo @ m + 0.05).clamp(0, 1)  # the render: the same scene under another light
    s = score_image(lit, photo, quantisation="none", compensated=True)
    assert s.psnr < 25 and s.compensated.psnr > 60 and s.compensated.ssim > 0.999
    wrong_right = lit.clone()
    wrong_right[:, 40:] = torch.rand(40, 24, 3, generator=g, dtype=torch.float64)
    r = score_image(wrong_right, photo, quantisation="none", compensated=True, color_fit=True)
    assert r.compensated.psnr < 20  # the right half is what is judged
    wrong_left = lit.clone()
    wrong_left[:, :8] = torch.rand(40, 8, 3, generator=g, dtype=torch.float64)
    left = score_image(wrong_left, photo, quantisation="none", compensated=True)
    assert left.compensated.psnr < s.compensated.psnr and left.compensated.psnr > r.compensated.psnr
    keep = torch.ones(40, 64, dtype=torch.bool)
    keep[:, :8] = False  # the spoilt columns masked out: the fit is exact again
    masked = score_image(wrong_left, photo, keep, quantisation="none", compensated=True)
    assert masked.compensated.psnr > 60


def test_paint_masked_rounds_as_alpha_compositing() -> None:
    rng = np.random.default_rng(4)
    rgb = rng.integers(0, 256, (9, 11, 3), dtype=np.uint8)
    keep = rng.random((9, 11)) > 0.4
    for bg in ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (0.3, 0.5, 0.7), (0.002, 0.998, 0.5)):
        out = paint_masked(rgb, keep, bg)
        assert out.dtype == np.uint8 and np.array_equal(out[keep], rgb[keep])
        # a masked pixel gets what a fully transparent pixel gets over the same background
        transparent = composite(rgb[..., ::-1], np.zeros((9, 11), np.uint8), bg)[..., ::-1]
        assert np.array_equal(out[~keep], transparent[~keep])


def test_load_target_by_mask_mode(tmp_path) -> None:
    proj = make_tiny_project(tmp_path / "p", trained=False)
    proj.masks_dir.mkdir()
    name = proj.splits()["test"][0]
    m = np.full((40, 48), 255, np.uint8)
    m[:, :20] = 0
    cv2.imwrite(str(proj.mask_path(name)), m)
    proj.update_manifest(scene={**proj.manifest()["scene"], "masks": True, "mask_source": "files"})
    bg = (0.3, 0.5, 0.7)
    off, none = load_target(proj, name, (48, 40), bg, "off")
    ign, keep = load_target(proj, name, (48, 40), bg, "ignore")
    painted, none2 = load_target(proj, name, (48, 40), bg, "background")
    assert none is None and none2 is None and keep is not None and not keep[:, :20].any() and keep[:, 20:].all()
    assert np.array_equal(off, ign) and np.array_equal(painted, paint_masked(off, keep, bg))
    assert (painted[:, :20] == [77, 128, 179]).all()  # 0.3, 0.5, 0.7 of 255, halves up
    # alpha masks: the photographs already are composited, so nothing is loaded or painted
    proj.update_manifest(scene={**proj.manifest()["scene"], "mask_source": "alpha"})
    alpha, none3 = load_target(proj, name, (48, 40), bg, "background")
    assert none3 is None and np.array_equal(alpha, off)


def test_holdout_split() -> None:
    names = [f"img_{i:02d}.png" for i in range(17)]
    shuffled = names[::-1]
    s = holdout_split(shuffled)
    assert s["test"] == ["img_00.png", "img_08.png", "img_16.png"]
    assert s["train"] == [n for n in names if n not in s["test"]]
    assert holdout_split(names, ["img_03.png", "img_99.png"]) == \
        {"train": [n for n in names if n != "img_03.png"], "test": ["img_03.png"]}
    assert holdout_split(["a.png"]) == {"train": ["a.png"], "test": []}  # one image is trained on
    assert holdout_split(["b.png", "a.png"]) == {"train": ["b.png"], "test": ["a.png"]}
    assert holdout_split([]) == {"train": [], "test": []}


def test_a_project_without_splits_is_split_once_for_every_command(tmp_path) -> None:
    proj = make_tiny_project(tmp_path / "p", trained=False)
    manifest = proj.manifest()
    del manifest["splits"]
    proj.write_manifest(manifest)
    names = [f"img_{i:03d}.png" for i in range(10)]
    assert proj.splits() == {"train": [], "test": []}
    assert proj.splits(names) == holdout_split(names) and holdout_split(names)["test"] == ["img_000.png", "img_008.png"]
    data = load_train_data(proj, 1.0, None, CPU)
    assert [v.camera.name for v in data.test] == ["img_000.png", "img_008.png"]
    assert [v.camera.name for v in data.train] == holdout_split(names)["train"]
    assert [v.camera.name for v in dataset_views(proj, "test")] == ["img_000.png", "img_008.png"]


@pytest.mark.parametrize("n,fraction,k", [
    (30, 0.1, 3),  # 0.1 * 30 = 3.0000000000000004: the ceiling would keep 4
    (100, 0.29, 29),  # 28.999999999999996: int() would keep 28
    (100, 1 / 3, 33),  # 33.33: not exact, nearest is below
    (200, 1 / 3, 67),  # 66.67: not exact, nearest is above (int() kept 66)
    (5, 0.5, 3),  # a half: up
    (300, 0.25, 75), (40, 0.25, 10),
    (1000, 1e-6, 1),  # never none of a non-empty set
    (7, 1.0, 7), (0, 0.5, 0),
])
def test_kept_count(n: int, fraction: float, k: int) -> None:
    assert kept_count(n, fraction) == k


def test_top_by_weight_ties_and_compact_agrees_with_eval() -> None:
    w = torch.tensor([0.5, 2.0, 0.5, 3.0, 0.5, 0.1])
    assert top_by_weight(w, 3).tolist() == [True, True, False, True, False, False]  # ties: the lower index
    assert not top_by_weight(w, 0).any() and top_by_weight(w, 9).all()
    # eval's budgets and --compact keep the same Gaussians for the same weights and fraction
    g = tiny_gaussians(200, seed=6, sh_degree=0)
    weight = torch.rand(200, generator=torch.Generator().manual_seed(6))
    weight[::7] = weight[0]  # some ties
    kept = prune_to(g, weight, 1 / 3)
    assert len(kept) == kept_count(200, 1 / 3) == 67
    params = {"means": torch.nn.Parameter(g.means.clone())}
    splats = Splats(params, {"means": torch.optim.Adam(params.values())})
    ctx = context(weight)
    step = CompactStep(CompactConfig(enabled=True, keep=1 / 3, finetune=0, rounds=1), 10, ctx)
    step.catch_up(splats, CompactState(), 10)  # the one cut of a resumed run
    assert torch.equal(splats.params["means"].detach(), kept.means)


def test_compact_cuts_first_when_resumed_a_step_past_its_schedule() -> None:
    """A run of K processes ends its main schedule up to K - 1 views past it, and is resumed there
    by one process: --compact's first cut still happens then, and a round whose step comes first
    cuts from the model as it is (never from an empty "before")."""
    g = tiny_gaussians(200, seed=7, sh_degree=0)
    weight = torch.rand(200, generator=torch.Generator().manual_seed(7))

    def fresh() -> Splats:
        params = {"means": torch.nn.Parameter(g.means.clone())}
        return Splats(params, {"means": torch.optim.Adam(params.values())})

    step = CompactStep(CompactConfig(enabled=True, keep=1 / 3, finetune=12, rounds=3), 10, context(weight))
    assert step.prune_steps() == [10, 12, 14]
    splats, state = fresh(), CompactState()
    step.catch_up(splats, state, 11)  # one step past `at`
    assert state.round == 1 and state.before_count == 200
    assert len(splats.params["means"]) == kept_count(200, (1 / 3) ** (1 / 3))
    splats, state = fresh(), CompactState()
    info = StepInfo(render=None, width=0, height=0, heldout=(30.0, 0.9))  # type: ignore[arg-type]
    step.step_post_backward(splats, state, 12, info)  # round 2 reached with no cut made
    assert state.before_count == 200 and len(splats.params["means"]) == kept_count(200, (1 / 3) ** (2 / 3))


@pytest.mark.parametrize("cap, kept", [(None, 67), (300, 100), (450, 150), (900, 200)])
def test_compact_keeps_its_share_of_the_cap_whatever_grew(cap, kept) -> None:
    """--compact-keep is a share of MCMC's --max-gaussians: a run that grew to 200 of a 300 cap in its
    time keeps a third of 300 (the count a run that reached the cap keeps), all 200 where that is more
    than it has, and without a cap (the default strategy's is only a ceiling) a third of what grew."""
    g = tiny_gaussians(200, seed=3, sh_degree=0)
    params = {"means": torch.nn.Parameter(g.means.clone())}
    splats = Splats(params, {"means": torch.optim.Adam(params.values())})
    ctx = context()
    ctx.evaluator.weights = lambda: splats.params["means"].detach()[:, 0]  # the model as each cut finds it
    step = CompactStep(CompactConfig(enabled=True, keep=1 / 3, finetune=12, rounds=3), 10, ctx, cap)
    state = CompactState()
    for at in step.prune_steps():
        step.catch_up(splats, state, at) if at == 10 else step.step_post_backward(
            splats, state, at, StepInfo(render=None, width=0, height=0, heldout=(30.0, 0.9)))  # type: ignore[arg-type]
    assert state.round == 3 and state.before_count == 200 and len(splats.params["means"]) == kept


def test_compact_takes_its_share_of_mcmc_s_cap_alone() -> None:
    """MCMC grows to exactly --max-gaussians, so --compact keeps a share of it; the default strategy's
    --max-gaussians is only a ceiling it may never reach, so there the share is of what grew."""
    from splatcli.cli.train_config import make_config
    from splatcli.train.state import make_strategies

    def cap(strategy: str) -> int | None:
        cfg = make_config(strategy=strategy, max_gaussians=900, compact=True)
        return next(s for s in make_strategies(cfg, 1.0, context()) if isinstance(s, CompactStep)).cap

    assert cap("mcmc") == 900 and cap("default") is None
