"""The COLMAP feature database of an image-track build (``image_tracks``): opened and closed, its images numbered
before SIFT, and the given cameras under the ids it holds."""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Iterator
from pathlib import Path

import pycolmap


def names_by_camera(given: pycolmap.Reconstruction) -> dict[int, list[str]]:
    """``given``'s image names per camera id, both sorted: the order one extraction thread numbers them in."""
    by_camera: dict[int, list[str]] = {}
    for image in sorted(given.images.values(), key=lambda image: image.name):
        by_camera.setdefault(image.camera_id, []).append(image.name)
    return dict(sorted(by_camera.items()))


@contextlib.contextmanager
def open_database(database: Path) -> Iterator[pycolmap.Database]:
    """The COLMAP database ``database``, closed when the block ends."""
    db = pycolmap.Database.open(database)
    try:
        yield db
    finally:
        db.close()


def number_images(given: pycolmap.Reconstruction, database: Path) -> None:
    """Write ``given``'s cameras (one rig each, a prior focal length) and images (one frame each) into the empty
    ``database`` in ``names_by_camera`` order before SIFT, which on several threads would number images in the order
    they finish."""
    with open_database(database) as db:
        for camera_id, names in names_by_camera(given).items():
            camera = copy.copy(given.cameras[camera_id])
            camera.has_prior_focal_length = True
            stored = db.read_camera(db.write_camera(camera))
            rig = pycolmap.Rig()
            rig.add_ref_sensor(stored.sensor_id)
            rig_id = db.write_rig(rig)
            for name in names:
                image_id = db.write_image(pycolmap.Image(name=name, camera_id=stored.camera_id))
                frame = pycolmap.Frame()
                frame.rig_id = rig_id
                frame.add_data_id(db.read_image(image_id).data_id)
                db.write_frame(frame)


def given_with_database_ids(given: pycolmap.Reconstruction, database: Path) -> pycolmap.Reconstruction:
    """``given``'s cameras and poses under their ids in ``database`` (COLMAP's triangulator matches by id), without
    the images SIFT could not read."""
    with open_database(database) as db:
        stored = {image.name: image for image in db.read_all_images() if db.exists_keypoints(image.image_id)}
    given_by_name = {image.name: image for image in given.images.values()}
    reconstruction = pycolmap.Reconstruction()
    added: set[int] = set()
    for name, stored_image in sorted(stored.items(), key=lambda item: item[1].image_id):
        image = given_by_name[name]
        if stored_image.camera_id not in added:
            camera = copy.copy(given.cameras[image.camera_id])
            camera.camera_id = stored_image.camera_id
            reconstruction.add_camera_with_trivial_rig(camera)
            added.add(stored_image.camera_id)
        posed = pycolmap.Image(name=name, camera_id=stored_image.camera_id, image_id=stored_image.image_id)
        reconstruction.add_image_with_trivial_frame(posed, image.cam_from_world())
    return reconstruction


__all__ = ["given_with_database_ids", "names_by_camera", "number_images", "open_database"]
