"""Our side of the CamP check: cameras and s2camp-camp's Gram matrices, written to an .npz (project venv).

Run from the repository root with the project's environment (see tools/camp_check/README.md):

    .venv/bin/python tools/camp_check/ours.py --out /tmp/camp_check/ours.npz

For every check camera (room intrinsics at 1/4 resolution and the 90 degree "wide" camera of
benchmarks/s2camp_bench/common.py, each at the identity pose and at a generic world pose) it writes

- the cameras (OpenCV c2w, fx, fy, cx, cy, W, H),
- Sigma of ``CAMP_SAMPLING`` (5000 points) for ``--seeds`` seeds and a ``--reference-points`` reference of the
  same measure, in a 13-column basis: our 12 parameters with the focal column split into its fx and fy parts.

The split is exact bookkeeping, not a new model: our focal delta is added to fx and fy, so its Jacobian column is the
sum of the fx and fy columns and our 12-parameter Sigma is ``A^T Sigma_13 A`` (checked here for every seed). CamP's
log focal scale moves fx and fy in proportion to themselves, which only the split basis can express exactly when
fx != fy.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from s2camp_bench.common import FRUSTA
from s2camp_ns.core.camera import Intrinsics, se3_exp, tangent_bounds
from s2camp_ns.core.camp_sampling import camp_frustum_points
from s2camp_ns.core.frustum import sample_frustum
from s2camp_ns.core.jacobian import gram_matrix, projection_jacobian
from s2camp_ns.core.preconditioner import CAMP_SAMPLING, compute_preconditioner

BASIS_13 = ("rho_x", "rho_y", "rho_z", "omega_x", "omega_y", "omega_z", "fx", "fy", "cx", "cy", "skew", "k1", "k2")
# Generic world pose (c2w = exp(xi)): rotation of about 0.6 rad, camera centre about 2.8 units from the origin.
GENERIC_POSE = torch.tensor([1.2, -0.7, 2.5, 0.3, -0.5, 0.2], dtype=torch.float64)


def check_cameras() -> list[dict]:
    identity = torch.eye(4, dtype=torch.float64)[:3]
    generic = se3_exp(GENERIC_POSE)
    cameras = []
    for frustum in ("room", "wide"):
        preset = FRUSTA[frustum]
        intrinsics = preset.intrinsics()
        for pose_name, c2w in (("identity", identity), ("generic", generic)):
            cameras.append({"name": f"{frustum}/{pose_name}", "intrinsics": intrinsics, "c2w": c2w})
    return cameras


def previous_points(intrinsics: Intrinsics, num_points: int, generator: torch.Generator) -> torch.Tensor:
    """The CamP re-implementation this check replaced: uniform random pixel (undistorted tangents) and uniform
    contracted distance in [0.4, 1.99] about the camera centre. Kept here only as the check's negative control."""
    draws = torch.rand((intrinsics.num_cameras, num_points, 3), generator=generator, dtype=torch.float64)
    return sample_frustum(draws[..., [2, 1, 0]], tangent_bounds(intrinsics), 0.4, 1.99, "pixel", "ray").camera


def split_focal(jacobian: torch.Tensor) -> torch.Tensor:
    """[n, l, 2, 12] -> [n, l, 2, 13]: the focal column (du/dfocal, dv/dfocal) becomes (du/dfx, 0), (0, dv/dfy)."""
    focal = jacobian[..., 6]
    fx = torch.stack([focal[..., 0], torch.zeros_like(focal[..., 0])], dim=-1)
    fy = torch.stack([torch.zeros_like(focal[..., 1]), focal[..., 1]], dim=-1)
    return torch.cat([jacobian[..., :6], fx[..., None], fy[..., None], jacobian[..., 7:]], dim=-1)


def gram_13(points: torch.Tensor, intrinsics: Intrinsics) -> tuple[torch.Tensor, torch.Tensor]:
    """Sum of J^T J (13 columns, pixels / max(W, H)) over in-image points, and their count."""
    _, jacobian, mask = projection_jacobian(points, intrinsics)
    sigma, count = gram_matrix(split_focal(jacobian), mask, intrinsics.image_scale())
    return sigma * count.to(sigma.dtype)[:, None, None], count


def sum_to_focal() -> torch.Tensor:
    """A (13 x 12): our 12 deltas in the split basis (focal adds to fx and fy)."""
    a = torch.zeros(13, 12, dtype=torch.float64)
    for i in range(6):
        a[i, i] = 1.0
    a[6, 6] = a[7, 6] = 1.0
    for i in range(7, 12):
        a[i + 1, i] = 1.0
    return a


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", type=int, default=16, help="5000-point estimates (seeds 0..N-1)")
    parser.add_argument("--reference-points", type=int, default=2**21)
    parser.add_argument("--chunk", type=int, default=2**16)
    parser.add_argument(
        "--previous", action="store_true", help="negative control: the replaced contracted-distance sampler"
    )
    args = parser.parse_args()

    def points_of(intrinsics: Intrinsics, size: int, generator: torch.Generator) -> torch.Tensor:
        if args.previous:
            return previous_points(intrinsics, size, generator)
        return camp_frustum_points(intrinsics, size, generator=generator)

    cameras = check_cameras()
    a = sum_to_focal()
    estimates, references = [], []
    for camera in cameras:
        intrinsics = camera["intrinsics"]
        per_seed = []
        for seed in range(args.seeds):
            sampling = replace(CAMP_SAMPLING, seed=seed)
            points = points_of(intrinsics, sampling.num_points, torch.Generator().manual_seed(seed))
            total, count = gram_13(points, intrinsics)
            sigma = (total / count.to(total.dtype)[:, None, None])[0]
            if not args.previous:
                # The 12-parameter Sigma that s2camp-camp's camera optimizer gets is this matrix in our basis.
                ours_12 = compute_preconditioner(intrinsics, sampling=sampling).gram[0]
                atol = 1e-12 * float(ours_12.abs().max())
                torch.testing.assert_close(a.T @ sigma @ a, ours_12, rtol=1e-9, atol=atol)
            per_seed.append(sigma)
        estimates.append(torch.stack(per_seed))
        generator = torch.Generator().manual_seed(987654321)
        total, count = 0.0, 0
        for start in range(0, args.reference_points, args.chunk):
            size = min(args.chunk, args.reference_points - start)
            points = points_of(intrinsics, size, generator)
            chunk_total, chunk_count = gram_13(points, intrinsics)
            total, count = total + chunk_total[0], count + int(chunk_count[0])
        references.append(total / count)
        print(f"ours: {camera['name']}: {args.seeds} x 5000-point estimates, reference of {count} points")

    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(
        args.out,
        names=np.array([c["name"] for c in cameras]),
        c2w=np.stack([c["c2w"].numpy() for c in cameras]),
        intrinsics=np.stack(
            [
                np.array(
                    [float(getattr(c["intrinsics"], field)[0]) for field in ("fx", "fy", "cx", "cy", "width", "height")]
                )
                for c in cameras
            ]
        ),
        basis=np.array(BASIS_13),
        estimates=torch.stack(estimates).numpy(),
        reference=torch.stack(references).numpy(),
        reference_points=args.reference_points,
        num_points=CAMP_SAMPLING.num_points,
        t_near=CAMP_SAMPLING.t_near,
        t_far=CAMP_SAMPLING.t_far,
        ladder_p=CAMP_SAMPLING.ladder_p,
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
