"""The landmark map's keyframe window (torchtrack/estimators/keyframe_window.py) against exact synthetic truth."""

from __future__ import annotations

import math

import torch

from torchtrack.estimators.keyframe_window import refine_keyframes
from torchtrack.estimators.window import window_measure
from torchtrack.geometry import T_inv, make_T, se3_exp, so3_exp

F64 = torch.float64


def _scene(B=2, S=3, P=8, L=12, C=6, seed=0):
    """Keyframe slots in shuffled insertion order (stamps 2, 0, 1; sequence 1's stamp-2 slot empty), each seeing P of L
    landmarks (identities 0..L-1) exactly; the current camera sees C of them. Returns the truth and the inputs."""
    g = torch.Generator().manual_seed(seed)
    xi = torch.cat([0.05 * torch.randn(B, S + 1, 3, generator=g, dtype=F64),
                    math.radians(3) * torch.randn(B, S + 1, 3, generator=g, dtype=F64)], -1)  # fmt: skip
    T_world_cam = se3_exp(xi)
    X = torch.cat(
        [torch.rand(B, L, 2, generator=g, dtype=F64) - 0.5, 2 + torch.rand(B, L, 1, generator=g, dtype=F64)], -1
    )
    K = torch.tensor([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]], dtype=F64).expand(B, 3, 3)
    T_cd = make_T(so3_exp(torch.tensor([0.0, 0.01, 0.0], dtype=F64)), torch.tensor([0.025, 0, 0], dtype=F64))
    T_cd = T_cd.expand(B, 4, 4)
    ident = torch.stack([torch.stack([torch.randperm(L, generator=g)[:P] for _ in range(S)]) for _ in range(B)])
    h = window_measure(T_inv(T_world_cam), X, K, T_cd).h  # B,S+1,L,5
    pick = lambda t, idx: t.gather(2, idx[..., None].expand(*idx.shape, t.shape[-1]))  # noqa: E731
    pts, pix = pick(h[:, :S, :, :3], ident), pick(h[:, :S, :, 3:], ident)
    now = torch.stack([torch.randperm(L, generator=g)[:C] for _ in range(B)])
    stamp = torch.tensor([[2, 0, 1], [-1, 0, 1]])
    valid = (stamp >= 0)[..., None].expand(B, S, P).clone()
    world = X.gather(1, ident.reshape(B, S * P)[..., None].expand(-1, -1, 3)).reshape(B, S, P, 3)
    return dict(T_world_cam=T_world_cam, X=X, K=K, T_cd=T_cd, ident=ident, pts=pts, pix=pix, now=now, stamp=stamp,
                valid=valid, world=world, h_now=h[:, S].gather(1, now[..., None].expand(-1, -1, 5)))  # fmt: skip


def _run(d, T_kf, T_now, world, world_now, has_xyz=None):
    B, S, P = d["ident"].shape
    one = torch.ones(B, S, dtype=F64)
    return refine_keyframes(T_kf, d["stamp"], d["ident"], d["pix"], d["pts"], d["valid"], world, one, 1e-4 * one,
                            T_now, d["now"], d["h_now"][..., 3:], d["h_now"][..., :3],
                            torch.ones_like(d["now"], dtype=torch.bool), world_now, torch.ones(B, dtype=F64),
                            1e-4 * torch.ones(B, dtype=F64), d["K"], d["T_cd"], has_xyz=has_xyz)  # fmt: skip


def test_exact_keyframes_are_recovered_around_the_oldest():
    d = _scene()
    B, S, P = d["ident"].shape
    g = torch.Generator().manual_seed(1)
    noise = lambda s, x: se3_exp(x * torch.randn(*s, 6, generator=g, dtype=F64))  # noqa: E731
    T_kf = noise((B, S), 0.01) @ d["T_world_cam"][:, :S]
    oldest = d["stamp"].clamp_min(0) == 0  # the gauge: stamp 0 is the oldest valid slot of both sequences
    T_kf = torch.where(oldest[..., None, None], d["T_world_cam"][:, :S], T_kf)
    T_now = noise((B,), 0.01) @ d["T_world_cam"][:, S]
    world = d["world"] + 0.01 * torch.randn(d["world"].shape, generator=g, dtype=F64)
    world_now = d["X"].gather(1, d["now"][..., None].expand(-1, -1, 3)) + 0.01
    has_xyz = torch.rand(B, S, P, generator=g) > 0.3  # some keyframe observations are pixels only
    out = _run(d, T_kf, T_now, world, world_now, has_xyz)
    assert bool(out.used.all()) and bool(out.inlier_now.all())
    torch.testing.assert_close(out.T_world_depth, d["T_world_cam"][:, S], rtol=0, atol=1e-9)
    ok = d["stamp"] >= 0
    torch.testing.assert_close(out.T_world_kf[ok], d["T_world_cam"][:, :S][ok], rtol=0, atol=1e-9)
    assert torch.equal(out.T_world_kf[~ok], T_kf[~ok])  # the empty slot is left alone
    truth = d["X"].gather(1, d["ident"].reshape(B, S * P)[..., None].expand(-1, -1, 3)).reshape(B, S, P, 3)
    seen = torch.stack([torch.bincount(torch.cat([d["ident"][b][ok[b]].reshape(-1), d["now"][b]]), minlength=12)
                        for b in range(B)])  # fmt: skip
    twice = (seen.gather(1, d["ident"].reshape(B, -1)) >= 2).reshape(B, S, P) & ok[..., None]
    torch.testing.assert_close(out.world_kf[twice], truth[twice], rtol=0, atol=1e-9)
    assert torch.equal(out.world_kf[~twice], world[~twice]) and (~twice).any()  # seen once: left as it was
    twice_now = seen.gather(1, d["now"]) >= 2
    X_now = d["X"].gather(1, d["now"][..., None].expand(-1, -1, 3))
    torch.testing.assert_close(out.world_now[twice_now], X_now[twice_now], rtol=0, atol=1e-9)
    assert torch.equal(out.world_now[~twice_now], world_now[~twice_now])


def test_batched_equals_looped():
    d = _scene(seed=3)
    B = 2
    g = torch.Generator().manual_seed(4)
    T_kf = se3_exp(0.01 * torch.randn(B, 3, 6, generator=g, dtype=F64)) @ d["T_world_cam"][:, :3]
    T_now = se3_exp(0.01 * torch.randn(B, 6, generator=g, dtype=F64)) @ d["T_world_cam"][:, 3]
    world_now = d["X"].gather(1, d["now"][..., None].expand(-1, -1, 3))
    out = _run(d, T_kf, T_now, d["world"], world_now)
    for b in range(B):
        db = {k: v[b : b + 1] for k, v in d.items()}
        one = _run(db, T_kf[b : b + 1], T_now[b : b + 1], d["world"][b : b + 1], world_now[b : b + 1])
        torch.testing.assert_close(one.T_world_depth[0], out.T_world_depth[b], rtol=0, atol=1e-12)
        torch.testing.assert_close(one.T_world_kf[0], out.T_world_kf[b], rtol=0, atol=1e-12)
        torch.testing.assert_close(one.world_kf[0], out.world_kf[b], rtol=0, atol=1e-12)


def test_camera_prior_fuses_with_the_windows_information():
    """``camera_info``: a prior on the current camera combines with what the window knows of it like two Gaussians.
    Exact keyframes and landmarks; the camera starts (and the prior is centred) 10 um / 10 urad off the truth. Without a
    prior the window lands on the truth; with the prior's information equal to the window's own marginal information
    of the camera (the inverse of its covariance block), on the midpoint ``exp(delta / 2) T_true`` (to first order:
    measured 3e-10 here, the bound 1e-8 against a 5e-6 half-offset; 3e-6 at 1 mm offsets, second order); with a
    1e12 x stronger prior, on its start."""
    from torchtrack.geometry import se3_log

    d = _scene()
    B, S, P = d["ident"].shape
    T_true = d["T_world_cam"][:, S]
    delta = torch.tensor([1e-5, -1e-5, 5e-6, 1e-5, 0.0, -1e-5], dtype=F64).expand(B, 6)
    T_cam0 = se3_exp(delta) @ T_inv(T_true)  # the window's left twist acts on world -> camera
    T_now = T_inv(T_cam0)
    world_now = d["X"].gather(1, d["now"][..., None].expand(-1, -1, 3))

    def run(info):
        one = torch.ones(B, S, dtype=F64)
        return refine_keyframes(d["T_world_cam"][:, :S], d["stamp"], d["ident"], d["pix"], d["pts"], d["valid"],
                                d["world"], one, 1e-4 * one, T_now, d["now"], d["h_now"][..., 3:], d["h_now"][..., :3],
                                torch.ones_like(d["now"], dtype=torch.bool), world_now, torch.ones(B, dtype=F64),
                                1e-4 * torch.ones(B, dtype=F64), d["K"], d["T_cd"], camera_info=info)  # fmt: skip

    free = run(None)
    torch.testing.assert_close(free.T_world_depth, T_true, rtol=0, atol=1e-9)
    marginal = torch.linalg.inv(free.result.cov_poses[:, S, S])
    half = run(marginal)
    twist = se3_log(T_inv(half.T_world_depth) @ T_true)  # the result's world -> camera is exp(twist) T_true^-1
    torch.testing.assert_close(twist, delta / 2, rtol=0, atol=1e-8)
    pinned = run(marginal * 1e12)
    torch.testing.assert_close(pinned.T_world_depth, T_now, rtol=0, atol=1e-9)
