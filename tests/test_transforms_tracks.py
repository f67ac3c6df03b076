"""The track prior's scale for ``ns-process-data`` scenes: a transforms.json beside ``colmap/sparse/0``
(``s2camp_ns.tracks.transforms_tracks``). Each scene is laid out from the session's generated scene by
nerfstudio's own ``colmap_to_json``, as ``ns-process-data`` writes it."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest
import torch

from s2camp_ns.data.dataparser import S2CampDataParserConfig


def _ns_process_data_layout(scene: Path, data: Path, keep_original_world_coordinate: bool = False) -> Path:
    """``data/{images, images_2, colmap/sparse/0, transforms.json}`` of the generated ``scene``; the json's path."""
    from nerfstudio.process_data.colmap_utils import colmap_to_json

    for folder in ("images", "images_2"):
        shutil.copytree(scene / folder, data / folder)
    model = data / "colmap" / "sparse" / "0"
    shutil.copytree(scene / "sparse" / "0", model)
    colmap_to_json(model, data, keep_original_world_coordinate=keep_original_world_coordinate)
    return data / "transforms.json"


def _parse(data: Path, split: str = "train", **options):
    """The data parser's outputs of ``split``; keypoints not refined unless asked: the generated tracks are exact, and
    refining them against the images would move them by the refinement's own error."""
    options.setdefault("refine_keypoints", False)
    return S2CampDataParserConfig(data=data, **options).setup().get_dataparser_outputs(split)


def perturbed_with_scene_tracks(data: Path, **options):
    """The data parser's training outputs with the cameras moved by CamP's perturbation (seed 0) outside the parser,
    the scene's own tracks measured under them (``track_rms_px``, ``track_evidence``) and the unperturbed cameras as
    ``reference_cameras``. The data parser itself never gives perturbed cameras these tracks (they were made with the
    unperturbed cameras): the plumbing is tested here by perturbing outside it."""
    import dataclasses

    from s2camp_ns.core.perturbation import PerturbationConfig
    from s2camp_ns.data.camera_perturbation import perturb_nerfstudio_cameras
    from s2camp_ns.data.scene_formats import detect_format
    from s2camp_ns.tracks.track_evidence import colmap_track_evidence, transforms_track_evidence

    options.setdefault("refine_keypoints", False)  # exact tracks (``_parse``)
    config = S2CampDataParserConfig(data=data, image_tracks="never", **options)
    parser = config.setup()
    outputs = parser.get_dataparser_outputs("train")
    moved = perturb_nerfstudio_cameras(outputs.cameras, PerturbationConfig(enabled=True))
    data_format, source = detect_format(config)
    if data_format == "colmap":
        result = colmap_track_evidence(moved, source, outputs.metadata["image_names"], outputs)
    else:
        result = transforms_track_evidence(config, source, moved, outputs, outputs.metadata["downscale_factor"])
    assert result is not None, "the scene's tracks must be found"
    metadata = dict(outputs.metadata, reference_cameras=outputs.cameras, perturbed=True)
    metadata["track_rms_px"], metadata["track_evidence"] = result
    return dataclasses.replace(outputs, cameras=moved, metadata=metadata)


def perturbed_track_rms(data: Path, **options) -> torch.Tensor:
    """The scene's own tracks' reprojection RMS (px [N]) under its perturbed training cameras
    (``perturbed_with_scene_tracks``)."""
    return perturbed_with_scene_tracks(data, **options).metadata["track_rms_px"]


def _rms_by_name(outputs) -> dict[str, float]:
    return dict(zip(outputs.metadata["image_names"], outputs.metadata["track_rms_px"].tolist(), strict=True))


def _stderr(capsys: pytest.CaptureFixture) -> str:
    return " ".join(capsys.readouterr().err.split())


@pytest.mark.parametrize(("downscale_factor", "perturbed"), [(1, False), (1, True), (2, True)])
def test_ns_process_data_tracks_equal_the_colmap_scene_s(
    tiny_scene: Path, tmp_path: Path, downscale_factor: int, perturbed: bool
) -> None:
    source = _ns_process_data_layout(tiny_scene, tmp_path / "ns")
    colmap = _parse(tiny_scene, downscale_factor=downscale_factor)
    transforms = _parse(source, downscale_factor=downscale_factor)
    assert transforms.metadata["source_format"] == "nerfstudio"
    assert transforms.metadata["image_names"] == colmap.metadata["image_names"]
    # The same cameras: both formats normalize the same COLMAP world the same way.
    torch.testing.assert_close(
        transforms.cameras.camera_to_worlds, colmap.cameras.camera_to_worlds, atol=1e-6, rtol=0.0
    )
    torch.testing.assert_close(transforms.cameras.fx, colmap.cameras.fx, atol=1e-4, rtol=0.0)
    rms = transforms.metadata["track_rms_px"]
    torch.testing.assert_close(rms, colmap.metadata["track_rms_px"], atol=1e-6, rtol=0.0)
    if perturbed:  # both formats' cameras perturbed alike, measured against the scene's tracks
        rms = perturbed_track_rms(source, downscale_factor=downscale_factor)
        expected = perturbed_track_rms(tiny_scene, downscale_factor=downscale_factor)
        torch.testing.assert_close(rms, expected, atol=1e-6, rtol=0.0)
        # The CamP perturbation moves the 64x48 cameras' tracks by 0.66-1.10 px at full size, half that at half size.
        assert float(rms.min()) > 0.5 / downscale_factor and float(rms.max()) < 3.0
    else:
        # The generator's observations are exact projections: only float32 storage of the poses remains.
        assert float(rms.max()) < 1e-3


def _rename_frame(source: Path, old: str, new: str, keep_colmap_id: bool) -> None:
    """Rename a frame's image (file and json), keeping or dropping the frame's ``colmap_im_id``."""
    meta = json.loads(source.read_text())
    (frame,) = [frame for frame in meta["frames"] if frame["file_path"] == f"images/{old}"]
    frame["file_path"] = f"images/{new}"
    if not keep_colmap_id:
        del frame["colmap_im_id"]
    source.write_text(json.dumps(meta))
    (source.parent / "images" / old).rename(source.parent / "images" / new)


def test_unregistered_image_gets_no_prior_and_the_others_keep_theirs(tiny_scene: Path, tmp_path: Path) -> None:
    source = _ns_process_data_layout(tiny_scene, tmp_path / "ns")
    # Names the model does not hold: one frame still has the colmap_im_id ns-process-data wrote (found by it), the
    # other has none (an image COLMAP never registered).
    _rename_frame(source, "frame_00003.png", "zz_00003.png", keep_colmap_id=True)
    _rename_frame(source, "frame_00004.png", "zz_00004.png", keep_colmap_id=False)
    # Every image in the training split, so that both scenes hold the same cameras whatever their order.
    expected = _rms_by_name(_parse(tiny_scene, downscale_factor=1, eval_mode="all"))
    got = _rms_by_name(_parse(source, downscale_factor=1, eval_mode="all"))
    assert math.isnan(got.pop("zz_00004.png"))
    got["frame_00003.png"] = got.pop("zz_00003.png")
    del expected["frame_00004.png"]
    assert got.keys() == expected.keys() and len(got) == 11
    # Exact observations: float32 noise only (the centring sums the poses in another order: not bit-identical).
    assert all(value < 1e-4 for value in (*got.values(), *expected.values()))
    # Perturbed (the draws follow the frame order, which the renames changed): every registered camera measured,
    # the unregistered one still NaN.
    names = _parse(source, downscale_factor=1, eval_mode="all").metadata["image_names"]
    rms = perturbed_track_rms(source, downscale_factor=1, eval_mode="all")
    perturbed = dict(zip(names, rms.tolist(), strict=True))
    assert math.isnan(perturbed.pop("zz_00004.png"))
    assert all(value > 0.3 for value in perturbed.values())


def test_transforms_json_without_applied_transform(tiny_scene: Path, tmp_path: Path, capsys) -> None:
    # Written with --keep-original-world-coordinate: no applied_transform, but the cameras are COLMAP's, so the
    # tracks are used: exact for the cameras as given, about a pixel once perturbed.
    kept = _ns_process_data_layout(tiny_scene, tmp_path / "kept", keep_original_world_coordinate=True)
    assert "applied_transform" not in json.loads(kept.read_text())
    assert float(_parse(kept, downscale_factor=1).metadata["track_rms_px"].max()) < 1e-3
    assert float(perturbed_track_rms(kept, downscale_factor=1).min()) > 0.3
    # applied_transform removed from a json whose cameras it had rotated: the frame is unknown, no tracks, said once.
    source = _ns_process_data_layout(tiny_scene, tmp_path / "ns")
    meta = json.loads(source.read_text())
    del meta["applied_transform"]
    source.write_text(json.dumps(meta))
    capsys.readouterr()
    assert "track_rms_px" not in _parse(source).metadata
    assert "track_rms_px" not in _parse(source, split="val").metadata
    err = _stderr(capsys)
    assert err.count("No SfM tracks:") == 1
    assert f"No SfM tracks: {source} has no applied_transform and its cameras are in neither COLMAP's frame of" in err
    assert "colmap/sparse/0/images.bin (10 of 10 cameras are not where COLMAP has them" in err
    assert "nor nerfstudio's legacy one: the frame is unknown" in err
    # Written by ns-process-data before applied_transform was recorded: x and y swapped, z negated (the frame that
    # nerfstudio's parser assumes for such files), written out here from the json's applied_transform.
    legacy = _ns_process_data_layout(tiny_scene, tmp_path / "legacy")
    meta = json.loads(legacy.read_text())
    to_colmap = torch.eye(4, dtype=torch.float64)
    to_colmap[:3] = torch.tensor(meta.pop("applied_transform"), dtype=torch.float64)
    old_world = torch.tensor([[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]], dtype=torch.float64)
    for frame in meta["frames"]:
        saved = torch.tensor(frame["transform_matrix"], dtype=torch.float64)
        frame["transform_matrix"] = (old_world @ torch.linalg.inv(to_colmap) @ saved).tolist()
    legacy.write_text(json.dumps(meta))
    assert float(_parse(legacy, downscale_factor=1).metadata["track_rms_px"].max()) < 1e-3
    assert float(perturbed_track_rms(legacy, downscale_factor=1).min()) > 0.3


def test_no_model_no_points_or_tracks_off_give_no_prior(tiny_scene: Path, tmp_path: Path, capsys) -> None:
    source = _ns_process_data_layout(tiny_scene, tmp_path / "ns")
    assert "track_rms_px" not in _parse(source, tracks=False).metadata
    model = tmp_path / "ns" / "colmap" / "sparse" / "0"
    (model / "points3D.bin").unlink()
    assert "track_rms_px" not in _parse(source).metadata
    assert f"No SfM tracks: no COLMAP model with points (cameras, images, points3D) in {model}" in _stderr(capsys)
    shutil.rmtree(tmp_path / "ns" / "colmap")
    assert "track_rms_px" not in _parse(source).metadata


def _move_camera(source: Path, file_path: str, dx: float) -> None:
    """Move one frame's camera by ``dx`` along the transforms.json's x axis (a rotation of COLMAP's: same length)."""
    meta = json.loads(source.read_text())
    (frame,) = [frame for frame in meta["frames"] if frame["file_path"] == file_path]
    frame["transform_matrix"][0][3] += dx
    source.write_text(json.dumps(meta))


def test_a_moved_camera_is_detected_and_named(tiny_scene: Path, tmp_path: Path, capsys) -> None:
    # The generated ring's camera centres spread 4 units about their centroid: the tolerance is 0.04.
    source = _ns_process_data_layout(tiny_scene, tmp_path / "ns")
    _move_camera(source, "images/frame_00005.png", 0.02)  # within the tolerance: measured, off by a fraction of a px
    rms = _rms_by_name(_parse(source, downscale_factor=1, eval_mode="all"))
    assert rms.pop("frame_00005.png") > 0.05 and all(value < 1e-3 for value in rms.values())
    _move_camera(source, "images/frame_00005.png", 0.98)
    capsys.readouterr()
    assert "track_rms_px" not in _parse(source).metadata
    err = _stderr(capsys)
    assert f"No SfM tracks: the cameras of {source} disagree with {tmp_path}/ns/colmap/sparse/0/images.bin" in err
    assert "1 of 10 cameras are not where COLMAP has them; the farthest, 'frame_00005.png', is 1 from" in err
    assert "(tolerance 0.04: 0.01 of the camera centres' spread 4, in COLMAP's units)" in err
    assert "the transforms.json was edited or belongs to another reconstruction" in err


def test_a_colmap_camera_of_another_size_is_named(tiny_scene: Path, tmp_path: Path, capsys) -> None:
    import pycolmap

    source = _ns_process_data_layout(tiny_scene, tmp_path / "ns")
    model = tmp_path / "ns" / "colmap" / "sparse" / "0"
    reconstruction = pycolmap.Reconstruction(str(model))
    reconstruction.cameras[1].width = 128  # the json and its images say 64x48: COLMAP's pixels are not theirs
    reconstruction.write_binary(str(model))
    capsys.readouterr()
    assert "track_rms_px" not in _parse(source).metadata
    assert "image 'frame_00001.png' is declared 64x48 but its COLMAP camera is 128x48" in _stderr(capsys)


def test_a_transforms_json_whose_colmap_keypoints_are_at_another_scale_is_refused(tiny_scene: Path, tmp_path: Path):
    import pycolmap

    source = _ns_process_data_layout(tiny_scene, tmp_path / "ns")
    model = tmp_path / "ns" / "colmap" / "sparse" / "0"
    reconstruction = pycolmap.Reconstruction(str(model))
    for image in reconstruction.images.values():
        for point in image.points2D:
            point.xy = point.xy * 0.25  # keypoints of a quarter-size SfM run, cameras at full size
    reconstruction.write_binary(str(model))
    with pytest.raises(ValueError, match=r"colmap/sparse/0/images.bin: the model's own cameras miss their tracks by"):
        _parse(source, image_tracks="never")
    assert "track_evidence" not in _parse(source, tracks=False).metadata
