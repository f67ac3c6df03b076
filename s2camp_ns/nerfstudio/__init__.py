"""nerfstudio integration of S2CamP: camera optimizer, data manager, model and pipeline."""
