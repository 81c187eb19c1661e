"""Initialisation (kNN scales, random points, budget subsets, .ply) and the
training data cache (resolution rule, image decoding, splits)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from splatcli.camera import Camera
from splatcli.cli.train_config import make_config
from splatcli.errors import SplatError
from splatcli.formats.ply import write_ply
from splatcli.gaussians import SH_C0, Gaussians
from splatcli.inputs.images import load_rgb
from splatcli.render.output import RenderOutput
from splatcli.render.projection import NEAR, in_frustum
from splatcli.strategy import DefaultStrategy, DefaultStrategyConfig, Splats, StepInfo, SupportConfig, SupportPrune
from splatcli.train.data import TrainView, load_train_data, views_seeing
from splatcli.train.init import (
    far_points,
    gaussians_from_points,
    initial_gaussians,
    knn_rms_distance,
    random_points,
    subsample_index,
)
from support.context import context
from support.tiny_project import make_tiny_project, run_cli

CPU = torch.device("cpu")


def _brute_knn(p: torch.Tensor, k: int) -> torch.Tensor:
    d = torch.cdist(p.double(), p.double(), compute_mode="donot_use_mm_for_euclid_dist")
    return d.topk(k + 1, dim=1, largest=False).values[:, 1:].square().mean(1).sqrt()


@pytest.mark.parametrize("kind", ["uniform", "clustered", "flat", "duplicates", "tiny"])
def test_knn_matches_brute_force(kind):
    g = torch.Generator().manual_seed(7)
    if kind == "uniform":
        p = torch.rand(3000, 3, generator=g)
    elif kind == "clustered":  # dense core, sparse halo: per-block radii must still bound the search
        p = torch.randn(2500, 3, generator=g) ** 3
    elif kind == "flat":
        p = torch.rand(1500, 3, generator=g) * torch.tensor([10.0, 1.0, 1e-3]) + 100.0
    elif kind == "duplicates":
        p = torch.rand(400, 3, generator=g).repeat(2, 1)
    else:
        p = torch.rand(3, 3, generator=g)
    # float32 input; the reference is float64: differences are float32 rounding of distances
    torch.testing.assert_close(knn_rms_distance(p, 3).double(), _brute_knn(p, min(3, len(p) - 1)),
                               rtol=1e-3, atol=1e-5)


def test_knn_single_point_gets_unit_scale():
    assert knn_rms_distance(torch.zeros(1, 3), 3).tolist() == [1.0]


def test_gaussians_from_points_follow_the_recipe():
    pts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    cols = torch.tensor([[1.0, 0.0, 0.5]] * 4)
    g = gaussians_from_points(pts, cols, sh_degree=2)
    assert g.sh.shape == (4, 9, 3) and bool((g.sh[:, 1:] == 0).all())
    torch.testing.assert_close(SH_C0 * g.sh[:, 0] + 0.5, cols)
    torch.testing.assert_close(torch.sigmoid(g.opacity_logits), torch.full((4,), 0.1))
    assert torch.equal(g.quats, torch.tensor([[1.0, 0, 0, 0]] * 4))
    # point 0's three neighbours are at distance 1: log scale 0, isotropic
    torch.testing.assert_close(g.log_scales[0], torch.zeros(3), rtol=0, atol=1e-6)
    with pytest.raises(SplatError):
        gaussians_from_points(torch.zeros(0, 3), torch.zeros(0, 3), 0)


def test_random_points_are_seeded_and_inside_the_box():
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([1.0, 0.5, 3.0])
    a, ca = random_points(500, lo, hi, seed=3, device=CPU)
    b, cb = random_points(500, lo, hi, seed=3, device=CPU)
    c, _ = random_points(500, lo, hi, seed=4, device=CPU)
    assert torch.equal(a, b) and torch.equal(ca, cb) and not torch.equal(a, c)
    assert bool((a >= torch.tensor(lo, dtype=torch.float32)).all() and (a <= torch.tensor(hi, dtype=torch.float32)).all())


def test_subsample_index():
    idx = subsample_index(100, 30, seed=0)
    assert len(idx) == 30 == len(set(idx.tolist())) and torch.equal(idx, idx.sort().values)
    assert torch.equal(subsample_index(5, 30, seed=0), torch.arange(5))


def test_init_from_ply_pads_sh(tmp_path):
    g = Gaussians(torch.randn(6, 3), torch.randn(6, 4), torch.randn(6, 3), torch.randn(6), torch.randn(6, 4, 3))
    write_ply(tmp_path / "s.ply", g)
    h = initial_gaussians(make_config(init_ply=str(tmp_path / "s.ply"), sh_degree="3"), None, CPU)
    assert h.sh.shape == (6, 16, 3)
    torch.testing.assert_close(h.sh[:, :4], g.sh)
    torch.testing.assert_close(h.means, g.means)


def test_training_camera_rule():
    cam = Camera("a.png", 1920, 1080, np.array([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]]), np.eye(4))
    c = cam.at_resolution(2.0, 1600)
    assert (c.width, c.height) == (960, 540)
    c = cam.at_resolution(1.0, 480)
    assert (c.width, c.height) == (480, 270) and math.isclose(c.K[0, 0], 250.0)
    assert cam.at_resolution(1.0, 4000) is cam


@pytest.mark.parametrize("kind", ["rgb", "rgba", "gray", "u16"])
def test_load_rgb_decodes_to_rgb_uint8(tmp_path, kind):
    rgb = np.zeros((8, 10, 3), np.uint8)
    rgb[..., 0] = 200  # red
    path = tmp_path / "x.png"
    if kind == "rgb":
        cv2.imwrite(str(path), rgb[..., ::-1])
    elif kind == "rgba":
        cv2.imwrite(str(path), np.dstack([rgb[..., ::-1], np.full((8, 10), 255, np.uint8)]))
    elif kind == "gray":
        cv2.imwrite(str(path), np.full((8, 10), 200, np.uint8))
    else:
        cv2.imwrite(str(path), (rgb[..., ::-1].astype(np.uint16) * 257))
    out = load_rgb(path, (10, 8))
    assert out.shape == (8, 10, 3) and out.dtype == np.uint8 and out[0, 0, 0] == 200
    assert load_rgb(path, (5, 4)).shape == (4, 5, 3)
    with pytest.raises(SplatError):
        load_rgb(tmp_path / "missing.png", (5, 4))


def test_load_train_data_uses_the_splits(tmp_path):
    proj = make_tiny_project(tmp_path / "p", trained=False, background=1.0)
    data = load_train_data(proj, 2.0, None, CPU)
    names = proj.splits()
    assert [v.camera.name for v in data.train] == names["train"]
    assert [v.camera.name for v in data.test] == names["test"]
    assert data.train[0].image.shape == (20, 24, 3) and data.train[0].image.dtype == torch.uint8
    assert data.background.tolist() == [1.0, 1.0, 1.0] and data.extent > 0
    assert load_train_data(proj, 1.0, None, CPU, eval_max_views=1).test[0].camera.name == names["test"][0]


def test_coarse_views_are_area_filtered_and_cameras_scaled(tmp_path):
    proj = make_tiny_project(tmp_path / "p", trained=False)
    v = load_train_data(proj, 1.0, None, CPU).train[0]
    h = v.at_scale(0.5)
    assert (h.camera.width, h.camera.height) == (round(v.camera.width / 2), round(v.camera.height / 2))
    np.testing.assert_allclose(h.camera.K[:2], v.camera.K[:2] * np.array([[h.camera.width / v.camera.width],
                                                                          [h.camera.height / v.camera.height]]))
    # a 2x2 block mean, rounded (the widths here are even)
    blocks = v.image.float().reshape(h.camera.height, 2, h.camera.width, 2, 3).mean(dim=(1, 3))
    assert torch.equal(h.image, blocks.round().to(torch.uint8))
    assert v.at_scale(0.5) is h and v.at_scale(1.0) is v  # cached; full scale is the view itself
    assert v._scaled == {}  # ... and frees the coarse copy
    q = v.at_scale(0.25)
    v.at_scale(0.5)
    assert list(v._scaled) == [0.5] and q.image.shape[0] == round(v.camera.height / 4)  # one level at a time


def test_coarse_schedule_rises_to_full_resolution():
    cfg = make_config("fast", coarse_scale=0.25, coarse_until=0.5)
    scales = [cfg.train_scale(s) for s in range(0, cfg.iterations + 1, 50)]
    assert scales[0] == 0.25 and all(b >= a for a, b in zip(scales, scales[1:]))
    assert all(s == 1.0 for s, step in zip(scales, range(0, cfg.iterations + 1, 50)) if step >= 3500)
    assert all(s * 8 == int(s * 8) for s in scales)  # a few cached levels, not one per step
    assert make_config("default").train_scale(0) == 1.0  # the paper's schedule stays at full resolution
    assert make_config("fast").train_scale(0) == 0.25  # the CPU preset starts coarse


def test_far_points_lie_on_the_sphere_where_views_see_them_coloured_by_the_pixels():
    """--init-far: a camera at the origin looking along +z with a left-half red, right-half
    blue image sees the points of the far sphere in its frustum only; each takes the colour
    of the pixel it falls on."""
    cam = Camera("a", 64, 48, np.array([[40.0, 0, 32], [0, 40, 24], [0, 0, 1]]), np.eye(4))
    img = torch.zeros(48, 64, 3, dtype=torch.uint8)
    img[:, :32, 0] = 255
    img[:, 32:, 2] = 255
    vm, K = cam.torch(CPU)
    pts, cols = far_points(4000, [TrainView(cam, img, vm, K)], np.zeros(3), 10.0)
    assert 50 < len(pts) < 4000  # the frustum's share of the sphere
    torch.testing.assert_close(pts.norm(dim=1), torch.full((len(pts),), 10.0))
    assert bool((pts[:, 2] > 0).all())  # in front of the camera
    u = pts[:, 0] / pts[:, 2] * 40.0 + 32.0
    assert bool(((cols[:, 0] == 1) == (u < 32)).all()) and bool(((cols[:, 2] == 1) == (u >= 32)).all())


def test_init_far_adds_the_sphere_to_the_sfm_points(tmp_path):
    proj = make_tiny_project(tmp_path / "p", trained=False)
    data = load_train_data(proj, 1.0, None, CPU)
    plain = initial_gaussians(make_config("fast"), data, CPU)
    g = initial_gaussians(make_config("fast", init_far=2000), data, CPU)
    far = g.means[len(plain):].double()
    assert len(g) > len(plain) and torch.equal(g.means[: len(plain)], plain.means)
    r = (far - torch.as_tensor(data.center)).norm(dim=1)
    torch.testing.assert_close(r, torch.full_like(r, 5.0 * data.extent), rtol=1e-5, atol=0)  # float32 points
    with pytest.raises(SplatError, match="init_far_radius"):
        make_config("fast", init_far=10, init_far_radius=0.5)


def test_mcmc_starts_from_its_own_initial_opacity(tmp_path):
    """--strategy mcmc starts SfM points at mcmc_init_opacity (0.5, gsplat's MCMC example's),
    the default strategy at init_opacity (0.1, 3DGS's); random points start at init_opacity
    under either (0.5 fogs the box on lego); out-of-range values are one-line errors."""
    proj = make_tiny_project(tmp_path / "p", trained=False)
    data = load_train_data(proj, 1.0, None, CPU)
    assert not len(data.points)  # the tiny project has no SfM points: random points in the box
    rand = initial_gaussians(make_config("fast", strategy="mcmc", max_gaussians=500), data, CPU)
    torch.testing.assert_close(torch.sigmoid(rand.opacity_logits), torch.full((len(rand),), 0.1))
    rng = np.random.default_rng(0)
    data.points, data.colors = rng.uniform(-1, 1, (64, 3)), rng.integers(0, 256, (64, 3), dtype=np.uint8)
    plain = initial_gaussians(make_config("fast"), data, CPU)
    mcmc = initial_gaussians(make_config("fast", strategy="mcmc", max_gaussians=10**6), data, CPU)
    torch.testing.assert_close(torch.sigmoid(plain.opacity_logits), torch.full((64,), 0.1))
    torch.testing.assert_close(torch.sigmoid(mcmc.opacity_logits), torch.full((64,), 0.5))
    assert torch.equal(plain.means, mcmc.means) and torch.equal(plain.log_scales, mcmc.log_scales)
    with pytest.raises(SplatError, match="mcmc_init_opacity"):
        make_config("fast", mcmc_init_opacity=0.0)


def test_far_gaussians_are_size_pruned_by_angle_not_world_size():
    """The default strategy's world-size prune (after the first reset) spares a large
    Gaussian far from the cameras when given the scene centre, and prunes it without."""

    def run(center):
        means = torch.tensor([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0]])
        p = {"means": means, "quats": torch.tensor([[1.0, 0, 0, 0]] * 2),
             "log_scales": torch.full((2, 3), math.log(2.0)), "opacity_logits": torch.zeros(2),
             "sh0": torch.zeros(2, 1, 3)}
        params = {k: nn.Parameter(v) for k, v in p.items()}
        sp = Splats(params, {k: torch.optim.Adam([v]) for k, v in params.items()}, [])
        s = DefaultStrategy(DefaultStrategyConfig(refine_start=0, opacity_reset=10, refine_every=100), 10.0, center)
        st = s.initial_state(2, CPU)
        sp.states.append(st)
        z = torch.zeros(2)
        out = RenderOutput(image=torch.zeros(2, 2, 3), alpha=torch.zeros(2, 2), depth=torch.zeros(2, 2),
                           means2d=torch.zeros(2, 2), radii=torch.zeros(2, dtype=torch.int32), visible=z.bool(),
                           depths=z)
        s.step_post_backward(sp, st, 100, StepInfo(out, 2, 2))
        return sp.params["means"][:, 0].tolist()

    assert run(None) == []  # 2 > 0.1 x 10: both pruned by world size
    assert run(torch.zeros(3)) == [50.0]  # 50 away: its limit is 5 x 1.0 = 5 > 2


@pytest.mark.slow
def test_views_seeing_counts_frustums_and_prune_views_drops_the_rest(tmp_path):
    """views_seeing: a point counts for a view when in front of its near plane and inside its
    image; --prune-views then prunes while densifying, and the run still trains."""
    cam = Camera("a", 64, 48, np.array([[40.0, 0, 32], [0, 40, 24], [0, 0, 1]]), np.eye(4))
    vm, K = cam.torch(CPU)
    v = TrainView(cam, torch.zeros(48, 64, 3, dtype=torch.uint8), vm, K)
    pts = torch.tensor([[0.0, 0, 5], [0, 0, -5], [0, 0, 0.1], [100, 0, 5], [-3.9, -2.9, 5]])  # seen, behind, too near, outside, corner
    assert views_seeing([v, v], pts).tolist() == [2, 0, 0, 0, 2]
    proj = make_tiny_project(tmp_path / "p", trained=False)
    r = run_cli("train", proj.root, "--preset", "demo", "--iterations", "400", "--prune-views", "3", "--eval-every", "0",
                "--json", "-q")
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout.strip().splitlines()[-1])["num_gaussians"] > 0


def test_support_prune_drops_what_few_views_see_on_the_refinement_schedule():
    seen = torch.tensor([5, 1, 3, 0], dtype=torch.int32)
    ctx = context(seeing=lambda means: seen[: len(means)])
    params = {"means": nn.Parameter(torch.arange(4.0)[:, None].repeat(1, 3))}
    sp = Splats(params, {"means": torch.optim.Adam([params["means"]])}, [])
    s = SupportPrune(SupportConfig(prune_views=3), 100, 400, 100, ctx)
    assert s.step_post_backward(sp, None, 150, None) is None and len(sp) == 4  # not a refinement step
    stats = s.step_post_backward(sp, None, 200, None)
    assert stats.pruned == 2 and sp.params["means"][:, 0].tolist() == [0.0, 2.0]
    assert s.step_post_backward(sp, None, 500, None) is None  # after refine_stop


def test_in_frustum_bounds_near_plane_and_margin():
    K = torch.tensor([[10.0, 0, 5], [0, 10.0, 4], [0, 0, 1]], dtype=torch.float64)
    vm = torch.eye(4, dtype=torch.float64)
    # centre; the right edge (u = 10 = width: outside); behind the near plane; 2 px left of the image
    pts = torch.tensor([[0, 0, 1.0], [0.5, 0, 1], [0, 0, NEAR / 2], [-0.7, 0, 1]], dtype=torch.float64)
    uv, z, inside = in_frustum(pts, vm, K, 10, 8)
    torch.testing.assert_close(uv[0], torch.tensor([5.0, 4.0], dtype=torch.float64))
    assert inside.tolist() == [True, False, False, False] and z[2] == NEAR / 2
    assert in_frustum(pts, vm, K, 10, 8, margin=0.25)[2].tolist() == [True, True, False, True]  # 2.5 px grace
