"""Geometry: property tests (round trips, q == -q) and closed forms."""

import math

import pytest
import torch
from kornia.geometry.liegroup import Se3, So3
from tolerances import F64_UNIT

from torchtrack.geometry import (
    T_inv,
    backproject,
    backproject_depth,
    euler_to_matrix,
    hat,
    intrinsics_matrix,
    make_T,
    matrix_to_euler,
    matrix_to_quat_xyzw,
    point_jacobian,
    project,
    quat_xyzw_to_matrix,
    rigid,
    rotation_angle,
    sample_depth,
    sample_depth_bilinear,
    se3_exp,
    se3_log,
    so3_exp,
    so3_log,
    transform_points,
)

TOL = {torch.float32: 1e-5, torch.float64: 1e-10}


def random_axis_angle(n, max_angle=math.pi - 1e-3, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    axis = torch.randn(n, 3, generator=g, dtype=dtype)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    return axis * torch.rand(n, 1, generator=g, dtype=dtype) * max_angle


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_so3_exp_log_round_trip(dtype):
    w = random_axis_angle(200, dtype=dtype)
    R = so3_exp(w)
    assert R.shape == (200, 3, 3)
    eye = torch.eye(3, dtype=dtype).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, atol=TOL[dtype] * 10, rtol=0)
    torch.testing.assert_close(so3_log(R), w, atol=TOL[dtype] * 100, rtol=0)


def test_so3_and_se3_are_kornias():
    """so3_exp/so3_log and se3_exp/se3_log (hand-written for the filter's per-frame speed) equal kornia's So3 and Se3
    (quaternion based) on random rotations up to near pi and random twists, in float64."""
    w = random_axis_angle(200, dtype=torch.float64, seed=3)
    xi = torch.cat([torch.randn(200, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4)), w], -1)
    torch.testing.assert_close(so3_exp(w), So3.exp(w).matrix(), atol=F64_UNIT, rtol=0)
    torch.testing.assert_close(so3_log(so3_exp(w)), So3.exp(w).log(), atol=1e-9, rtol=0)  # a quaternion's log at pi
    torch.testing.assert_close(se3_exp(xi), Se3.exp(xi).matrix(), atol=F64_UNIT, rtol=0)
    torch.testing.assert_close(se3_log(se3_exp(xi)), Se3.exp(xi).log(), atol=1e-9, rtol=0)


def test_so3_log_near_pi_and_zero():
    for angle in [1e-9, 1e-5, math.pi - 1e-2, math.pi - 1e-6]:
        w = random_axis_angle(20, dtype=torch.float64, seed=1)
        w = w / w.norm(dim=-1, keepdim=True) * angle
        torch.testing.assert_close(so3_exp(so3_log(so3_exp(w))), so3_exp(w), atol=1e-9, rtol=0)


def test_so3_exp_closed_form_about_z():
    a = torch.tensor(0.3, dtype=torch.float64)
    R = so3_exp(torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64))
    expected = torch.tensor([[a.cos(), -a.sin(), 0], [a.sin(), a.cos(), 0], [0, 0, 1]], dtype=torch.float64)
    torch.testing.assert_close(R, expected)


def test_hat_is_cross_product():
    a, b = torch.randn(10, 3, dtype=torch.float64), torch.randn(10, 3, dtype=torch.float64)
    torch.testing.assert_close((hat(a) @ b[..., None])[..., 0], torch.linalg.cross(a, b))


def test_se3_round_trip_and_inverse():
    xi = torch.cat([torch.randn(100, 3, dtype=torch.float64), random_axis_angle(100)], dim=-1)
    T = se3_exp(xi)
    torch.testing.assert_close(se3_log(T), xi, atol=1e-8, rtol=0)
    torch.testing.assert_close(T @ T_inv(T), torch.eye(4, dtype=torch.float64).expand_as(T), atol=1e-12, rtol=0)
    p = torch.randn(100, 7, 3, dtype=torch.float64)
    back = transform_points(T_inv(T), transform_points(T, p))
    torch.testing.assert_close(back, p)


def test_se3_exp_is_the_matrix_exponential_of_the_twist():
    """The closed form (Rodrigues and the left Jacobian) against the matrix exponential of the twist's 4x4 matrix
    [[hat(omega), v], [0, 0]], from a tiny to a large rotation: equal within 1e-13."""
    g = torch.Generator().manual_seed(0)
    for scale in (1e-9, 1e-4, 0.05, 1.0, 3.0):
        xi = torch.randn(8, 6, generator=g, dtype=torch.float64) * scale
        twist = torch.zeros(8, 4, 4, dtype=torch.float64)
        twist[:, :3, :3], twist[:, :3, 3] = hat(xi[:, 3:]), xi[:, :3]
        torch.testing.assert_close(se3_exp(xi), torch.linalg.matrix_exp(twist), atol=1e-13, rtol=0)


def test_euler_convention_and_round_trip():
    angles = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    Rx = so3_exp(torch.tensor([0.1, 0, 0], dtype=torch.float64))
    Ry = so3_exp(torch.tensor([0, -0.2, 0], dtype=torch.float64))
    Rz = so3_exp(torch.tensor([0, 0, 0.3], dtype=torch.float64))
    torch.testing.assert_close(euler_to_matrix(angles), Rz @ Ry @ Rx)
    g = torch.Generator().manual_seed(3)
    a = (torch.rand(500, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor(
        [6.2, 3.1, 6.2], dtype=torch.float64
    )
    torch.testing.assert_close(matrix_to_euler(euler_to_matrix(a)), a, atol=1e-9, rtol=0)


def test_quaternion_round_trip_and_sign_invariance():
    R = so3_exp(random_axis_angle(300))
    q = matrix_to_quat_xyzw(R)
    assert (q[:, 3] >= 0).all()
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(300, dtype=torch.float64))
    torch.testing.assert_close(quat_xyzw_to_matrix(q), R, atol=1e-12, rtol=0)
    torch.testing.assert_close(quat_xyzw_to_matrix(-q), R, atol=1e-12, rtol=0)  # q == -q
    # closed form: 90 degrees about x is (sin45, 0, 0, cos45) in xyzw
    qx = matrix_to_quat_xyzw(so3_exp(torch.tensor([math.pi / 2, 0, 0], dtype=torch.float64)))
    torch.testing.assert_close(qx, torch.tensor([math.sqrt(0.5), 0, 0, math.sqrt(0.5)], dtype=torch.float64))
    with pytest.raises(ValueError, match="xyzw"):
        quat_xyzw_to_matrix(torch.zeros(3))


def test_quaternion_of_half_turns_and_unbatched_input():
    """Trace -1 (half turns: every branch of Shepperd's method) gives the axis itself as quaternion (w = 0, up to
    the sign), and a single (3, 3) matrix converts without a batch dimension, in float32 too."""
    axes = torch.tensor([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, -1, 1]], dtype=torch.float64)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    q = matrix_to_quat_xyzw(so3_exp(math.pi * axes))
    torch.testing.assert_close(q[:, 3], torch.zeros(5, dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close((q[:, :3] * axes).sum(-1).abs(), torch.ones(5, dtype=torch.float64))
    R = so3_exp(torch.tensor([0.3, -0.2, 0.1]))
    torch.testing.assert_close(quat_xyzw_to_matrix(matrix_to_quat_xyzw(R)), R)
    assert matrix_to_quat_xyzw(R).shape == (4,)


def test_rotation_angle_matches_axis_angle_norm():
    w = random_axis_angle(50)
    torch.testing.assert_close(rotation_angle(so3_exp(w)), w.norm(dim=-1), atol=1e-9, rtol=0)


def test_project_backproject_round_trip_and_depth_image():
    K = intrinsics_matrix(525.0, 520.0, 319.5, 239.5, dtype=torch.float64)[None].expand(2, 3, 3)
    pix = torch.rand(2, 50, 2, dtype=torch.float64) * torch.tensor([639.0, 479.0], dtype=torch.float64)
    z = 0.3 + 3 * torch.rand(2, 50, dtype=torch.float64)
    pts = backproject(K, pix, z)
    torch.testing.assert_close(project(K, pts), pix)
    depth = torch.full((2, 1, 4, 5), 2.0, dtype=torch.float64)
    img = backproject_depth(K, depth)
    assert img.shape == (2, 4, 5, 3)
    torch.testing.assert_close(
        img[0, 3, 4], torch.tensor([(4 - 319.5) / 525 * 2, (3 - 239.5) / 520 * 2, 2.0], dtype=torch.float64)
    )
    with pytest.raises(ValueError, match="depth must be"):
        backproject_depth(K, depth[:, 0])


def test_sample_depth_nearest_and_outside():
    depth = torch.arange(12, dtype=torch.float32).reshape(1, 1, 3, 4)
    pix = torch.tensor([[[1.2, 0.9], [3.0, 2.0], [-1.0, 0.0], [4.6, 1.0]]])
    torch.testing.assert_close(sample_depth(depth, pix), torch.tensor([[5.0, 11.0, 0.0, 0.0]]))


def test_make_T_layout():
    R = so3_exp(torch.tensor([0.1, 0.2, 0.3]))
    T = make_T(R, torch.tensor([1.0, 2.0, 3.0]))
    assert T.shape == (4, 4) and T[3].tolist() == [0, 0, 0, 1]


def test_warp_depth_identity_and_known_shift():
    from torchtrack.geometry import warp_depth

    K = intrinsics_matrix(500.0, 500.0, 15.5, 11.5)[None]
    depth = torch.full((1, 1, 24, 32), 2.0)
    depth[..., 5:9, 5:9] = 1.0  # a nearer square
    eye = torch.eye(4)[None]
    torch.testing.assert_close(warp_depth(depth, K, K, eye, (24, 32)), depth)
    # translating the camera by tx = -fx^-1 * 2 px * z shifts the far plane by exactly 2 px to the left
    T = make_T(torch.eye(3), torch.tensor([-2.0 * 2.0 / 500.0, 0.0, 0.0]))[None]
    out = warp_depth(depth, K, K, T, (24, 32))
    torch.testing.assert_close(out[..., :, 12:28], depth[..., :, 14:30])
    assert (out[..., :, 30:] == 0).all()  # nothing lands there


def test_sample_depth_bilinear_on_a_plane_and_nearest_across_edges():
    from torchtrack.geometry import sample_depth_bilinear

    ys, xs = torch.meshgrid(torch.arange(6.0), torch.arange(8.0), indexing="ij")
    depth = (1.0 + 0.01 * xs + 0.002 * ys)[None, None]  # a slanted plane: bilinear is exact
    pix = torch.tensor([[[2.3, 1.6], [5.75, 4.1], [0.0, 0.0]]])
    expected = 1.0 + 0.01 * pix[..., 0] + 0.002 * pix[..., 1]
    torch.testing.assert_close(sample_depth_bilinear(depth, pix), expected)
    depth[..., :, 4:] = 3.0  # a depth edge between x = 3 and x = 4: nearest pixel, nothing in between
    z = sample_depth_bilinear(depth, torch.tensor([[[3.4, 2.0], [3.6, 2.0]]]))
    torch.testing.assert_close(z, torch.tensor([[1.0 + 0.03 + 0.004, 3.0]]))


def test_depth_along_rays_meets_a_slanted_plane_seen_by_another_camera():
    """A depth camera 10 cm to the side and turned by 3 degrees, with its own intrinsics, sees a slanted plane; each
    colour pixel's ray meets the plane at a depth known in closed form. The ray intersection finds it to 1e-6 of the
    depth from the forward warp's start (which is off by up to 2.5e-4 from its nearest-pixel resampling); a ray that
    leaves the depth image, or meets a hole, gets no depth."""
    from torchtrack.geometry import depth_along_rays, warp_depth

    dt = torch.float64
    K = intrinsics_matrix(525.0, 525.0, 159.5, 119.5, dtype=dt)[None]
    Kd = intrinsics_matrix(570.0, 568.0, 162.0, 117.0, dtype=dt)[None]
    T_cd = make_T(
        so3_exp(torch.tensor([0.0, math.radians(3.0), 0.0], dtype=dt)), torch.tensor([-0.10, 0.0, 0.0], dtype=dt)
    )
    n, d = torch.tensor([0.2, -0.1, 1.0], dtype=dt), 1.5  # the plane n . X = d in the colour camera
    # the depth image: each depth pixel's ray meets the plane, in the depth camera's frame
    ys, xs = torch.meshgrid(torch.arange(240.0, dtype=dt), torch.arange(320.0, dtype=dt), indexing="ij")
    ray_d = backproject(Kd[0], torch.stack([xs, ys], -1).reshape(1, -1, 2), torch.ones(1, 240 * 320, dtype=dt))
    R, t = T_cd[:3, :3], T_cd[:3, 3]  # colour <- depth
    z_d = (d - n @ t) / (ray_d @ R.T @ n)
    depth = z_d.reshape(1, 1, 240, 320)
    depth[..., 100:110, 150:160] = 0.0  # a hole
    g = torch.Generator().manual_seed(0)
    pixels = torch.rand(1, 200, 2, generator=g, dtype=dt) * torch.tensor([300.0, 220.0], dtype=dt) + 10.0
    pixels = torch.cat([pixels, torch.tensor([[[319.0, 5.0]]], dtype=dt)], 1)  # its ray leaves the depth image
    ray_c = backproject(K[0], pixels, torch.ones(1, pixels.shape[1], dtype=dt))
    exact = d / (ray_c @ n)
    warped = warp_depth(depth, Kd, K, T_cd[None], (240, 320))
    z0 = sample_depth_bilinear(warped, pixels)
    z = depth_along_rays(depth, Kd, K, T_cd[None], pixels, z0)
    hole = (z0 > 0) & (z == 0)
    good = (z > 0)[0]
    assert int(good.sum()) >= 180 and int(hole.sum()) <= 12 and not bool(good[-1])
    err = ((z - exact).abs() / exact)[0][good]
    warp_err = ((z0 - exact).abs() / exact)[0][good]  # measured: 2.5e-4 at most, 1.1e-4 RMS
    assert float(err.max()) < 1e-6 and float(warp_err.max()) > 1e-4  # measured: 2.5e-8 (float64, 4 steps)


def test_point_jacobian_is_the_derivative_of_the_exponential_at_zero():
    """point_jacobian(p) = d(exp(xi) p)/dxi at xi = 0, against autograd through se3_exp."""
    p = torch.tensor([[0.3, -1.2, 2.5], [1.0, 0.5, -0.7]], dtype=torch.float64)
    for q in p:
        auto = torch.func.jacfwd(lambda xi, q=q: transform_points(se3_exp(xi), q[None])[0])(
            torch.zeros(6, dtype=torch.float64)
        )
        torch.testing.assert_close(point_jacobian(q), auto, atol=1e-12, rtol=0)
    assert point_jacobian(p).shape == (2, 3, 6)


def test_rigid_is_the_polar_factor():
    """``rigid``: a rotation times a symmetric positive definite matrix (its polar decomposition) gives the rotation
    back exactly (to round-off), the translation kept; a rigid transform is unchanged; a reflection becomes a proper
    rotation."""
    g = torch.Generator().manual_seed(0)
    R = so3_exp(torch.randn(5, 3, generator=g, dtype=torch.float64))
    A = torch.randn(5, 3, 3, generator=g, dtype=torch.float64) * 1e-3
    S = torch.eye(3, dtype=torch.float64) + A + A.transpose(-1, -2)  # symmetric, positive definite
    t = torch.randn(5, 3, generator=g, dtype=torch.float64)
    out = rigid(make_T(R @ S, t))
    assert torch.allclose(out[:, :3, :3], R, atol=1e-12) and torch.equal(out[:, :3, 3], t)
    T = make_T(R, t)
    assert torch.allclose(rigid(T), T, atol=1e-14)
    mirror = rigid(make_T(R @ torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)), t))[:, :3, :3]
    assert torch.allclose(torch.linalg.det(mirror), torch.ones(5, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(
        mirror.transpose(-1, -2) @ mirror, torch.eye(3, dtype=torch.float64).expand(5, 3, 3), atol=1e-12
    )


@pytest.mark.equivalence
def test_rigid_flips_the_smallest_direction_and_passes_non_finite_rows():
    """A reflection with distinct singular values, ``R diag(3, 2, -1)``: the nearest rotation flips the direction of
    the smallest one and is R (flipping another column would not be); a transform with a NaN is returned as given
    and the others of the batch are projected alone (batched equals one by one within F64_UNIT)."""
    g = torch.Generator().manual_seed(1)
    R = so3_exp(torch.randn(3, 3, generator=g, dtype=torch.float64))
    t = torch.randn(3, 3, generator=g, dtype=torch.float64)
    D = torch.diag(torch.tensor([3.0, 2.0, -1.0], dtype=torch.float64))
    T = make_T(R @ D, t)
    T[1, 0, 0] = float("nan")
    out = rigid(T)
    assert torch.allclose(out[[0, 2], :3, :3], R[[0, 2]], atol=1e-12)
    assert torch.equal(out[1].isnan(), T[1].isnan()) and torch.equal(out[1].nan_to_num(), T[1].nan_to_num())
    for b in (0, 2):
        torch.testing.assert_close(rigid(T[b]), out[b], rtol=0, atol=F64_UNIT)  # one SVD alone vs in a batch
    with pytest.raises(ValueError, match="rigid"):
        rigid(torch.eye(3))
