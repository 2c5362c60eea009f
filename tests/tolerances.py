"""The one table of equivalence tolerances (STYLE.md item 8).

Two computations of one quantity that differ only in shape (batch size, chunking, padding, channels), thread count
or order run other kernels and sum in other orders, and which ones depends on the CPU (AVX-512, AVX2, none: torch's
``ATEN_CPU_CAPABILITY``). They agree within float error, not bit for bit. Each entry says where its size comes from
and what it still catches. The same computation run twice (determinism, resume, caching) is compared exactly.

The tests that use these are marked ``equivalence``; CI runs them again under ``ATEN_CPU_CAPABILITY=default`` and
``=avx2`` (``.ci/run``).
"""

from __future__ import annotations

# float32 quantities of order one (normalised cornerness, shape index, colour in [0, 1], points within ~10 m): a few
# stages of sums over windows of up to ~1e3 terms, each off by ~sqrt(n) eps (float32 eps 1.2e-7) in another order:
# ~100 eps. Mixing two images or sequences changes them by ~0.1 or more.
F32_UNIT = 1e-5

# float64 poses and states on unit-scale data (metres ~1, radians): a closed form or a contracting iteration (Horn,
# ICP, an EKF update), ~1e4 eps (2.2e-16). Another sequence's data moves a pose by their difference (~1e-2 here).
F64_UNIT = 1e-12

# LK end points (float32), pixels: coordinates up to ~500 px round at 2^-15 = 3e-5 px, and an iteration's window sums
# of ~400 products in another order move the step by ~1e-7 of its size; a few roundings: 1e-4 px, 3 ulps of a 500 px
# coordinate (measured: 4e-6 px on AVX2 and AVX-512, 8e-6 px with ATEN_CPU_CAPABILITY=default: one ulp of a ~100 px
# coordinate). A track that took another point's start or another image is off by pixels (a start one point off in
# test_chunks_track_as_one_call: 169 px).
LK_PX = 1e-4

# LK's mean |residual| (intensity in [0, 1]): end points within LK_PX over image gradients of <= ~0.1 per px.
LK_RESIDUAL = 1e-5

# d_TIM = |x - x'| of a forward and a backward track, each within LK_PX per coordinate: 2 sqrt(2) LK_PX.
TIM_PX = 3e-4

# Camera poses of a tracked trajectory (m, and rotation-matrix entries ~ rad), on short sequences: the front end's
# float32 differences (LK_PX per feature: ~4e-7 m at 2 m and f = 525 px, averaged over ~100 features) pass through
# the filter frame after frame. Measured, batch vs alone, AVX2 and default: <= 2e-7 on the synthetic tracker tests
# (6-24 frames), 1e-8 on 10 frames of visp_castle_simu; but 3e-6 on 20 frames of sun3d_fragment1 (LK on real images
# amplifies them, and a re-selection or LK stop decision that flips would not stay within this): keep real sequences
# at ~10 frames. A batch that mixes sequences' frames, features or filter states is off by their difference: mm to cm.
TRAJ = 1e-5

# The compiled LK operator (torchtrack/image/csrc/lk.cpp) vs the pure-torch reference: the same arithmetic
# in float32, but the window sums run in another order (8-wide FMA lanes vs torch's bmm), so a step differs by
# rounding and a track by ~LK_PX. Measured on 49,512 points of 5 real sequences (pairs 2 frames apart, 300 corners and
# 200 random points each, forward and backward; 39,744 tracked by both): median 0, 99 % within 1.2e-4 px, 99.9 % within
# 6.7e-4 px: hence LK_OP_PX. Beyond it: a stop decision (update <= eps = 0.01 px; a Newton step not halved) that
# flips on that rounding ends a track one update away (~eps; measured max 0.011 px), and on repetitive texture a flip
# at a coarse level can end in another minimum (an earlier build of the op, other roundings: once 49 px on
# visp_castle_simu). Such points and status flips are counted: 27 of 49,512 (6 status flips, 21 beyond LK_OP_PX;
# 9.3e-4 with the earlier build), so LK_OP_OUTLIERS = 5e-3 of the points may differ in status or beyond LK_OP_PX.
# A broken rule or a wrong window moves many points (a Newton rule of 1.0 instead of 0.25: 8 of 400 on real frames;
# gradients' 3/16 for 3/13: 288 of 400).
LK_OP_PX = 1e-3
LK_OP_OUTLIERS = 5e-3
# d_TIM of the op vs the reference: a forward and a backward track, each within LK_OP_PX per coordinate.
LK_OP_TIM = 3e-3

# The compiled SIM operator (torchtrack/image/csrc/sim.cpp) vs shape_index.py, whose smoothing is kornia's separable
# correlation: the same float32 stages, but the blur sums in another order (the op without FMA, kornia's convolution
# its own), and the curvatures' second derivatives of a smoothed surface amplify that rounding. Each is about as far from
# a float64 blur as the other (measured, SI: op 6.1e-3, kornia 3.8e-3 on the analytic sphere at full resolution; 5.8e-4
# and 6.9e-4 on sun3d_fragment1). Op vs reference, measured on the four analytic surfaces (full and half resolution) and
# two frames each of four real sequences: SI within 8.3e-3 where both are valid (the pipe at full resolution; <= 3.1e-3
# on real depth), mean 7.4e-4 (<= 8.2e-5 on real depth), validity flips 1.2e-4 of the pixels (7-Scenes), the 8-bit image
# one quantum (1/255) apart at 1.7e-2 of the pixels (the sphere at full resolution; <= 5.9e-3 on real depth). So
# SIM_OP_SI = 1e-2 (largest), SIM_OP_SI_MEAN = 1e-3, SIM_OP_FLIPS = 3e-4, SIM_OP_QUANTA = 3e-2. A wrong stage is caught:
# one blur pass more moves SI by 1.1e-2 on average on sun3d_fragment1 (0.17 at most) and flips 2.3e-2 of the pixels;
# a depth-step or support threshold 10 % off flips 2.2e-3 and 6.4e-3 of them.
SIM_OP_SI = 1e-2
SIM_OP_SI_MEAN = 1e-3
SIM_OP_FLIPS = 3e-4
SIM_OP_QUANTA = 3e-2

# The compiled dense alignment (torchtrack/map/csrc/dense.cpp) vs DenseMap._fit_torch (pure torch): both float64,
# the normal equations summed over a few thousand pairs in another order (~1e3 eps relative), a 6x6 solve and a few
# steps: measured within 8e-16 (corrections) on six 7-Scenes alignments and the room render. Culling and pairing are
# in float64 too, so a point flips only within ~1e-16 of a boundary. What the bounds still catch: one point more or
# less moves a step by 2e-6 to 1.3e-4 and the information by 4e-4 to 9e-4 of its largest entry (measured on the room
# render); a wrong weight or Jacobian by far more.
DENSE_OP_POSE = 1e-9  # correction entries (metres, rotation entries) and its twist
DENSE_OP_INFO = 1e-9  # the data's information, relative to its largest entry
DENSE_OP_PAIRS = 0.0  # pairs (fraction): the same points pair
# a keyframe's world points, metres: R p + t of a few-metre point in another summation order (and FMA) than torch's
# matmul, each of its ~6 roundings ~1.1e-16 relative
DEPTH_POINTS = 1e-14
