"""A copy of nerfstudio ``Cameras`` with some fields replaced (nerfstudio's Cameras has no such method)."""

from __future__ import annotations

from nerfstudio.cameras.cameras import Cameras


def replace_cameras(cameras: Cameras, **fields) -> Cameras:
    """A copy of ``cameras`` with the given fields replaced (nerfstudio's Cameras has no such method)."""
    values = dict(
        camera_to_worlds=cameras.camera_to_worlds,
        fx=cameras.fx,
        fy=cameras.fy,
        cx=cameras.cx,
        cy=cameras.cy,
        width=cameras.width,
        height=cameras.height,
        distortion_params=cameras.distortion_params,
        camera_type=cameras.camera_type,
        times=cameras.times,
        metadata=cameras.metadata,
    )
    values.update(fields)
    return Cameras(**values)


__all__ = ["replace_cameras"]
