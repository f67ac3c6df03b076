"""3D Gaussian Splatting support, framework-agnostic (torch only, no nerfstudio import).

- ``s2camp_ns.splat.intrinsics_view``: refined intrinsics through a rasterizer that takes only a view matrix
  gradient (K' = K A, view matrix [[A R, A t], [0, 1]]; docs/SPLAT.md).
- ``s2camp_ns.splat.reference_rasterizer``: a dense pure-torch rasterization with the contract of gsplat's
  ``rasterization`` for the subset splatfacto uses (CPU path, tests).
"""
