"""Synthetic scenes in the mip-NeRF 360 layout with known cameras (``make_scene``, ``s2camp-make-scene``)."""
