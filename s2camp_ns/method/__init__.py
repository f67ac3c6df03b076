"""The ns-train methods' parts: models (nerfacto, splatfacto), pipeline, data manager, trainer, the camera's schedule
and the rays cast through the refined cameras."""
