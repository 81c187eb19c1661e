"""LPIPS in `splatcli eval`: the AlexNet trunk loaded from --lpips-weights or the torch
hub cache (never downloaded), its value against the `lpips` package called directly,
and eval without the package or the weights (PSNR/SSIM, a null and one hint line).

The real ImageNet weights cannot be fetched here, so each test writes a stand-in:
a seeded random AlexNet `features.*` state dict in torchvision's key layout.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from splatcli.errors import SplatError
from splatcli.eval import lpips as lp
from splatcli.eval.report import ImageScore
from support.tiny_project import assert_user_error, make_tiny_project, run_cli, run_ok

PKG = lp.import_package()
needs_pkg = pytest.mark.skipif(PKG is None, reason="the lpips package (splatcli[lpips]) is not installed")

# torchvision's AlexNet `features`: (index, out channels, in channels, kernel)
ALEX = [(0, 64, 3, 11), (3, 192, 64, 5), (6, 384, 192, 3), (8, 256, 384, 3), (10, 256, 256, 3)]


def stand_in_weights(path: Path, seed: int = 0) -> Path:
    """A seeded random AlexNet trunk in torchvision's layout (plus a classifier key, as the real file has)."""
    g = torch.Generator().manual_seed(seed)
    sd = {}
    for i, cout, cin, k in ALEX:
        sd[f"features.{i}.weight"] = torch.randn(cout, cin, k, k, generator=g) * (2.0 / (cin * k * k)) ** 0.5
        sd[f"features.{i}.bias"] = torch.randn(cout, generator=g) * 0.01
    sd["classifier.1.weight"] = torch.zeros(4, 4)
    torch.save(sd, path)
    return path


@pytest.fixture
def no_hub(tmp_path: Path, monkeypatch) -> Path:
    """An empty torch hub cache: the user's own never decides a test."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch-home"))
    return tmp_path / "torch-home" / "hub" / "checkpoints"


def _image(seed: int, h: int = 40, w: int = 48) -> torch.Tensor:  # [H, W, 3] in [0, 1], smooth and textured
    g = torch.Generator().manual_seed(seed)
    small = torch.rand(1, 3, h // 4, w // 4, generator=g, dtype=torch.float64)
    return torch.nn.functional.interpolate(small, size=(h, w), mode="bilinear", align_corners=False)[0].permute(1, 2, 0)


@needs_pkg
def test_lpips_from_a_weights_file_and_from_the_hub_cache(tmp_path: Path, no_hub: Path) -> None:
    w = stand_in_weights(tmp_path / "alex.pth")
    scorer, why_not = lp.load_lpips(w, torch.device("cpu"))
    assert scorer is not None and why_not is None and scorer.weights == w
    gt = _image(0)
    # same input, same float ops: every feature difference is exactly zero
    assert scorer(gt, gt) == 0.0
    noise = torch.randn(gt.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    d = [scorer((gt + a * noise).clamp(0, 1), gt) for a in (0.01, 0.03, 0.1, 0.3)]
    assert 0 < d[0] and all(a < b for a, b in zip(d, d[1:])), d
    assert scorer(gt[:30], gt[:30]) is None  # below AlexNet's reach

    # the same value through the hub cache (TORCH_HOME), with no path given
    assert lp.load_lpips(None, torch.device("cpu"))[0] is None  # empty cache
    no_hub.mkdir(parents=True)
    stand_in_weights(no_hub / lp.ALEXNET_FILE)
    cached, why_not = lp.load_lpips(None, torch.device("cpu"))
    assert why_not is None and cached is not None and cached.weights == no_hub / lp.ALEXNET_FILE
    assert cached((gt + 0.1 * noise).clamp(0, 1), gt) == d[2]


@needs_pkg
def test_lpips_matches_the_package_called_directly(tmp_path: Path, no_hub: Path) -> None:
    w = stand_in_weights(tmp_path / "alex.pth", seed=3)
    scorer, _ = lp.load_lpips(w, torch.device("cpu"))
    with pytest.warns(UserWarning):  # torchvision's deprecation of `pretrained=`, which lpips passes
        net = PKG.LPIPS(net="alex", pnet_rand=True, verbose=False)  # the package's own layers, v0.1 linear weights
    sd = torch.load(w, weights_only=True)
    slices = {0: 1, 3: 2, 6: 3, 8: 4, 10: 5}  # lpips splits torchvision's features into five slices
    net.net.load_state_dict({f"slice{slices[i]}.{i}.{p}": sd[f"features.{i}.{p}"] for i, *_ in ALEX
                             for p in ("weight", "bias")})
    pred, gt = _image(4), _image(5)
    with torch.no_grad():
        direct = float(net(pred.permute(2, 0, 1)[None].float(), gt.permute(2, 0, 1)[None].float(), normalize=True))
    # the same network on the same float32 inputs (our [-1, 1] mapping is lpips' normalize=True), so the same
    # operations in the same order: equal to the last bit
    assert scorer(pred, gt) == direct


@needs_pkg
@pytest.mark.parametrize("content, fragment", [
    (b"not a torch file", "not a torch weights file"),
    ({"features.0.weight": torch.zeros(64, 3, 11, 11)}, "features.0.bias: missing"),
    ({f"features.{i}.{p}": torch.zeros(3) for i, *_ in ALEX for p in ("weight", "bias")}, "shape (3,)"),
    ([1, 2, 3], "not a state dict"),
])
def test_a_bad_weights_file_is_one_line_naming_it(tmp_path: Path, no_hub: Path, content, fragment: str) -> None:
    path = tmp_path / "bad.pth"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        torch.save(content, path)
    with pytest.raises(SplatError) as e:
        lp.load_lpips(path, torch.device("cpu"))
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"--lpips-weights {path}:") and fragment in msg, msg
    # the same file found in the hub cache is not the user's request: LPIPS is skipped, eval goes on
    no_hub.mkdir(parents=True)
    path.rename(no_hub / lp.ALEXNET_FILE)
    scorer, why_not = lp.load_lpips(None, torch.device("cpu"))
    assert scorer is None and why_not.startswith("LPIPS skipped:") and fragment in why_not


def test_without_the_package_lpips_is_skipped_with_a_hint(tmp_path: Path, no_hub: Path, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "lpips", None)  # `import lpips` now raises ImportError
    assert "no AlexNet weights" in lp.load_lpips(None, torch.device("cpu"))[1]
    no_hub.mkdir(parents=True)
    stand_in_weights(no_hub / lp.ALEXNET_FILE)
    scorer, why_not = lp.load_lpips(None, torch.device("cpu"))
    assert scorer is None and "not installed" in why_not and "splatcli[lpips]" in why_not
    assert "--lpips-weights" in why_not and str(no_hub) in why_not and "\n" not in why_not
    w = stand_in_weights(tmp_path / "alex.pth")  # asked for by name: an error, not a silent skip
    with pytest.raises(SplatError, match="lpips package is not installed"):
        lp.load_lpips(w, torch.device("cpu"))
    with pytest.raises(SplatError, match="no such file"):
        lp.load_lpips(tmp_path / "none.pth", torch.device("cpu"))
    assert ImageScore("a", 30.0, 0.9).lpips is None


@pytest.fixture(scope="module")
def proj(tmp_path_factory):
    return make_tiny_project(tmp_path_factory.mktemp("lpips") / "p")


@needs_pkg
def test_eval_reports_lpips_with_weights(proj, tmp_path: Path, no_hub: Path) -> None:
    w = stand_in_weights(tmp_path / "alex.pth")
    r = run_cli("eval", proj.root, "--lpips-weights", w, "--budgets", "1,0.5", "--formats", "spz", "--no-plots",
                "--out", tmp_path / "rep", "--json")
    assert r.exit_code == 0, r.output
    assert "LPIPS skipped" not in r.stderr
    data = json.loads((tmp_path / "rep" / "eval.json").read_text())
    assert json.loads(r.stdout)["lpips"] == data["lpips"]
    per = [x["lpips"] for x in data["per_image"]]
    assert all(isinstance(x, float) and x > 0 for x in per)  # a perturbed model, not the truth
    assert data["lpips"] == pytest.approx(sum(per) / len(per))
    assert data["budgets"][0]["lpips"] == data["lpips"] and data["budgets"][1]["lpips"] > 0
    assert data["formats"][0]["lpips"] > 0
    md = (tmp_path / "rep" / "eval.md").read_text()
    assert f"| LPIPS (AlexNet) | {data['lpips']:.4f} |" in md
    assert_user_error(run_cli("eval", proj.root, "--lpips-weights", tmp_path / "none.pth"), "--lpips-weights",
                      "none.pth", "no such file")
    # --pred/--gt: a folder against itself is at distance 0
    r = run_ok("eval", "--pred", proj.images_dir, "--gt", proj.images_dir, "--lpips-weights", w, "--json")
    folder = json.loads(r.stdout)
    assert folder["lpips"] == 0.0 and all(x["lpips"] == 0.0 for x in folder["per_image"])


def test_eval_without_weights_reports_null_and_one_hint(proj, tmp_path: Path, no_hub: Path) -> None:
    r = run_ok("eval", proj.root, "--budgets", "1", "--no-plots", "--out", tmp_path / "rep", "--json")
    hints = [line for line in r.stderr.splitlines() if "LPIPS skipped" in line]
    assert len(hints) == 1 and "--lpips-weights" in hints[0] and "pip install 'splatcli[lpips]'" in hints[0], r.stderr
    data = json.loads((tmp_path / "rep" / "eval.json").read_text())
    assert data["lpips"] is None and json.loads(r.stdout)["lpips"] is None
    assert all(x["lpips"] is None for x in data["per_image"]) and data["psnr"] > 15 and data["ssim"] > 0
    md = (tmp_path / "rep" / "eval.md").read_text()
    assert "| LPIPS (AlexNet) | — |" in md and "Note: LPIPS skipped" in md
