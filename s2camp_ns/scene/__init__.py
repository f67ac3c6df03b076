"""Synthetic scenes in the mip-NeRF 360 layout with known cameras (ground truth for camera refinement).

Entry point: ``s2camp_ns.scene.make_scene`` (``make_scene(MakeSceneConfig(...))`` or ``s2camp-make-scene``).
"""
