"""Well-posed random rigid motions and point sets shared by the estimator tests (Horn, ICP, CPD)."""

import torch

from torchtrack.geometry import make_T, so3_exp


def random_T(B, dtype=torch.float64, max_angle=0.2, max_trans=0.03, seed=0):
    """Rotations from axis-angle up to ``max_angle`` rad and translations up to ``max_trans`` m
    (defaults: inter-frame motions of ~11 degrees and 3 cm, for the local methods ICP and CPD)."""
    g = torch.Generator().manual_seed(seed)
    axis = torch.randn(B, 3, generator=g, dtype=torch.float64)
    omega = axis / axis.norm(dim=-1, keepdim=True) * torch.rand(B, 1, generator=g, dtype=torch.float64) * max_angle
    t = (torch.rand(B, 3, generator=g, dtype=torch.float64) * 2 - 1) * max_trans
    return make_T(so3_exp(omega), t).to(dtype)


def random_cloud(B, N, dtype=torch.float64, spread=0.1, seed=1):
    """An object of ~spread metres at ~1 m in front of the camera (depth >= 0.3 m)."""
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(B, N, 3, generator=g, dtype=torch.float64) * spread
    return (p + torch.tensor([0.05, -0.02, 1.0], dtype=torch.float64)).to(dtype)


def eye(B, dtype=torch.float64):
    return torch.eye(4, dtype=dtype).expand(B, 4, 4).clone()


def ones(B, N):
    return torch.ones(B, N, dtype=torch.bool)


def registration_args(B=2, N=5, M=7):
    """Well-formed keyword arguments of a registration (src, dst, their masks, T_init), for bad-input tests."""
    return dict(
        src=torch.zeros(B, N, 3),
        dst=torch.zeros(B, M, 3),
        valid_src=torch.ones(B, N, dtype=torch.bool),
        valid_dst=torch.ones(B, M, dtype=torch.bool),
        T_init=torch.eye(4).expand(B, 4, 4),
    )
