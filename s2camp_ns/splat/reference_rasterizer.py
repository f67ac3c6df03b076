"""Pure-torch 3D Gaussian rasterization with the contract of gsplat 1.4's ``rasterization`` (the subset splatfacto
uses), for the CPU: dense, slow, differentiable by autograd. It computes:

1. Projection (pinhole): x = R m + t, covariances R Sigma R^T with Sigma = (Q S)(Q S)^T; depth z = x_z;
   means2d = K x / z (skew included).
2. EWA: Sigma_2d = J Sigma_cam J^T, J's columns K_2x2 / z and -(u_c - c) / z, u_c the projected mean clamped to
   [-0.15 W, 1.15 W] x [-0.15 H, 1.15 H] (gsplat's field-of-view clamp).
3. Blur: Sigma_2d + eps2d I; ``rasterize_mode="antialiased"`` scales the opacities by
   sqrt(det Sigma_2d / det(Sigma_2d + eps2d I)).
4. Culling: valid when det > 0 and near <= z <= far; radius = ceil(3 sqrt(lambda_max)), lambda_max =
   b + sqrt(max(0.01, b^2 - det)), b the mean of the diagonal; 0 (not rendered) when <= radius_clip or off-image.
5. Colours: raw [N, D] / [C, N, D], or SH coefficients [N, (deg+1)^2, 3] evaluated toward the mean, + 0.5, >= 0.
6. Compositing per 16 x 16 tile, front to back, at pixel centres: alpha = min(0.999, o exp(-q)),
   q = 0.5 d^T Sigma_2d^-1 d, skipped when q < 0 or alpha < 1/255, stopping before T would reach 1e-4; colour
   sum_i c_i alpha_i T_i (+ T background), alpha 1 - T.

``info`` holds what splatfacto and gsplat's ``DefaultStrategy`` read (non-packed): ``means2d`` [C, N, 2] (non-leaf,
with ``means2d.absgrad`` after backward when ``absgrad``), ``radii`` [C, N] int32, ``depths``, ``conics``,
``opacities``, ``width``, ``height``, ``n_cameras``, ``tile_size``. ValueError for ``packed=True``, ``sparse_grad``,
camera models other than pinhole and render modes other than RGB / D / ED / RGB+D / RGB+ED.
"""

from __future__ import annotations

import math

import torch
from jaxtyping import Float, Int
from torch import Tensor

ALPHA_MAX = 0.999
"""Largest alpha of one Gaussian at one pixel (gsplat's cap)."""
ALPHA_MIN = 1.0 / 255.0
"""Smaller alphas are skipped."""
TRANSMITTANCE_MIN = 1e-4
"""A pixel stops before the Gaussian that would take its transmittance to this or below."""
CLAMP_MARGIN = 0.3
"""gsplat's field-of-view clamp margin (tan(fov / 2) units): 0.15 image sizes outside the image."""
RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
    1.445305721320277, -0.5900435899266435,
)  # fmt: skip
SH_C4 = (
    2.5033429417967046, -1.7701307697799304, 0.9461746957575601, -0.6690465435572892, 0.10578554691520431,
    -0.6690465435572892, 0.47308734787878004, -1.7701307697799304, 0.6258357354491761,
)  # fmt: skip


def spherical_harmonics(
    degree: int, directions: Float[Tensor, "*batch 3"], coefficients: Float[Tensor, "*batch k 3"]
) -> Float[Tensor, "*batch 3"]:
    """Real spherical harmonics of degree <= 4 (3DGS signs) at the normalized ``directions``, weighted by the first
    (degree + 1)^2 ``coefficients``."""
    if not 0 <= degree <= 4:
        raise ValueError(f"sh_degree must be in [0, 4], got {degree}")
    needed = (degree + 1) ** 2
    if coefficients.shape[-2] < needed:
        raise ValueError(f"SH degree {degree} needs {needed} coefficients per colour, got {coefficients.shape[-2]}")
    c = coefficients
    result = SH_C0 * c[..., 0, :]
    if degree == 0:
        return result
    d = directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    x, y, z = d[..., 0:1], d[..., 1:2], d[..., 2:3]
    result = result + SH_C1 * (-y * c[..., 1, :] + z * c[..., 2, :] - x * c[..., 3, :])
    if degree == 1:
        return result
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    basis2 = (xy, yz, 2.0 * zz - xx - yy, xz, xx - yy)
    for i, (const, value) in enumerate(zip(SH_C2, basis2, strict=True)):
        result = result + const * value * c[..., 4 + i, :]
    if degree == 2:
        return result
    basis3 = (
        y * (3.0 * xx - yy),
        xy * z,
        y * (4.0 * zz - xx - yy),
        z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
        x * (4.0 * zz - xx - yy),
        z * (xx - yy),
        x * (xx - 3.0 * yy),
    )
    for i, (const, value) in enumerate(zip(SH_C3, basis3, strict=True)):
        result = result + const * value * c[..., 9 + i, :]
    if degree == 3:
        return result
    basis4 = (
        xy * (xx - yy),
        yz * (3.0 * xx - yy),
        xy * (7.0 * zz - 1.0),
        yz * (7.0 * zz - 3.0),
        zz * (35.0 * zz - 30.0) + 3.0,
        xz * (7.0 * zz - 3.0),
        (xx - yy) * (7.0 * zz - 1.0),
        xz * (xx - 3.0 * yy),
        xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy),
    )
    for i, (const, value) in enumerate(zip(SH_C4, basis4, strict=True)):
        result = result + const * value * c[..., 16 + i, :]
    return result


def quaternion_to_rotation(quats: Float[Tensor, "n 4"]) -> Float[Tensor, "n 3 3"]:
    """Rotation matrices of quaternions (w, x, y, z), normalized first."""
    w, x, y, z = (quats / quats.norm(dim=-1, keepdim=True)).unbind(dim=-1)
    rows = [
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], dim=-1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], dim=-1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1),
    ]
    return torch.stack(rows, dim=-2)


def covariances_from(quats: Float[Tensor, "n 4"], scales: Float[Tensor, "n 3"]) -> Float[Tensor, "n 3 3"]:
    """World covariances Sigma = (Q S)(Q S)^T."""
    m = quaternion_to_rotation(quats) * scales[:, None, :]
    return m @ m.transpose(-1, -2)


def project_gaussians(
    means: Float[Tensor, "n 3"],
    covariances: Float[Tensor, "n 3 3"],
    viewmats: Float[Tensor, "c 4 4"],
    Ks: Float[Tensor, "c 3 3"],
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
) -> dict[str, Tensor]:
    """Steps 1-4 for C cameras: ``means2d`` [C, N, 2], ``depths`` [C, N], ``covars2d`` (blurred) [C, N, 2, 2],
    ``conics`` [C, N, 3] (upper triangle of the inverse), ``compensations`` [C, N], ``radii`` [C, N] (int32)."""
    rotation = viewmats[:, None, :3, :3]
    means_cam = (rotation @ means[None, :, :, None])[..., 0] + viewmats[:, None, :3, 3]
    covars_cam = rotation @ covariances[None] @ rotation.transpose(-1, -2)
    depths = means_cam[..., 2]
    k2 = Ks[:, None, :2, :2]
    principal = Ks[:, None, :2, 2]
    # gsplat's lim_x = (W - cx) / fx + 0.3 * 0.5 W / fx is u = 1.15 W (lim_-x: u = -0.15 W) for a skew-free K.
    tangents = means_cam[..., :2] / depths[..., None]
    means2d = (k2 @ tangents[..., None])[..., 0] + principal
    # The clamp's own copy: ``means2d``'s gradient must hold the compositing's part only (as gsplat's).
    size = torch.tensor([float(width), float(height)], dtype=means2d.dtype, device=means2d.device)
    margin = 0.5 * CLAMP_MARGIN * size
    unclamped = (k2 @ tangents[..., None])[..., 0] + principal
    clamped = torch.minimum(torch.maximum(unclamped, -margin), size + margin)
    inv_z = 1.0 / depths[..., None, None]
    jacobian = torch.cat([k2 * inv_z, -(clamped - principal)[..., None] * inv_z], dim=-1)
    covars2d = jacobian @ covars_cam @ jacobian.transpose(-1, -2)
    det_raw = covars2d[..., 0, 0] * covars2d[..., 1, 1] - covars2d[..., 0, 1] * covars2d[..., 1, 0]
    covars2d = covars2d + eps2d * torch.eye(2, dtype=covars2d.dtype, device=covars2d.device)
    a, b, c = covars2d[..., 0, 0], 0.5 * (covars2d[..., 0, 1] + covars2d[..., 1, 0]), covars2d[..., 1, 1]
    det = a * c - b * b
    compensations = torch.sqrt((det_raw / det).clamp_min(0.0))
    valid = (det > 0) & (depths >= near_plane) & (depths <= far_plane)
    safe_det = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / safe_det, -b / safe_det, a / safe_det], dim=-1)
    with torch.no_grad():
        half_trace = 0.5 * (a + c)
        largest = half_trace + torch.sqrt((half_trace * half_trace - det).clamp_min(0.01))
        radii = torch.ceil(3.0 * torch.sqrt(largest.clamp_min(0.0)))
        valid = valid & (radii > radius_clip)
        inside = (
            (means2d[..., 0] + radii > 0)
            & (means2d[..., 0] - radii < width)
            & (means2d[..., 1] + radii > 0)
            & (means2d[..., 1] - radii < height)
        )
        radii = torch.where(valid & inside, radii, torch.zeros_like(radii)).to(torch.int32)
    return dict(
        means2d=means2d, depths=depths, covars2d=covars2d, conics=conics, compensations=compensations, radii=radii
    )


class _PixelOffsets(torch.autograd.Function):
    """d = mean2d - pixel [p, n, 2]; backward adds the per-pixel absolute gradients, summed, to ``record``."""

    @staticmethod
    def forward(ctx, means2d: Tensor, pixels: Tensor, record: dict) -> Tensor:
        ctx.record = record
        return means2d[None, :, :] - pixels[:, None, :]

    @staticmethod
    def backward(ctx, grad: Tensor):
        ctx.record["absgrad"] = ctx.record.get("absgrad", 0) + grad.abs().sum(dim=0)
        return grad.sum(dim=0), None, None


def composite_tile(
    offsets_means2d: Float[Tensor, "n 2"],
    conics: Float[Tensor, "n 3"],
    opacities: Float[Tensor, " n"],
    features: Float[Tensor, "n d"],
    pixels: Float[Tensor, "p 2"],
    record: dict | None = None,
) -> tuple[Float[Tensor, "p d"], Float[Tensor, " p"]]:
    """Step 6 for ``n`` Gaussians in depth order at ``pixels``: accumulated features [p, d], final T [p]."""
    if record is None:
        d = offsets_means2d[None, :, :] - pixels[:, None, :]
    else:
        d = _PixelOffsets.apply(offsets_means2d, pixels, record)
    dx, dy = d[..., 0], d[..., 1]
    sigma = 0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) + conics[:, 1] * dx * dy
    alpha = torch.clamp_max(opacities * torch.exp(-sigma), ALPHA_MAX)
    alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
    # T after each Gaussian, prod_{j <= i} (1 - alpha_j), as exp of a cumsum (finite: alpha <= 0.999).
    log_after = torch.cumsum(torch.log1p(-alpha), dim=1)
    after = torch.exp(log_after)
    before = torch.exp(log_after - torch.log1p(-alpha))
    # T only decreases: stopping before the first Gaussian that takes it to <= 1e-4 keeps those with T after > 1e-4.
    keep = (after > TRANSMITTANCE_MIN).to(alpha.dtype)
    weights = alpha * before * keep
    transmittance = torch.exp(torch.log1p(-alpha * keep).sum(dim=1))
    return weights @ features, transmittance


def _check_arguments(
    unsupported: dict, packed: bool, sparse_grad: bool, camera_model: str, render_mode: str, rasterize_mode: str
) -> None:
    """ValueError for arguments outside the subset of gsplat's ``rasterization`` covered here."""
    if unsupported:
        raise ValueError(f"reference rasterization does not support the argument(s) {sorted(unsupported)}")
    if packed:
        raise ValueError("reference rasterization: packed=True is not supported (splatfacto passes packed=False)")
    if sparse_grad:
        raise ValueError("reference rasterization: sparse_grad=True is not supported")
    if camera_model != "pinhole":
        raise ValueError(f"reference rasterization: camera_model {camera_model!r} is not supported; allowed: 'pinhole'")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if rasterize_mode not in ("classic", "antialiased"):
        raise ValueError(f"rasterize_mode must be 'classic' or 'antialiased', got {rasterize_mode!r}")


def _features(
    means: Float[Tensor, "n 3"],
    colors: Tensor,
    viewmats: Float[Tensor, "c 4 4"],
    projected: dict[str, Tensor],
    sh_degree: int | None,
    render_mode: str,
) -> Float[Tensor, "c n d"]:
    """Channels to composite [C, N, D]: the colour (RGB modes; SH evaluated toward the camera, 0 when culled), then
    the depth (depth modes)."""
    c = viewmats.shape[0]
    features = []
    if render_mode in ("RGB", "RGB+D", "RGB+ED"):
        if sh_degree is None:
            rgb = colors if colors.dim() == 3 else colors[None].expand(c, *colors.shape)
        else:
            campos = torch.linalg.inv(viewmats)[:, :3, 3]
            directions = means[None] - campos[:, None]
            coefficients = colors if colors.dim() == 4 else colors[None].expand(c, *colors.shape)
            rgb = spherical_harmonics(sh_degree, directions, coefficients)
            rgb = torch.where((projected["radii"] > 0)[..., None], rgb, torch.zeros_like(rgb))
            rgb = torch.clamp_min(rgb + 0.5, 0.0)
        features.append(rgb)
    if render_mode != "RGB":
        features.append(projected["depths"][..., None])
    return torch.cat(features, dim=-1)


def _sorted_tile_bounds(
    means2d: Float[Tensor, "n 2"],
    radius: Float[Tensor, " n"],
    depths: Float[Tensor, " n"],
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
) -> tuple[Int[Tensor, " m"], Float[Tensor, "m 2"], Float[Tensor, "m 2"]]:
    """Visible Gaussians (radius > 0) front to back (stable) and the tile range [min, max) in x, y each covers."""
    with torch.no_grad():
        order = torch.argsort(depths, stable=True)
        order = order[radius[order] > 0]
        centre = means2d[order].detach() / tile_size
        extent = (radius[order] / tile_size)[:, None]
        upper = torch.tensor([tiles_x, tiles_y], dtype=centre.dtype, device=centre.device)
        tile_min = torch.minimum(torch.floor(centre - extent).clamp_min(0), upper)
        tile_max = torch.minimum(torch.ceil(centre + extent).clamp_min(0), upper)
    return order, tile_min, tile_max


def _render_camera(
    projected: dict[str, Tensor],
    opacities_cam: Float[Tensor, "c n"],
    features: Float[Tensor, "c n d"],
    camera: int,
    width: int,
    height: int,
    tile_size: int,
    camera_record: dict | None,
) -> tuple[Float[Tensor, "h w d"], Float[Tensor, "h w"]]:
    """Composited channels [h, w, d] and alpha [h, w] of camera ``camera``, tile by tile; with ``camera_record``,
    each tile's Gaussian ids and record are appended to its "tiles" (``_attach_absgrad``)."""
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    means2d = projected["means2d"][camera]
    radius = projected["radii"][camera].to(means2d.dtype)
    order, tile_min, tile_max = _sorted_tile_bounds(
        means2d, radius, projected["depths"][camera], tile_size, tiles_x, tiles_y
    )
    image = means2d.new_zeros(height, width, features.shape[-1])
    alpha_image = means2d.new_zeros(height, width)
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            hits = (tile_min[:, 0] <= tx) & (tx < tile_max[:, 0]) & (tile_min[:, 1] <= ty) & (ty < tile_max[:, 1])
            x0, y0 = tx * tile_size, ty * tile_size
            x1, y1 = min(x0 + tile_size, width), min(y0 + tile_size, height)
            ids = order[hits]
            if ids.numel() == 0:
                continue
            ys, xs = torch.meshgrid(
                torch.arange(y0, y1, dtype=means2d.dtype, device=means2d.device),
                torch.arange(x0, x1, dtype=means2d.dtype, device=means2d.device),
                indexing="ij",
            )
            pixels = torch.stack([xs + 0.5, ys + 0.5], dim=-1).reshape(-1, 2)
            if camera_record is not None:
                tile_record: dict = {}
                camera_record.setdefault("tiles", []).append((ids, tile_record))
            else:
                tile_record = None
            colour, transmittance = composite_tile(
                means2d[ids],
                projected["conics"][camera][ids],
                opacities_cam[camera][ids],
                features[camera][ids],
                pixels,
                tile_record,
            )
            image = image.index_put((ys.reshape(-1).long(), xs.reshape(-1).long()), colour)
            alpha_image = alpha_image.index_put((ys.reshape(-1).long(), xs.reshape(-1).long()), 1.0 - transmittance)
    return image, alpha_image


def _over_background(
    render_colors: Float[Tensor, "c h w d"],
    render_alphas: Float[Tensor, "c h w 1"],
    backgrounds: Tensor | None,
    render_mode: str,
) -> Float[Tensor, "c h w d"]:
    """The channels over ``backgrounds`` (depth over 0), the expected depth (ED modes) divided by the alpha."""
    c = render_colors.shape[0]
    if backgrounds is not None:
        if render_mode != "RGB":  # gsplat pads the backgrounds with 0 for the depth
            depth_background = backgrounds.new_zeros(c, 1)
            if render_mode in ("D", "ED"):
                backgrounds = depth_background
            else:
                backgrounds = torch.cat([backgrounds, depth_background], dim=-1)
        render_colors = render_colors + (1.0 - render_alphas) * backgrounds[:, None, None, :]
    if render_mode in ("ED", "RGB+ED"):
        expected = render_colors[..., -1:] / render_alphas.clamp_min(1e-10)
        render_colors = torch.cat([render_colors[..., :-1], expected], dim=-1)
    return render_colors


def rasterization(
    means: Float[Tensor, "n 3"],
    quats: Float[Tensor, "n 4"],
    scales: Float[Tensor, "n 3"],
    opacities: Float[Tensor, " n"],
    colors: Tensor,
    viewmats: Float[Tensor, "c 4 4"],
    Ks: Float[Tensor, "c 3 3"],
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    packed: bool = False,
    tile_size: int = 16,
    backgrounds: Tensor | None = None,
    render_mode: str = "RGB",
    sparse_grad: bool = False,
    absgrad: bool = False,
    rasterize_mode: str = "classic",
    camera_model: str = "pinhole",
    **unsupported,
) -> tuple[Float[Tensor, "c h w d"], Float[Tensor, "c h w 1"], dict]:
    """gsplat 1.4's ``rasterization`` (module docstring): render_colors [C, H, W, D] (colour channels, + 1 with
    depth), render_alphas [C, H, W, 1], info."""
    _check_arguments(unsupported, packed, sparse_grad, camera_model, render_mode, rasterize_mode)
    n = means.shape[0]
    c = viewmats.shape[0]
    projected = project_gaussians(
        means, covariances_from(quats, scales), viewmats, Ks, width, height, eps2d, near_plane, far_plane, radius_clip
    )
    radii = projected["radii"]
    opacities_cam = opacities[None].expand(c, n)
    if rasterize_mode == "antialiased":
        opacities_cam = opacities_cam * projected["compensations"]
    features = _features(means, colors, viewmats, projected, sh_degree, render_mode)
    record: dict = {}
    images, alphas = [], []
    for camera in range(c):
        camera_record = record.setdefault(camera, {}) if absgrad else None
        image, alpha_image = _render_camera(
            projected, opacities_cam, features, camera, width, height, tile_size, camera_record
        )
        images.append(image)
        alphas.append(alpha_image[..., None])
    render_alphas = torch.stack(alphas)
    render_colors = _over_background(torch.stack(images), render_alphas, backgrounds, render_mode)
    info = {
        "means2d": projected["means2d"],
        "depths": projected["depths"],
        "conics": projected["conics"],
        "radii": radii,
        "opacities": opacities_cam,
        "compensations": projected["compensations"],
        "width": width,
        "height": height,
        "tile_size": tile_size,
        "tile_width": math.ceil(width / tile_size),
        "tile_height": math.ceil(height / tile_size),
        "n_cameras": c,
        "camera_ids": None,
        "gaussian_ids": None,
    }
    if absgrad:
        _attach_absgrad(projected["means2d"], record, n)
    return render_colors, render_alphas, info


def _attach_absgrad(means2d: Tensor, record: dict, n: int) -> None:
    """After backward, ``means2d.absgrad`` [C, N, 2]: the per-pixel absolute gradients summed, from every tile."""

    def gather(grad: Tensor) -> Tensor:
        absgrad = torch.zeros_like(grad)
        for camera, camera_record in record.items():
            for ids, tile_record in camera_record.get("tiles", []):
                if "absgrad" in tile_record:
                    absgrad[camera].index_add_(0, ids, tile_record["absgrad"])
        means2d.absgrad = absgrad
        return grad

    if means2d.requires_grad:
        means2d.register_hook(gather)


__all__ = [
    "ALPHA_MAX", "ALPHA_MIN", "TRANSMITTANCE_MIN", "composite_tile", "covariances_from", "project_gaussians",
    "quaternion_to_rotation", "rasterization", "spherical_harmonics",
]  # fmt: skip
