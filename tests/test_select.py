"""Spatio-textural feature selection (eq. 9): patch maxima, eligibility, back-projection, batching."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from tolerances import F32_UNIT

from torchtrack.geometry import backproject
from torchtrack.image.corners import harris
from torchtrack.image.select import (
    Features,
    cornerness_maps,
    patch_shape,
    roi_patch_size,
    select_features,
)
from torchtrack.image.shape_index import compute_sim

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
H, W, F_ = 240, 320, 300.0


def K_of(f=F_, cx=(W - 1) / 2, cy=(H - 1) / 2) -> torch.Tensor:
    return torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])[None]


def synthetic_frame(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """gray (1,1,H,W) blocky texture; depth (1,1,H,W): a sphere (r 0.15 m at 0.8 m) before a wall at 1.5 m,
    with a hole; K (1,3,3)."""
    rng = np.random.default_rng(seed)
    tex = cv2.resize(rng.random((H // 12, W // 12)).astype(np.float32), (W, H), interpolation=cv2.INTER_NEAREST)
    gray = torch.from_numpy(cv2.GaussianBlur(tex, (0, 0), 1.0))[None, None]
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    x, y = (u - (W - 1) / 2) / F_, (v - (H - 1) / 2) / F_
    a = x * x + y * y + 1
    disc = 0.64 - a * (0.64 - 0.15**2)
    z = torch.where(disc > 0, (0.8 - disc.clamp_min(0).sqrt()) / a, torch.full_like(a, 1.5))
    z[20:40, 30:90] = 0.0  # no depth here
    return gray, z.float()[None, None], K_of()


def real_frames(seqs=("visp_rbt_sequence", "sun3d_fragment1", "visp_castle_simu"), i=2):
    """B=len(seqs) real frames (gray, depth, K) from ../shared/data, different intrinsics; skip when absent."""
    grays, depths, Ks = [], [], []
    for seq in seqs:
        folder = DATA / seq
        if not (folder / "rgb.txt").exists():
            pytest.skip(f"{folder} not available")
        lines = [ln.split() for ln in (folder / "rgb.txt").read_text().splitlines() if ln and ln[0] != "#"]
        dlines = [ln.split() for ln in (folder / "depth.txt").read_text().splitlines() if ln and ln[0] != "#"]
        intr = [ln for ln in (folder / "intrinsics.txt").read_text().splitlines() if ln and ln[0] != "#"][0]
        fx, fy, cx, cy, scale = (float(v) for v in intr.split())
        g = cv2.cvtColor(cv2.imread(str(folder / lines[i][1])), cv2.COLOR_BGR2GRAY).astype(np.float32) / 255
        d = cv2.imread(str(folder / dlines[i][1]), cv2.IMREAD_UNCHANGED).astype(np.float32) / scale
        grays.append(torch.from_numpy(g)[None])
        depths.append(torch.from_numpy(d)[None])
        Ks.append(torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float32))
    return torch.stack(grays), torch.stack(depths), torch.stack(Ks)


def patch_id(pixels: torch.Tensor, ph: int, pw: int, gw: int) -> torch.Tensor:
    return (pixels[..., 1].long() // ph) * gw + pixels[..., 0].long() // pw


# ---------------------------------------------------------------------------------------------- smoke/shape
def test_shapes_and_dtypes():
    gray, depth, K = synthetic_frame()
    f = select_features(gray, depth, K)
    assert isinstance(f, Features)
    B, N = f.valid.shape
    assert B == 1 and 0 < N <= (H // 32 + 1) * (W // 32)
    assert f.pixels.shape == (B, N, 2) and f.points.shape == (B, N, 3)
    for c in (f.cornerness, f.cornerness_int, f.cornerness_sim):
        assert c.shape == (B, N) and c.dtype == torch.float32
    assert f.valid.dtype == torch.bool and f.valid.all()  # N is the largest count: no padding at B = 1
    assert torch.all(f.cornerness[:, :-1] >= f.cornerness[:, 1:])  # sorted by decreasing C


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(gray=torch.rand(1, H, W)), "gray and depth"),
        (dict(depth=torch.rand(1, 1, H, W + 1)), "gray and depth"),
        (dict(K=torch.eye(3)), "K must be"),
        (dict(roi=torch.ones(1, 1, H, W - 1, dtype=torch.bool)), "roi must be"),
        (dict(lam=1.5), "lam must be"),
        (dict(border=H), "border"),
        (dict(patch_size=0), "patch size"),
    ],
)
def test_bad_input_raises(kwargs, match):
    gray, depth, K = synthetic_frame()
    args = dict(gray=gray, depth=depth, K=K)
    args.update(kwargs)
    g, d, k = args.pop("gray"), args.pop("depth"), args.pop("K")
    with pytest.raises(ValueError, match=match):
        select_features(g, d, k, **args)


def test_patch_shape():
    assert patch_shape(480, 640) == (32, 32, 15, 20)  # 300 patches
    assert patch_shape(480, 640, grid=(15, 20)) == (32, 32, 15, 20)
    assert patch_shape(480, 640, (24, 40)) == (24, 40, 20, 16)
    assert patch_shape(100, 100, 32) == (32, 32, 4, 4)  # partial patches at the edge


# ---------------------------------------------------------------------------------------------- oracles
@pytest.mark.parametrize("lam", [1.0, 0.5, 0.0])
def test_one_feature_per_patch_at_its_maximum(lam):
    """Brute-force oracle: per patch, the feature is the eligible pixel of maximum C, if C > min_cornerness."""
    gray, depth, K = synthetic_frame(1)
    ps, border, min_c = 24, 6, 0.05
    ph, pw, gh, gw = patch_shape(H, W, ps)
    f = select_features(gray, depth, K, lam=lam, patch_size=ps, border=border, min_cornerness=min_c)
    maps = cornerness_maps(gray, depth, K, roi=None, sim=None, lam=lam, patches=(ph, pw, gh, gw), border=border)
    C = maps.C[0, 0].numpy()
    got = {
        int(p): tuple(xy)
        for p, xy in zip(
            patch_id(f.pixels[0], ph, pw, gw)[f.valid[0]].tolist(), f.pixels[0][f.valid[0]].tolist(), strict=True
        )
    }
    assert len(got) == int(f.valid.sum())  # at most one feature per patch
    for i in range(gh):
        for j in range(gw):
            block = C[i * ph : (i + 1) * ph, j * pw : (j + 1) * pw]
            r, c = np.unravel_index(np.argmax(block), block.shape)
            if block[r, c] > min_c:
                assert got.pop(i * gw + j) == (j * pw + c, i * ph + r)
    assert not got  # no feature in a patch without a candidate


def test_features_are_eligible_and_backprojected():
    gray, depth, K = synthetic_frame(2)
    roi = torch.zeros(1, 1, H, W, dtype=torch.bool)
    roi[..., :, : W // 2 + 40] = True
    sim = compute_sim(depth, K)
    border = 10
    f = select_features(gray, depth, K, roi=roi, sim=sim, lam=0.5, border=border, patch_size=16, require_sim=True)
    px = f.pixels[0][f.valid[0]].long()
    u, v = px[:, 0], px[:, 1]
    assert len(px) > 20
    assert torch.all(depth[0, 0, v, u] > 0)  # valid depth
    assert torch.all(roi[0, 0, v, u])  # in the region of interest
    assert torch.all(sim.valid[0, 0, v, u])  # valid SIM (lam < 1)
    assert torch.all((u >= border) & (u < W - border) & (v >= border) & (v < H - border))
    expected = backproject(K, f.pixels.double(), depth[0, 0, f.pixels[..., 1].long(), f.pixels[..., 0].long()].double())
    assert torch.allclose(f.points[f.valid].double(), expected[f.valid], atol=1e-6)
    assert torch.allclose(f.cornerness[f.valid], 0.5 * (f.cornerness_int + f.cornerness_sim)[f.valid], atol=1e-6)


def test_lambda_one_is_pure_intensity_harris():
    """lam = 1 picks, per patch, the pixel of maximum raw Harris response of the intensity image."""
    gray, depth, K = synthetic_frame(3)
    ph, pw, gh, gw = patch_shape(H, W, 32)
    f = select_features(gray, depth, K, lam=1.0, border=4, min_cornerness=0.0)
    R = harris(gray)[0, 0].numpy()
    R[depth[0, 0].numpy() <= 0] = -np.inf
    R[:4], R[-4:], R[:, :4], R[:, -4:] = -np.inf, -np.inf, -np.inf, -np.inf
    for (x, y), ok in zip(f.pixels[0].long().tolist(), f.valid[0].tolist(), strict=True):
        assert ok
        i, j = y // ph, x // pw
        block = R[i * ph : (i + 1) * ph, j * pw : (j + 1) * pw]
        assert R[y, x] == block.max()
    assert torch.all(f.cornerness_sim == 0)


def test_contrast_invariance():
    """Normalisation: an affine change of the intensity image (contrast 0.4, offset 0.3) selects the same pixels."""
    gray, depth, K = synthetic_frame(4)
    a = select_features(gray, depth, K, lam=0.5)
    b = select_features(0.4 * gray + 0.3, depth, K, lam=0.5)
    assert torch.equal(a.valid, b.valid)
    assert torch.equal(a.pixels, b.pixels)
    assert torch.allclose(a.cornerness_int, b.cornerness_int, atol=1e-4)


def test_no_spread_is_global_top_n_with_nms():
    gray, depth, K = synthetic_frame(5)
    n, r, border = 40, 3, 8
    f = select_features(gray, depth, K, lam=1.0, spread=False, max_features=n, nms_radius=r, border=border)
    maps = cornerness_maps(gray, depth, K, roi=None, sim=None, lam=1.0, patches=patch_shape(H, W), border=border)
    C = maps.C[0, 0].numpy()
    peak = (C == cv2.dilate(C, np.ones((2 * r + 1,) * 2, np.uint8))) & (C > 0.05)
    ys, xs = np.nonzero(peak)
    top = np.argsort(-C[ys, xs], kind="stable")[:n]
    assert f.valid.sum() == n
    assert set(map(tuple, f.pixels[0].long().tolist())) == set(zip(xs[top].tolist(), ys[top].tolist(), strict=True))
    d = (f.pixels[0, :, None] - f.pixels[0, None]).abs().amax(-1) + 1e3 * torch.eye(n)
    assert d.min() > r  # suppressed within the NMS window


def test_max_features_keeps_the_strongest():
    gray, depth, K = synthetic_frame(6)
    full = select_features(gray, depth, K, lam=1.0)
    top = select_features(gray, depth, K, lam=1.0, max_features=10)
    assert top.pixels.shape[1] == 10
    assert torch.equal(top.pixels, full.pixels[:, :10])


def test_grid_equals_patch_size():
    gray, depth, K = synthetic_frame(7)
    a = select_features(gray, depth, K, grid=(8, 10), roi_fraction=None)  # a grid is the fixed grid
    b = select_features(gray, depth, K, patch_size=(30, 32), roi_fraction=None)
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


def test_empty_roi_gives_no_features():
    gray, depth, K = synthetic_frame(8)
    f = select_features(gray, depth, K, roi=torch.zeros(1, 1, H, W, dtype=torch.bool))
    assert f.valid.shape == (1, 1) and not f.valid.any() and torch.all(f.points == 0)


# ---------------------------------------------------------------------------------------------- batching
def assert_batched_equals_looped(gray, depth, K, **kw):
    """Other batch shapes run other kernels: values within F32_UNIT (cornerness in [0, 1), points within ~5 m); the
    choices (valid, the integer pixels) exactly: a flip needs two candidates within rounding (none on these frames)."""
    batched = select_features(gray, depth, K, **kw)
    whole = select_features(gray, depth, K, cpu_chunk=None, **kw)  # one pass over the batch, no chunks
    assert all(torch.allclose(x.float(), y.float(), atol=F32_UNIT, rtol=0) for x, y in zip(batched, whole, strict=True))
    for b in range(gray.shape[0]):
        one = select_features(gray[b : b + 1], depth[b : b + 1], K[b : b + 1], **kw)
        n = one.valid.shape[1]
        assert one.valid.sum() > 15
        assert torch.equal(batched.valid[b, :n], one.valid[0]) and not batched.valid[b, n:].any()
        for x, y in zip(batched, one, strict=True):
            assert torch.allclose(x[b, :n].float(), y[0].float(), atol=F32_UNIT, rtol=0)


@pytest.mark.equivalence
def test_batched_equals_looped_real_frames():
    assert_batched_equals_looped(*real_frames())  # three sequences, three cameras


@pytest.mark.equivalence
def test_batched_equals_looped_no_spread():
    frames = [synthetic_frame(s) for s in range(3)]
    gray, depth = torch.cat([f[0] for f in frames]), torch.cat([f[1] for f in frames])
    K = torch.cat([K_of(), K_of(f=280.0), K_of(f=320.0, cx=150.0)])
    assert_batched_equals_looped(gray, depth, K, lam=0.7, spread=False, max_features=60)


def test_list_arguments_equal_tuples():
    """The pipeline binds select_features with Hydra's ``_partial_``, which passes patch_size and grid as lists."""
    gray, depth, K = synthetic_frame(9)
    out = select_features(gray, depth, K, lam=0.3, patch_size=[20, 24], border=5, roi_fraction=None)
    ref = select_features(gray, depth, K, lam=0.3, patch_size=(20, 24), border=5, roi_fraction=None)
    assert all(torch.equal(a, b) for a, b in zip(out, ref, strict=True))
    out = select_features(gray, depth, K, grid=[6, 8], border=5, roi_fraction=None)
    ref = select_features(gray, depth, K, grid=(6, 8), border=5, roi_fraction=None)
    assert all(torch.equal(a, b) for a, b in zip(out, ref, strict=True))


# ---------------------------------------------------------------------------------------------- roi_fraction
def rect_roi(top: int, left: int, h: int, w: int, shape=(1, 1, H, W)) -> torch.Tensor:
    roi = torch.zeros(shape, dtype=torch.bool)
    roi[..., top : top + h, left : left + w] = True
    return roi


@pytest.mark.parametrize(("h", "w", "frac", "expected"), [(60, 80, 0.5, 11), (60, 80, 0.1, 25), (100, 120, 0.5, 17)])
def test_roi_patch_size_is_the_closed_form(h, w, frac, expected):
    """floor(32 sqrt(box area / (frac H W))) clamped to [min_patch, 32]; the box is the eligible pixels' bounding box
    (holes inside it do not count); a box covering more than frac of the image keeps 32."""
    roi = rect_roi(30, 40, h, w)
    roi[..., 35:45, 50:60] = False  # a hole inside the box
    size = math.floor(32 * math.sqrt(h * w / (frac * H * W)))
    assert size == expected
    assert roi_patch_size(roi, 32, frac, min_patch=1) == [size]
    assert roi_patch_size(roi, 32, frac, min_patch=12) == [max(12, size)]
    assert roi_patch_size(torch.zeros_like(roi), 24, frac) == [24]  # nothing eligible: the configured size
    assert roi_patch_size(rect_roi(0, 0, H, W // 2 + 2), 32, 0.5) == [32]  # just over half the image
    inside = rect_roi(10, 10, H - 20, (W - 20) // 2 + 2)  # just over half the image inside a 10 px border
    no_border = math.floor(32 * math.sqrt((H - 20) * ((W - 20) // 2 + 2) / (0.5 * H * W)))
    assert roi_patch_size(inside, 32, 0.5, border=10) == [32] and roi_patch_size(inside, 32, 0.5) == [no_border] != [32]


def test_roi_fraction_is_the_fixed_grid_of_that_size():
    """With roi_fraction the selection equals the plain selection at the patch size of the closed form; a region that
    covers more of the image keeps the configured patch size, so the result is unchanged."""
    gray, depth, K = synthetic_frame(4)
    roi = rect_roi(60, 100, 90, 120)  # inside the border, with depth everywhere
    size = max(8, math.floor(32 * math.sqrt(90 * 120 / (0.5 * (H - 24) * (W - 24)))))  # border 12
    a = select_features(gray, depth, K, roi=roi, roi_fraction=0.5)
    b = select_features(gray, depth, K, roi=roi, patch_size=size, roi_fraction=None)
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    assert int(a.valid.sum()) > 2 * int(select_features(gray, depth, K, roi=roi, roi_fraction=None).valid.sum())
    full = rect_roi(0, 0, H, W)
    c = select_features(gray, depth, K, roi=full, patch_size=16, roi_fraction=0.5)  # the whole image inside the border
    d = select_features(gray, depth, K, roi=full, patch_size=16, roi_fraction=None)
    assert all(torch.equal(x, y) for x, y in zip(c, d, strict=True))


@pytest.mark.equivalence
def test_roi_fraction_batched_equals_looped():
    """Frames of one batch get their own patch sizes (a small and a large region)."""
    frames = [synthetic_frame(s) for s in range(2)]
    gray, depth, K = torch.cat([f[0] for f in frames]), torch.cat([f[1] for f in frames]), torch.cat([K_of()] * 2)
    roi = torch.cat([rect_roi(60, 100, 80, 110), rect_roi(20, 20, 200, 280)])
    batched = select_features(gray, depth, K, roi=roi, roi_fraction=0.5)
    for b in range(2):
        one = select_features(gray[b : b + 1], depth[b : b + 1], K[b : b + 1], roi=roi[b : b + 1], roi_fraction=0.5)
        n = one.valid.shape[1]
        assert torch.equal(batched.valid[b, :n], one.valid[0]) and not batched.valid[b, n:].any()
        assert torch.equal(batched.pixels[b, :n], one.pixels[0])
        for x, y in zip(batched, one, strict=True):  # other batch shapes: within rounding
            torch.testing.assert_close(x[b, :n], y[0], atol=F32_UNIT, rtol=0)


def test_roi_fraction_bad_input_raises():
    gray, depth, K = synthetic_frame()
    with pytest.raises(ValueError, match="roi_fraction needs an int patch_size"):
        select_features(gray, depth, K, grid=(8, 10), roi_fraction=0.5)
    with pytest.raises(ValueError, match="need 0 < roi_fraction <= 1"):
        select_features(gray, depth, K, roi_fraction=0.0)
