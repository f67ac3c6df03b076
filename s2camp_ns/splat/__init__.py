"""3D Gaussian Splatting support in torch alone: refined intrinsics as a view matrix (``intrinsics_view``) and a
pure-torch rasterization with gsplat's contract (``reference_rasterizer``)."""
