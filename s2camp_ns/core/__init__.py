"""Framework-agnostic PyTorch core of S2CamP (imports no nerfstudio; usable from 3DGS and other pipelines).

Typical use::

    from s2camp_ns.core import Intrinsics, compute_preconditioner
    intrinsics = Intrinsics.create(fx=793.1, fy=793.5, cx=389.2, cy=259.4, width=778, height=518)
    pre = compute_preconditioner(intrinsics)           # 500 Frolov-lattice points per camera, the paper's 12 parameters
    phi = pre.inverse @ phi_hat                         # camera deltas from whitened parameters (paper eq. 15)
"""

from s2camp_ns.core.camera import (
    CAMERA_MODEL_DISTORTION,
    NUM_CAMERA_PARAMS,
    PARAMETER_GROUPS,
    PARAMETER_NAMES,
    Intrinsics,
    ParameterLayout,
    pixel_to_ray_direction,
    project,
    project_with_delta,
    se3_exp,
    tangent_bounds,
    unproject,
)
from s2camp_ns.core.colmap_camera_models import SUPPORTED_COLMAP_MODELS, intrinsics_from_colmap
from s2camp_ns.core.jacobian import gram_matrix, projection_jacobian, relative_gram_error
from s2camp_ns.core.preconditioner import (
    DampingConfig,
    Preconditioner,
    SamplingConfig,
    compute_preconditioner,
    condition_number,
    sample_proxy_points,
    symmetric_sqrt_and_inverse,
    whitening_error,
)

__all__ = [
    "CAMERA_MODEL_DISTORTION", "SUPPORTED_COLMAP_MODELS", "NUM_CAMERA_PARAMS", "PARAMETER_GROUPS", "PARAMETER_NAMES",
    "DampingConfig", "Intrinsics", "ParameterLayout", "Preconditioner", "SamplingConfig", "compute_preconditioner",
    "condition_number", "gram_matrix", "intrinsics_from_colmap", "pixel_to_ray_direction", "project",
    "project_with_delta", "projection_jacobian", "relative_gram_error", "sample_proxy_points", "se3_exp",
    "symmetric_sqrt_and_inverse", "tangent_bounds", "unproject", "whitening_error",
]  # fmt: skip
