"""Windowed refinement: a batched, masked, robust Levenberg-Marquardt over K keyframe poses and P landmarks.

Unknowns of window b: K depth-camera poses ``T_cam_world`` (world -> depth camera), perturbed on the left
(``T <- exp(xi) T``, xi = (v, omega), :func:`~torchtrack.geometry.se3_exp`), and P landmark positions in the world.
The measurements are the filter's (eqs. 6-7): landmark p seen in keyframe k gives its 3D point in the depth camera
``X_d = R_k X_w + t_k`` (6) and its colour pixel ``pi(K (R_dv X_d + t_dv))`` (7), weighed by the per-feature
variances the filter uses (``var_xyz`` per coordinate, ``var_pix`` per pixel coordinate; eqs. 11-14 or the learned
weighting). Robust loss by iteratively reweighted least squares: Huber or Cauchy on each block's whitened norm (3D
point, pixel), its scale a chi-square quantile of the block's dof. After the robust iterations, ``polish_iters``
Gauss-Newton iterations on the inliers alone (a block is an inlier when its whitened squared norm passes the
``inlier_quantile`` test): exact data with planted outliers gives the exact answer.

Normal equations ``J^T W J dx = J^T W r`` are block-sparse: each landmark's block is 3x3, so the landmarks are
eliminated by the Schur complement and the reduced camera system (6K x 6K) is solved densely (Triggs et al.,
"Bundle Adjustment - A Modern Synthesis", 2000, §6.1). Levenberg-Marquardt damping: ``lambda diag(N)``, per window,
a step kept only when it lowers the robust cost.

Gauge: the first pose is fixed (``fix_first``), or the poses carry priors ``pose_prior_info`` (B, K, 6, 6) around their
starting values (residual ``log(T T0^-1)``, its Jacobian taken as the identity: exact at the start, first order
near it). Landmarks may carry priors ``point_prior_info`` (B, P, 3, 3) around their starting positions (their own
uncertainty). Covariance: the inverse of the Gauss-Newton normal matrix at the solution with the final weights
(the inliers', unit weight, after polishing), i.e. the Cramér-Rao bound of Gaussian measurements with those
variances; a fixed pose has zero covariance. Masks: a pose with ``pose_valid`` False and a landmark without any
valid measurement or prior are left where they are (zero covariance), and contribute nothing.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.config import WindowConfig
from torchtrack.filter.ekf import chi2_quantile
from torchtrack.geometry import T_inv, point_jacobian, se3_exp, se3_log

_LOSSES = ("huber", "cauchy", "l2")


class WindowResult(NamedTuple):
    """The refined window, batched over B.

    T_cam_world: (B, K, 4, 4) float64 refined depth-camera poses (world -> depth camera).
    points_world: (B, P, 3) float64 refined landmark positions.
    cov_poses: (B, K, K, 6, 6) joint covariance of the poses' left perturbations xi = (v, omega); zero for fixed poses.
    cov_points: (B, P, 3, 3) marginal covariance of each landmark (zero where it was left out).
    cov_pose_point: (B, K, P, 6, 3) cross-covariance of the poses and the landmarks.
    inlier_xyz, inlier_pix: (B, K, P) bool, the valid 3D / pixel measurements that pass the inlier test at the end.
    cost: (B,) final robust cost ``1/2 sum rho(|e|^2)`` of the whitened residual blocks (plus the priors').
    iterations: (B,) accepted LM steps.
    """

    T_cam_world: Tensor
    points_world: Tensor
    cov_poses: Tensor
    cov_points: Tensor
    cov_pose_point: Tensor
    inlier_xyz: Tensor
    inlier_pix: Tensor
    cost: Tensor
    iterations: Tensor


class Linearized(NamedTuple):
    """h (B, K, P, 5) = [X_d, pixel]; J_pose (B, K, P, 5, 6) = dh/dxi_k; J_point (B, K, P, 5, 3) = dh/dX_p."""

    h: Tensor
    J_pose: Tensor
    J_point: Tensor


def window_measure(T_cam_world: Tensor, points_world: Tensor, K: Tensor, T_color_depth: Tensor) -> Linearized:
    """Eqs. (6)-(7) of every landmark in every keyframe, with the closed-form Jacobians.

    ``X_d = R_k X_w + t_k``: ``dX_d/dxi = [I, -[X_d]x]`` (left perturbation), ``dX_d/dX_w = R_k``; pixel: ``u = A X_d +
    b`` with ``A = K R_dv``, ``pix = u[:2] / u[2]``, ``dpix/dX_d = (A[:2] - pix A[2]) / u[2]``.

    Args:
        T_cam_world: (B, K, 4, 4); points_world: (B, P, 3); K: (B, 3, 3) colour intrinsics; T_color_depth: (B, 4, 4).
    """
    R, t = T_cam_world[..., :3, :3], T_cam_world[..., :3, 3]
    X_d = torch.einsum("bkij,bpj->bkpi", R, points_world) + t[:, :, None]  # eq. (6)
    A = K @ T_color_depth[:, :3, :3]  # B,3,3
    u = torch.einsum("bij,bkpj->bkpi", A, X_d) + (K @ T_color_depth[:, :3, 3:])[:, None, None, :, 0]  # eq. (7)
    pix = u[..., :2] / u[..., 2:]
    dpix = (A[:, None, None, :2, :] - pix[..., None] * A[:, None, None, 2:, :]) / u[..., 2:, None]  # B,K,P,2,3
    dX_dxi = point_jacobian(X_d)  # B,K,P,3,6
    R_kp = R[:, :, None].expand(*dpix.shape[:3], 3, 3)
    J_pose = torch.cat([dX_dxi, dpix @ dX_dxi], -2)
    J_point = torch.cat([R_kp, dpix @ R_kp], -2)
    return Linearized(torch.cat([X_d, pix], -1), J_pose, J_point)


def _rho(e2: Tensor, loss: str, c: Tensor) -> tuple[Tensor, Tensor]:
    """(rho(e2), IRLS weight rho'(e2)) of squared whitened block norms e2 with scale c (in sigmas)."""
    if loss == "l2":
        return e2, torch.ones_like(e2)
    if loss == "huber":
        e = e2.clamp_min(1e-300).sqrt()
        inside = e <= c
        return torch.where(inside, e2, 2 * c * e - c * c), torch.where(inside, 1.0, c / e)
    return c * c * torch.log1p(e2 / (c * c)), 1.0 / (1.0 + e2 / (c * c))  # cauchy


class _Problem(NamedTuple):
    z: Tensor  # B,K,P,5
    w0: Tensor  # B,K,P,5 inverse variances, 0 where invalid
    K: Tensor
    T_cd: Tensor
    T0: Tensor
    X0: Tensor
    pose_info: Tensor | None
    point_info: Tensor | None
    pose_free: Tensor  # B,K
    point_free: Tensor  # B,P


def _evaluate(pb: _Problem, T: Tensor, X: Tensor, loss: str, scales: Tensor, use: Tensor, linearize: bool):
    """Robust cost (B,), per-component weights (B,K,P,5), residual r = z - h, squared block norms (B,K,P,2) and,
    with ``linearize``, the Jacobians. ``use`` (B,K,P,2): which blocks (3D, pixel) count."""
    lin = window_measure(T, X, pb.K, pb.T_cd) if linearize else None
    h = lin.h if linearize else window_measure(T, X, pb.K, pb.T_cd).h
    r = torch.where(pb.w0 > 0, pb.z - h, torch.zeros_like(h))
    wr2 = pb.w0 * r * r
    e2 = torch.stack([wr2[..., :3].sum(-1), wr2[..., 3:].sum(-1)], -1)  # B,K,P,2
    rho, wt = _rho(e2, loss, scales)
    rho, wt = torch.where(use, rho, 0.0), torch.where(use, wt, 0.0)
    cost = 0.5 * rho.sum((1, 2, 3))
    if pb.pose_info is not None:
        xi = se3_log(T @ T_inv(pb.T0))
        cost = cost + 0.5 * torch.einsum("bki,bkij,bkj->b", xi, pb.pose_info, xi)
    if pb.point_info is not None:
        dX = X - pb.X0
        cost = cost + 0.5 * torch.einsum("bpi,bpij,bpj->b", dX, pb.point_info, dX)
    w5 = pb.w0 * torch.cat([wt[..., :1].expand(-1, -1, -1, 3), wt[..., 1:].expand(-1, -1, -1, 2)], -1)
    return cost, w5, r, e2, lin


class _Normal(NamedTuple):
    U: Tensor  # B,K,6,6
    V: Tensor  # B,P,3,3
    W: Tensor  # B,K,P,6,3
    gc: Tensor  # B,K,6
    gp: Tensor  # B,P,3


def _normal(pb: _Problem, T: Tensor, X: Tensor, lin: Linearized, w5: Tensor, r: Tensor) -> _Normal:
    """Blocks of ``J^T W J`` and ``J^T W r`` (priors included); fixed poses and left-out landmarks decoupled (identity
    block, zero gradient)."""
    Jc, Jp = lin.J_pose, lin.J_point
    U = torch.einsum("bkpmi,bkpm,bkpmj->bkij", Jc, w5, Jc)
    V = torch.einsum("bkpmi,bkpm,bkpmj->bpij", Jp, w5, Jp)
    W = torch.einsum("bkpmi,bkpm,bkpmj->bkpij", Jc, w5, Jp)
    gc = torch.einsum("bkpmi,bkpm->bki", Jc, w5 * r)
    gp = torch.einsum("bkpmi,bkpm->bpi", Jp, w5 * r)
    if pb.pose_info is not None:
        U = U + pb.pose_info
        gc = gc - (pb.pose_info @ se3_log(T @ T_inv(pb.T0))[..., None])[..., 0]
    if pb.point_info is not None:
        V = V + pb.point_info
        gp = gp - (pb.point_info @ (X - pb.X0)[..., None])[..., 0]
    eye6, eye3 = torch.eye(6, dtype=U.dtype, device=U.device), torch.eye(3, dtype=U.dtype, device=U.device)
    fc, fp = _free(pb, w5)
    U = torch.where(fc[..., None, None], U, eye6)
    V = torch.where(fp[..., None, None], V, eye3)
    W = torch.where((fc[:, :, None] & fp[:, None, :])[..., None, None], W, 0.0)
    return _Normal(U, V, W, torch.where(fc[..., None], gc, 0.0), torch.where(fp[..., None], gp, 0.0))


def _free(pb: _Problem, w5: Tensor) -> tuple[Tensor, Tensor]:
    """Poses (B, K) and landmarks (B, P) that are estimated: free, with a used measurement or a prior."""
    used = w5 > 0  # B,K,P,5
    prior = pb.pose_info.abs().amax((-2, -1)) > 0 if pb.pose_info is not None else torch.zeros_like(pb.pose_free)
    fc = pb.pose_free & (used.any(-1).any(-1) | prior)  # a pose with a zero prior and no measurement stays put
    fp = pb.point_free & (used.any(-1).any(1) | (pb.point_info is not None))
    return fc, fp


def _reduced(n: _Normal, lam: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Reduced camera matrix S (B, 6K, 6K), V^-1 (B, P, 3, 3) and Y = W V^-1 (B, K, P, 6, 3), with the damping
    ``lam`` (B,) times the diagonal (Marquardt)."""
    B, K = n.U.shape[:2]
    U = n.U + lam[:, None, None, None] * torch.diag_embed(torch.diagonal(n.U, dim1=-2, dim2=-1))
    V = n.V + lam[:, None, None, None] * torch.diag_embed(torch.diagonal(n.V, dim1=-2, dim2=-1))
    Vinv = torch.linalg.inv(_floored(V))
    Y = n.W @ Vinv[:, None]
    eye = torch.eye(K, dtype=U.dtype, device=U.device)
    S = torch.einsum("kl,bkij->bkilj", eye, U) - torch.einsum("bkpij,blpmj->bkilm", Y, n.W)  # B,K,6,L,6
    return _floored(S.reshape(B, 6 * K, 6 * K)), Vinv, Y


def _floored(A: Tensor) -> Tensor:
    """``A + 1e-12 diag(A) + 1e-30 I`` (..., n, n): a landmark left with one pixel (its 3D point an outlier) or a pose
    seen along one ray is singular along it; the floor, 1e-12 of each unknown's own information, keeps the solve
    finite (that direction stays near its start, its variance ~1e12 times the others') and moves a well-posed answer
    by ~1e-12 of itself (independent of other unknowns, padding or priors)."""
    n = A.shape[-1]
    eye = torch.eye(n, dtype=A.dtype, device=A.device)
    return A + 1e-12 * torch.diag_embed(torch.diagonal(A, dim1=-2, dim2=-1)) + 1e-30 * eye


def _solve(n: _Normal, lam: Tensor) -> tuple[Tensor, Tensor]:
    """LM step (dxi (B, K, 6), dX (B, P, 3)) by the Schur complement on the landmarks."""
    B, K = n.U.shape[:2]
    S, Vinv, Y = _reduced(n, lam)
    rhs = n.gc - torch.einsum("bkpij,bpj->bki", Y, n.gp)
    dc = torch.linalg.solve(S, rhs.reshape(B, 6 * K)).reshape(B, K, 6)
    dp = (Vinv @ (n.gp - torch.einsum("bkpij,bki->bpj", n.W, dc))[..., None])[..., 0]
    return dc, dp


def refine_window(
    T_cam_world: Tensor,
    points_world: Tensor,
    points_cam: Tensor,
    pixels: Tensor,
    var_xyz: Tensor,
    var_pix: Tensor,
    valid_xyz: Tensor,
    valid_pix: Tensor,
    K: Tensor,
    T_color_depth: Tensor,
    *,
    pose_valid: Tensor | None = None,
    pose_prior_info: Tensor | None = None,
    point_prior_info: Tensor | None = None,
    iters: int = WindowConfig.iters,
    polish_iters: int = WindowConfig.polish_iters,
    loss: str = WindowConfig.loss,
    robust_quantile: float = WindowConfig.robust_quantile,
    inlier_quantile: float = WindowConfig.inlier_quantile,
    fix_first: bool = WindowConfig.fix_first,
    damping: float = WindowConfig.damping,
    tol: float = WindowConfig.tol,
) -> WindowResult:
    """Refine B windows of K keyframe poses and P landmarks jointly (module docstring: model, loss, gauge).

    Args:
        T_cam_world: (B, K, 4, 4) starting depth-camera poses (world -> depth camera); the first is the gauge.
        points_world: (B, P, 3) starting landmark positions in the world.
        points_cam: (B, K, P, 3) the landmarks' 3D points measured from depth in keyframe k (depth camera), eq. (6).
        pixels: (B, K, P, 2) their colour pixels in keyframe k, eq. (7).
        var_xyz, var_pix: (B, K, P) the filter's per-feature variances (m^2 per coordinate, px^2 per coordinate).
        valid_xyz, valid_pix: (B, K, P) bool, which measurements exist.
        K: (B, 3, 3) colour intrinsics; T_color_depth: (B, 4, 4) the depth-to-colour extrinsic.
        pose_valid: (B, K) bool, poses that take part (default all); the others are left as they are.
        pose_prior_info: (B, K, 6, 6) information of a prior on each pose's left perturbation around its start.
        point_prior_info: (B, P, 3, 3) information of a prior on each landmark around its start.
    """
    B, Kn, P = valid_xyz.shape
    if T_cam_world.shape != (B, Kn, 4, 4) or points_world.shape != (B, P, 3) or points_cam.shape != (B, Kn, P, 3):
        raise ValueError(f"refine_window: T_cam_world (B, K, 4, 4), points_world (B, P, 3), points_cam (B, K, P, 3) "
                         f"with valid (B, K, P) = {(B, Kn, P)}; got {tuple(T_cam_world.shape)}, "
                         f"{tuple(points_world.shape)}, {tuple(points_cam.shape)}")  # fmt: skip
    if pixels.shape != (B, Kn, P, 2) or var_xyz.shape != valid_xyz.shape or var_pix.shape != valid_pix.shape:
        raise ValueError("refine_window: pixels (B, K, P, 2), var_xyz / var_pix / valid_pix (B, K, P)")
    if loss not in _LOSSES:
        raise ValueError(f"refine_window: loss must be one of {_LOSSES}, got {loss!r}")
    f64 = dict(dtype=torch.float64, device=T_cam_world.device)
    T, X = T_cam_world.to(**f64), points_world.to(**f64)
    w0 = torch.cat([torch.where(valid_xyz, 1.0 / torch.where(valid_xyz, var_xyz, 1.0), 0.0)[..., None].expand(-1, -1, -1, 3),
                    torch.where(valid_pix, 1.0 / torch.where(valid_pix, var_pix, 1.0), 0.0)[..., None].expand(-1, -1, -1, 2)],
                   -1).to(**f64)  # fmt: skip
    z = torch.where(w0 > 0, torch.cat([points_cam, pixels], -1).to(**f64), 0.0)
    pose_free = torch.ones(B, Kn, dtype=torch.bool, device=T.device) if pose_valid is None else pose_valid.clone()
    if fix_first:
        pose_free[:, 0] = False
    elif pose_prior_info is None:
        raise ValueError("refine_window: without fix_first the poses need priors (pose_prior_info) for the gauge")
    seen = (valid_xyz | valid_pix) & pose_valid[..., None] if pose_valid is not None else valid_xyz | valid_pix
    point_free = seen.any(1) | (point_prior_info is not None)
    pb = _Problem(z, w0, K.to(**f64), T_color_depth.to(**f64), T.clone(), X.clone(),
                  None if pose_prior_info is None else pose_prior_info.to(**f64),
                  None if point_prior_info is None else point_prior_info.to(**f64), pose_free, point_free)  # fmt: skip
    obs = torch.stack([valid_xyz, valid_pix], -1)
    if pose_valid is not None:
        obs = obs & pose_valid[:, :, None, None]
    robust = torch.tensor(
        [math.sqrt(chi2_quantile(robust_quantile, 3)), math.sqrt(chi2_quantile(robust_quantile, 2))], **f64
    )
    gate = torch.tensor([chi2_quantile(inlier_quantile, 3), chi2_quantile(inlier_quantile, 2)], **f64)
    steps = torch.zeros(B, dtype=torch.long, device=T.device)
    T, X, steps = _lm(pb, T, X, loss, robust, obs, iters, damping, tol, steps)
    _, _, _, e2, _ = _evaluate(pb, T, X, "l2", robust, obs, False)
    inliers = obs & (e2 <= gate)
    if polish_iters > 0:
        T, X, steps = _lm(pb, T, X, "l2", robust, inliers, polish_iters, damping, tol, steps)
        _, _, _, e2, _ = _evaluate(pb, T, X, "l2", robust, obs, False)
        inliers = obs & (e2 <= gate)
        final_loss, final_use = "l2", inliers
    else:
        final_loss, final_use = loss, obs
    cost, w5, r, _, lin = _evaluate(pb, T, X, final_loss, robust, final_use, True)
    cov_c, cov_p, cov_cp = _covariance(_normal(pb, T, X, lin, w5, r), *_free(pb, w5))
    return WindowResult(T, X, cov_c, cov_p, cov_cp, inliers[..., 0], inliers[..., 1], cost, steps)


def _lm(pb, T, X, loss, robust, use, iters, damping, tol, steps):
    """``iters`` Levenberg-Marquardt iterations; a window stops once its step is below ``tol``."""
    B = T.shape[0]
    lam = torch.full((B,), damping, dtype=T.dtype, device=T.device)
    active = torch.ones(B, dtype=torch.bool, device=T.device)
    cost, w5, r, _, lin = _evaluate(pb, T, X, loss, robust, use, True)
    for _ in range(iters):
        if not bool(active.any()):
            break
        dc, dp = _solve(_normal(pb, T, X, lin, w5, r), lam)
        fc, fp = _free(pb, w5)
        dc, dp = torch.where(fc[..., None], dc, 0.0), torch.where(fp[..., None], dp, 0.0)
        T_new, X_new = se3_exp(dc) @ T, X + dp
        cost_new, w5_new, r_new, _, lin_new = _evaluate(pb, T_new, X_new, loss, robust, use, True)
        better = active & (cost_new <= cost)
        T = torch.where(better[:, None, None, None], T_new, T)
        X = torch.where(better[:, None, None], X_new, X)
        cost = torch.where(better, cost_new, cost)
        w5 = torch.where(better[:, None, None, None], w5_new, w5)
        r = torch.where(better[:, None, None, None], r_new, r)
        lin = Linearized(
            *(torch.where(better.view(B, *[1] * (a.dim() - 1)), a, b) for a, b in zip(lin_new, lin, strict=True))
        )
        steps = steps + better.long()
        lam = torch.where(better, lam / 10, lam * 10)
        size = torch.cat([dc.flatten(1), dp.flatten(1)], 1).abs().amax(1)
        active = active & ~(better & (size < tol)) & (lam < 1e12)
    return T, X, steps


def _covariance(n: _Normal, pose_free: Tensor, point_free: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The inverse of the undamped normal matrix in blocks: poses (B, K, K, 6, 6), landmarks' marginals (B, P, 3, 3),
    poses x landmarks (B, K, P, 6, 3). ``N^-1``'s pose block is ``S^-1`` (S the Schur complement), its landmark block
    ``V^-1 + Y^T S^-1 Y`` and the cross block ``-S^-1 Y`` (Y = W V^-1); fixed and left-out unknowns get zeros."""
    B, K = n.U.shape[:2]
    S, Vinv, Y = _reduced(n, torch.zeros(B, dtype=n.U.dtype, device=n.U.device))
    cov_c = torch.linalg.inv(S).reshape(B, K, 6, K, 6).permute(0, 1, 3, 2, 4)  # B,K,L,6,6
    free = pose_free[:, :, None] & pose_free[:, None, :]
    cov_c = torch.where(free[..., None, None], cov_c, 0.0)
    cov_cp = -torch.einsum("bklij,blpjm->bkpim", cov_c, Y)
    cov_p = Vinv + torch.einsum("bkpia,bklij,blpjc->bpac", Y, cov_c, Y)
    cov_p = torch.where(point_free[..., None, None], cov_p, 0.0)
    cov_cp = torch.where(point_free[:, None, :, None, None], cov_cp, 0.0)
    return cov_c, cov_p, cov_cp


class WindowRefiner:
    """Thin holder of :func:`refine_window`'s settings (:class:`~torchtrack.config.WindowConfig`)."""

    def __init__(
        self,
        *,
        iters: int = WindowConfig.iters,
        polish_iters: int = WindowConfig.polish_iters,
        loss: str = WindowConfig.loss,
        robust_quantile: float = WindowConfig.robust_quantile,
        inlier_quantile: float = WindowConfig.inlier_quantile,
        fix_first: bool = WindowConfig.fix_first,
        damping: float = WindowConfig.damping,
        tol: float = WindowConfig.tol,
    ) -> None:
        if loss not in _LOSSES or iters < 0 or polish_iters < 0:
            raise ValueError(f"WindowRefiner: loss in {_LOSSES}, iters >= 0; got {loss!r}, {iters}, {polish_iters}")
        self.kwargs = dict(iters=iters, polish_iters=polish_iters, loss=loss, robust_quantile=robust_quantile,
                           inlier_quantile=inlier_quantile, fix_first=fix_first, damping=damping, tol=tol)  # fmt: skip

    def __call__(self, *args, **kwargs) -> WindowResult:
        """:func:`refine_window` with these settings (keyword arguments given here win)."""
        return refine_window(*args, **{**self.kwargs, **kwargs})
