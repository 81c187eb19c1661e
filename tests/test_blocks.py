"""The block size measured at run time (render/blocks.py): the tuner follows what it measures,
not the cost model, and the picture does not depend on its choice beyond float rounding."""

from __future__ import annotations

import pytest
import torch

from splatcli.render import blocks, kernels, rasterize
from splatcli.render.blocks import BlockTuner
from support.scenes import test_scene as make_scene


def _small_gaussians(n: int = 500) -> tuple[torch.Tensor, torch.Tensor]:  # cov2d [n, 3], opacities [n]
    """Gaussians of 3 px sigma: the cost model's pick is 4 px, with 8 and 16 px in its range."""
    return torch.tensor([[9.0, 0.0, 9.0]]).repeat(n, 1), torch.full((n,), 0.9)


def _drive(tuner: BlockTuner, seconds_per_cost: dict, calls: int) -> list:
    """`calls` renders whose measured time is `seconds_per_cost[block]` (or [(block, chunk)]) times
    the model's cost; the blocks picked (or the layouts, when keyed by them)."""
    cov2d, opac = _small_gaussians()
    cost = blocks.block_costs(blocks.extents(cov2d, opac), 640, 480)
    by_layout = isinstance(next(iter(seconds_per_cost)), tuple)
    picked = []
    for _ in range(calls):
        layout, meter = tuner.choose(blocks.extents(cov2d, opac), 640, 480)
        key = tuple(layout) if by_layout else layout.block
        picked.append(key)
        if meter is not None:
            meter.add(seconds_per_cost[key] * cost[layout.block], last=True)
    return picked


def _one_chunk(**kw) -> BlockTuner:
    """A tuner of the block alone (one chunk size: the device's default)."""
    return BlockTuner(chunks=(None,), **kw)


def test_tuner_keeps_the_block_that_measures_fastest_not_the_models_pick():
    cov2d, opac = _small_gaussians()
    assert blocks.choose_block(blocks.extents(cov2d, opac), 640, 480) == 4
    cost = blocks.block_costs(blocks.extents(cov2d, opac), 640, 480)
    # 8 px blocks measure 10% faster in absolute time than the model's 4 px; 16 px slower
    truth = {4: 1.0 / cost[4], 8: 0.9 / cost[8], 16: 1.3 / cost[16]}
    tuner = _one_chunk(every=10)
    picked = _drive(tuner, truth, 60)
    assert picked[0] == 4  # the warm-up render: the model's pick, not measured
    assert picked[1:4] == [4, 4, 4]  # then each candidate, best predicted first
    settled = picked[1 + 3 * 3:]
    assert settled.count(8) >= len(settled) - 6  # kept, but for a look at the others every 10th render
    assert {4, 16} <= set(settled)  # ... which do happen
    assert tuner.summary()["used"]["8"] == picked.count(8)


def test_tuner_follows_a_change_of_speed():
    """The model's Gaussians change as training goes on: the others are measured again now and then,
    and the last five measurements of each block decide."""
    cov2d, opac = _small_gaussians()
    cost = blocks.block_costs(blocks.extents(cov2d, opac), 640, 480)
    tuner = _one_chunk(every=2)
    _drive(tuner, {4: 1.0 / cost[4], 8: 0.8 / cost[8], 16: 2.0 / cost[16]}, 30)
    late = _drive(tuner, {4: 0.5 / cost[4], 8: 0.8 / cost[8], 16: 2.0 / cost[16]}, 40)
    assert late[-10:].count(4) >= 5


def test_blocks_far_outside_the_model_are_never_tried():
    cov2d, opac = _small_gaussians()
    cost = blocks.block_costs(blocks.extents(cov2d, opac), 640, 480)
    tuner = _one_chunk(spread=1.0 + 1e-9)  # only the model's pick is within range
    assert set(_drive(tuner, {b: 1e-9 for b in cost}, 20)) == {4}


def test_millions_of_pairs_move_the_models_pick_to_larger_blocks():
    """A pair costs more once a plan holds millions: the same 3 px Gaussians that a sparse view draws
    in 4 px blocks, stacked 200k deep (7 million pairs at 4 px), are drawn in 8 px ones."""
    for n, expected in ((2_000, 4), (200_000, 8)):
        cov2d, opac = _small_gaussians(n)
        assert blocks.choose_block(blocks.extents(cov2d, opac), 640, 480) == expected


def test_nothing_drawn_draws_with_8px_and_measures_nothing():
    tuner = BlockTuner()
    layout, meter = tuner.choose(blocks.extents(torch.zeros(3, 3), torch.zeros(3)), 64, 64)
    assert (layout.block, meter) == (8, None)


def test_a_render_that_compiled_a_kernel_is_not_measured(monkeypatch):
    cov2d, opac = _small_gaussians()
    tuner = BlockTuner(warmup=0)
    layout, meter = tuner.choose(blocks.extents(cov2d, opac), 640, 480)
    monkeypatch.setattr(kernels.status(), "compile_s", kernels.status().compile_s + 5.0)
    meter.add(5.0, last=True)
    assert not tuner.ratios.get(layout)


@pytest.mark.parametrize("backward", [True, False])
def test_rasterize_with_a_tuner_measures_each_render_and_draws_the_same_picture(backward):
    torch.manual_seed(0)
    args = make_scene(300, 96, 64, dtype=torch.float32, seed=3)
    tuner = _one_chunk(backward=backward, warmup=0)
    recorded = []
    keep = tuner.record
    tuner.record = lambda block, ratio: (recorded.append(block), keep(block, ratio))  # type: ignore[method-assign]
    ref = rasterize(*args, 96, 64, block=8)
    for i in range(9):
        p = [a.clone().requires_grad_(j < 5) for j, a in enumerate(args)]
        out = rasterize(*p, 96, 64, block=tuner)
        # the alpha polynomial is expanded around each block's centre: float32 rounding differs by block
        torch.testing.assert_close(out.image, ref.image, atol=2e-5, rtol=1e-4)
        if backward:
            out.image.sum().backward()
        assert len(recorded) == i + 1  # every render measured, once its backward (if awaited) ran
    assert recorded[:3] == [recorded[0]] * 3 and recorded[3] != recorded[0]  # each candidate in turn


def test_a_tuner_without_gradients_waits_for_no_backward():
    """Rendering under no_grad with a training tuner (evaluation mid-run) measures nothing, counts
    nothing, and draws with the best block measured so far."""
    args = make_scene(100, 64, 64, dtype=torch.float32, seed=1)
    tuner = _one_chunk(warmup=0)
    with torch.no_grad():
        rasterize(*args, 64, 64, block=tuner)
    assert not any(tuner.ratios.values()) and tuner.calls == 0 and not any(tuner.used.values())
    cov2d, opac = _small_gaussians()
    cost = blocks.block_costs(blocks.extents(cov2d, opac), 640, 480)
    _drive(tuner, {4: 1.0 / cost[4], 8: 0.5 / cost[8], 16: 2.0 / cost[16]}, 12)
    assert tuner.choose(blocks.extents(cov2d, opac), 640, 480, measure=False) == ((8, None), None)


def test_tuner_measures_each_chunk_size_with_each_block_and_keeps_the_fastest_pair():
    cov2d, opac = _small_gaussians()
    cost = blocks.block_costs(blocks.extents(cov2d, opac), 640, 480)
    small, large = blocks.CHUNKS[0], blocks.CHUNKS[-1]
    # 8 px is fastest, and with the smallest chunk; 4 px is fastest with the largest
    truth = {(b, c): (1.0 if b == 4 else 1.3 if b == 16 else 0.9) / cost[b] for b in blocks.BLOCKS for c in blocks.CHUNKS}
    truth[(8, small)] *= 0.8
    truth[(4, large)] *= 0.95
    tuner = BlockTuner(every=10)
    n = len(blocks.BLOCKS) * len(blocks.CHUNKS) * tuner.samples
    picked = _drive(tuner, truth, 1 + n + 40)
    assert sorted(set(picked[1 : 1 + n])) == sorted(truth)  # every pair measured while settling
    settled = picked[1 + n:]
    assert settled.count((8, small)) >= len(settled) - 5
    s = tuner.summary()
    assert s["chunk"] == {"4": large, "8": small, "16": s["chunk"]["16"]} and sum(s["used"].values()) == len(picked)


def _with_wide_ones_past_the_edge(wide: int, x: float) -> tuple[torch.Tensor, ...]:
    """2,000 Gaussians of 3 px sigma over a 640x480 view, plus `wide` of 40 px sigma centred at x
    (off the left edge): cov2d, opacities, means2d, tile rects, float64."""
    from splatcli.render.projection import tile_rect

    g = torch.Generator().manual_seed(0)
    small, _ = _small_gaussians(2000)
    means = torch.cat([torch.rand(2000, 2, generator=g) * torch.tensor([640.0, 480.0]),
                       torch.stack([torch.full((wide,), x), torch.rand(wide, generator=g) * 480], 1)]).double()
    cov2d = torch.cat([small, torch.tensor([[1600.0, 0.0, 1600.0]]).repeat(wide, 1)]).double()
    opac = torch.full((2000 + wide,), 0.9, dtype=torch.float64)
    radii = torch.ceil(3 * torch.sqrt(cov2d[:, 0])).int()
    return cov2d, opac, means, tile_rect(means, radii, 640, 480)


def test_the_model_counts_only_the_part_of_each_box_inside_the_image():
    """A photo's background Gaussians reach far past the frame (fox: unclipped boxes held 1.9x the pairs
    of its 4 px plans and tipped the model to 8 px blocks, 1.15x slower). Given positions, the model
    counts each box within the image and the Gaussian's tiles: 50 wide Gaussians mostly past the left
    edge no longer move the pick off the small ones' 4 px, and one wholly outside counts nothing."""
    cov2d, opac, means, rect = _with_wide_ones_past_the_edge(50, -30.0)
    assert blocks.choose_block(blocks.extents(cov2d, opac), 640, 480) == 8  # boxes counted whole
    assert blocks.choose_block(blocks.extents(cov2d, opac, means, rect), 640, 480) == 4
    inside = blocks.block_costs(blocks.extents(*_with_wide_ones_past_the_edge(0, 0.0)), 640, 480)
    assert blocks.block_costs(blocks.extents(*_with_wide_ones_past_the_edge(50, -500.0)), 640, 480) == inside


def test_extents_drop_only_the_rows_below_1_255_and_costs_sum_each_box():
    """A faint row (255 o <= 1) gets no box, the others the same boxes as without it; the cost
    model's pair counts, taken from three sums, equal the per-box (w / b + 1)(h / b + 1) summed."""
    g = torch.Generator().manual_seed(3)
    n = 300
    cov2d = torch.stack([torch.rand(n, generator=g) * 40 + 0.3, torch.zeros(n), torch.rand(n, generator=g) * 40 + 0.3], 1)
    opac = torch.rand(n, generator=g) * 0.9 + 0.05
    means = torch.rand(n, 2, generator=g) * torch.tensor([640.0, 480.0])
    rect = torch.cat([(means // 16 - 2).clamp_min(0), (means // 16 + 3)], 1).long()
    full = blocks.extents(cov2d.double(), opac.double(), means.double(), rect)
    faint = opac.clone()
    faint[7] = 0.5 / 255
    part = blocks.extents(cov2d.double(), faint.double(), means.double(), rect)
    keep = torch.arange(n) != 7
    assert part.w.numel() == n - 1
    for a, b in ((part.w, full.w[keep]), (part.h, full.h[keep]), (part.lo, full.lo[keep]), (part.hi, full.hi[keep])):
        assert torch.equal(a, b)
    w, h = blocks._boxes(full, 640, 480)
    cost = blocks.block_costs(full, 640, 480)
    for b in blocks.BLOCKS:
        pairs = float(torch.where(w > 0, (w / b + 1) * (h / b + 1), torch.zeros_like(w)).sum())
        model = pairs * (blocks._COST_SLOT * (1 + pairs / blocks._PAIRS_CACHE) + blocks._COST_ELEM * b * b)
        assert cost[b] == pytest.approx(model, rel=1e-12)  # the sums' order differs: float64 rounding only
