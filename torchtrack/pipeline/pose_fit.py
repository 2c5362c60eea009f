"""The camera pose re-fitted to re-acquired landmarks (``landmarks.correct``): robust Gauss-Newton on world points
seen at pixels and measured in depth, the paper's two measurements per feature (eqs. 6-7) on a static pose."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.geometry import point_jacobian, se3_exp, transform_points


class PoseFit(NamedTuple):
    """T_color_world (B, 4, 4) float64; inliers (B, C): within ``inlier`` of the normalised residual at the end."""

    T_color_world: Tensor
    inliers: Tensor


def refine_pose(K: Tensor, T_color_world: Tensor, world: Tensor, pixels: Tensor, measured: Tensor, valid: Tensor, *,
                sigma_px: float = 1.0, sigma_m: float = 0.02, huber: float = 2.0, inlier: float = 3.0,
                iters: int = 8) -> PoseFit:  # fmt: skip
    """Gauss-Newton on the camera pose from world points seen at colour pixels, with their measured 3D points: the
    reprojection residual (px / ``sigma_px``) and the 3D residual (m / ``sigma_m`` max(1, z^2)), Huber-weighted per
    point, like the paper's 5 measurements per feature (eqs. 6-7) on a static pose. The pixel term fixes the pose
    where the keyframe's depth is noisy: along the ray a depth error barely moves a projection.

    Args:
        K: (B, 3, 3) colour intrinsics; T_color_world: (B, 4, 4) the starting pose (world -> colour camera).
        world: (B, C, 3) points in the world; pixels: (B, C, 2) where they are seen; measured: (B, C, 3) their
            points measured from depth, in the colour camera; valid: (B, C).
    Linearised at the current estimate each iteration (left perturbation ``exp(xi) T``, xi = (v, omega)).
    """
    T = T_color_world.double()
    K, world, measured, pixels = K.double(), world.double(), measured.double(), pixels.double()
    fx, fy, cx, cy = K[:, 0, 0, None], K[:, 1, 1, None], K[:, 0, 2, None], K[:, 1, 2, None]
    w = valid.double()
    eye = torch.eye(6, dtype=torch.float64, device=T.device)
    for i in range(iters + 1):
        p = transform_points(T, world)  # B,C,3
        px, py, pz = p.unbind(-1)
        z = pz.clamp_min(1e-3)
        r2 = torch.stack([fx * px / z + cx - pixels[..., 0], fy * py / z + cy - pixels[..., 1]], -1) / sigma_px
        sig3 = sigma_m * z.square().clamp_min(1.0)
        r3 = (p - measured) / sig3[..., None]
        err = torch.linalg.vector_norm(torch.cat([r2, r3], -1), dim=-1)
        if i == iters:
            break
        # the pixel rows of J: Jp [I, -[p]x] / sigma_px, Jp = [[a, 0, b], [0, c, d]] the projection's derivative,
        # written out (tiny batched matmuls are slow); the 3D rows: [I, -[p]x] / sig3
        a, b, c, d = fx / z, -fx * px / z**2, fy / z, -fy * py / z**2
        zero = torch.zeros_like(z)
        J2 = torch.stack([a, zero, b, b * py, a * pz - b * px, -a * py,
                          zero, c, d, d * py - c * pz, -d * px, c * px], -1).view(*z.shape, 2, 6) / sigma_px  # fmt: skip
        J3 = point_jacobian(p) / sig3[..., None, None]  # B,C,3,6
        hw = torch.where(err <= huber, 1.0, huber / err.clamp_min(1e-12)) * w
        H2, g2 = _normal_equations(J2, r2, hw)
        H3, g3 = _normal_equations(J3, r3, hw)
        T = se3_exp(-torch.linalg.solve(H2 + H3 + 1e-6 * eye, g2 + g3)) @ T
    return PoseFit(T, valid & (err <= inlier))


def _normal_equations(J: Tensor, r: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """sum_c w_c J_c^T J_c (B, 6, 6) and sum_c w_c J_c^T r_c (B, 6) of J (B, C, k, 6), r (B, C, k), w (B, C)."""
    Jw = (J * w[..., None, None]).flatten(1, 2).mT  # B,6,Ck
    return Jw @ J.flatten(1, 2), (Jw @ r.flatten(1, 2)[..., None])[..., 0]
