"""S2CamP for nerfstudio: deterministic frustum sampling for camera-parameter preconditioning."""

__version__ = "0.1.0"
