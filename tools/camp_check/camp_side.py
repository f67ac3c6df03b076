"""CamP's side of the check: CamP's own ``compute_approximate_hessian`` on our cameras (scratch venv with JAX).

Run with a separate environment that has CamP's dependencies, never the project's (see tools/camp_check/README.md):

    /tmp/camp-venv/bin/python tools/camp_check/camp_side.py --camp-repo /path/to/camp_zipnerf \
        --cameras /tmp/camp_check/ours.npz --out /tmp/camp_check/camp.npz

Nothing of CamP is copied or re-implemented here. The modules of ``camp_zipnerf/internal`` are imported from the
given checkout (as a package of their own, so that its ``__init__`` does not pull in the NeRF model, datasets and
TensorFlow, which the camera code does not use); CamP's published camera-optimisation configuration is read by gin
from ``configs/camp/camera_optim.gin`` of the same checkout; the camera-delta class is the one that file selects.
This script only builds jaxcam cameras from ours.npz, calls CamP's methods and writes:

- ``published``: J^T J exactly as CamP's training initialises it (``init`` of the camera delta, PRNGKey(0)),
- ``estimates``: CamP's ``compute_approximate_hessian`` with its configured 5000 points for seeds 0..N-1,
- ``reference``: the mean of ``compute_approximate_hessian`` over many chunks of points (``--reference-points``),
- ``mapping``: d(our 13 split-basis deltas)/d(CamP's flattened parameters) at zero, through CamP's own
  ``transform_camera``: rho = R (C' - C), omega = vee of the antisymmetric part of R R'^T (R world-to-camera,
  C camera centre; our c2w' = c2w exp(xi)), fx, fy, cx, cy, skew, k1, k2 of the transformed camera.
"""

from __future__ import annotations

import argparse
import importlib
import re
import subprocess
import sys
import types
from pathlib import Path

import gin
import jax
import jax.flatten_util
import jax.numpy as jnp
import jaxcam
import numpy as np
from jax import random


def load_camera_delta(repo: Path):
    internal = repo / "camp_zipnerf" / "internal"
    if not (internal / "camera_delta.py").is_file():
        raise SystemExit(f"--camp-repo: no camp_zipnerf/internal/camera_delta.py under {repo}")
    package = types.ModuleType("camp_internal")
    package.__path__ = [str(internal)]
    sys.modules["camp_internal"] = package
    return importlib.import_module("camp_internal.camera_delta")


def published_delta_class(camera_delta, gin_file: Path):
    match = re.search(r"^Config\.camera_delta_cls\s*=\s*@camera_delta\.(\w+)", gin_file.read_text(), re.MULTILINE)
    if match is None:
        raise SystemExit(f"{gin_file} does not set Config.camera_delta_cls")
    return getattr(camera_delta, match.group(1))


def make_cameras(data) -> jaxcam.Camera:
    c2w = np.asarray(data["c2w"], dtype=np.float64)
    fx, fy, cx, cy, width, height = np.asarray(data["intrinsics"], dtype=np.float64).T
    orientation = np.transpose(c2w[:, :3, :3], (0, 2, 1))  # jaxcam: world-to-camera rotation, OpenCV axes
    return jaxcam.Camera.create(
        orientation=orientation,
        position=c2w[:, :3, 3],
        focal_length=fx,
        principal_point=np.stack([cx, cy], axis=-1),
        image_size=np.stack([width, height], axis=-1),
        skew=np.zeros_like(fx),
        pixel_aspect_ratio=fy / fx,
    )


def _git_head(repo: Path) -> str:
    try:
        result = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True)
    except OSError:
        return "unknown"
    return result.stdout.strip() if result.returncode == 0 else "unknown"


def vee_antisymmetric(a: jnp.ndarray) -> jnp.ndarray:
    w = 0.5 * (a - a.T)
    return jnp.stack([w[2, 1], w[0, 2], w[1, 0]])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--camp-repo", type=Path, required=True, help="checkout of jonbarron/camp_zipnerf")
    parser.add_argument("--cameras", type=Path, required=True, help="ours.npz written by tools/camp_check/ours.py")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", type=int, default=16)
    parser.add_argument("--reference-points", type=int, default=2_000_000)
    parser.add_argument("--chunk", type=int, default=100_000)
    parser.add_argument("--camp-commit", default=None, help="commit of the checkout (default: git rev-parse HEAD)")
    args = parser.parse_args()
    commit = args.camp_commit or _git_head(args.camp_repo)

    camera_delta = load_camera_delta(args.camp_repo)
    gin_file = args.camp_repo / "configs" / "camp" / "camera_optim.gin"
    # Only the camera-delta configurables are registered here; the NeRF model's bindings are skipped.
    gin.parse_config_files_and_bindings([str(gin_file)], bindings=[], skip_unknown=True)
    delta_class = published_delta_class(camera_delta, gin_file)
    delta = delta_class()
    settings = {
        name: getattr(delta, name)
        for name in (
            "use_precondition",
            "precondition_num_points",
            "precondition_point_sample_method",
            "precondition_near",
            "precondition_far",
            "precondition_raydist_fn_kwargs",
            "precondition_diagonal_absolute_padding",
            "precondition_diagonal_relative_padding_scale",
            "precondition_use_full_matrix",
            "precondition_normalize_eigvals",
            "precondition_running_estimate",
            "precondition_momentum",
            "use_log_scales",
            "scale_pixel_units_to_metric_units",
            "use_principal_point",
            "use_radial_distortion",
            "num_radial_distortion_coeffs",
        )
    }
    settings["precondition_raydist_fn"] = delta.precondition_raydist_fn.__name__
    print(f"CamP {delta_class.__name__} from {gin_file}:")
    for name, value in settings.items():
        print(f"  {name} = {value!r}")

    data = np.load(args.cameras)
    cameras = make_cameras(data)
    variables = delta.init({"params": random.PRNGKey(0)}, cameras)
    published = np.asarray(variables["precondition"]["jtj"])
    params = variables["params"]
    single = jax.tree_util.tree_map(lambda x: x[0], params)
    flat, unflatten = jax.flatten_util.ravel_pytree(single)
    names = []
    for key in sorted(single):  # ravel_pytree flattens dict entries in sorted key order
        size = int(np.size(single[key]))
        names += [key] if size == 1 else [f"{key}[{i}]" for i in range(size)]
    assert len(names) == flat.size, (names, flat.size)

    def hessian(module, key):
        return np.asarray(module.apply(variables, params, cameras, key, method=module.compute_approximate_hessian))

    estimates = np.stack([hessian(delta, random.PRNGKey(seed)) for seed in range(args.seeds)], axis=1)
    big = delta_class(precondition_num_points=args.chunk)
    chunks = max(1, args.reference_points // args.chunk)
    reference = sum(hessian(big, random.PRNGKey(100_000 + k)).astype(np.float64) for k in range(chunks)) / chunks
    print(f"CamP: {args.seeds} x {delta.precondition_num_points}-point estimates, reference {chunks} x {args.chunk}")

    def ours_from_camp(theta, camera):
        moved = delta.apply(variables, unflatten(theta), camera, method=delta.transform_camera)
        rho = camera.orientation @ (moved.position - camera.position)
        omega = vee_antisymmetric(camera.orientation @ moved.orientation.T)
        intrinsic = jnp.stack(
            [
                moved.focal_length,
                moved.focal_length * moved.pixel_aspect_ratio,
                moved.principal_point[0],
                moved.principal_point[1],
                moved.skew,
                moved.radial_distortion[0],
                moved.radial_distortion[1],
            ]
        )
        return jnp.concatenate([rho, omega, intrinsic])

    mapping = np.stack([np.asarray(jax.jacfwd(ours_from_camp)(jnp.zeros_like(flat), cam)) for cam in cameras])
    for array, label in ((published, "published"), (estimates, "estimates"), (reference, "reference")):
        if not np.isfinite(array).all():
            print(f"warning: CamP's {label} J^T J has non-finite entries")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(
        args.out,
        names=data["names"],
        params=np.array(names),
        published=published,
        estimates=estimates,
        reference=reference,
        reference_points=chunks * args.chunk,
        mapping=mapping,
        settings=np.array(repr(settings)),
        delta_class=np.array(delta_class.__name__),
        camp_commit=np.array(commit),
        jax_version=jax.__version__,
        jaxcam_version=getattr(jaxcam, "__version__", "unknown"),
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
