"""Broken inputs, one class at a time, on tiny generated scenes: each is refused where the file is read, by an error
that names the file (and the frame or image), what is wrong and what is allowed, or, for a damaged cache entry,
rebuilt with a notice that names it. Parse-level: no training (the resumed runs are in tests/test_e2e.py).

The transforms.json scenes are the conftest's tiny COLMAP scene written as a transforms.json
(``conftest.write_transforms``), without a COLMAP model beside them: the data parser would make image tracks for
them, so the cases that must fail before the tracks are parsed with ``image_tracks`` both on and off.
"""

from __future__ import annotations

import io
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from conftest import write_transforms
from PIL import Image
from rich.console import Console

from s2camp_ns.data import image_check
from s2camp_ns.data.colmap_files import ColmapModelError
from s2camp_ns.data.dataparser import S2CampDataParserConfig
from s2camp_ns.data.image_check import ImageFileError
from s2camp_ns.data.transforms_file import TransformsFileError
from s2camp_ns.tracks import image_tracks as image_tracks_module
from s2camp_ns.tracks import robust_adjustment
from s2camp_ns.tracks.image_tracks import MODEL_FILES, RESULT_FILE, cache_key, image_tracks


def parse(data: Path, **options):
    """The training split of ``data`` as the data parser reads it."""
    return S2CampDataParserConfig(data=data, **options).setup().get_dataparser_outputs(split="train")


@pytest.fixture
def scene(tiny_scene: Path, tmp_path: Path) -> Path:
    """A private copy of the conftest's COLMAP scene (images/, images_2/, sparse/0) that a test may damage."""
    return Path(shutil.copytree(tiny_scene, tmp_path / "scene", ignore=shutil.ignore_patterns("s2camp_image_tracks")))


@pytest.fixture
def transforms(tiny_scene: Path, tmp_path: Path) -> Path:
    """A transforms.json of the tiny scene, its images beside it; tests edit it."""
    return write_transforms(tiny_scene, tmp_path / "ns")


def edit(source: Path, change) -> dict:
    """Apply ``change`` to the parsed transforms.json and write it back (a NaN or infinity as JSON's NaN, Infinity)."""
    meta = json.loads(source.read_text())
    change(meta)
    source.write_text(json.dumps(meta))
    return meta


def cut_short(path: Path, keep: float = 0.5) -> None:
    """Keep the first ``keep`` of the file's bytes, as a copy or download that stopped."""
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


# ---------------------------------------------------------------------------------------------------- transforms.json
def test_transforms_json_cut_short_names_the_file_line_and_column(transforms: Path):
    cut_short(transforms)
    pattern = rf"^{re.escape(str(transforms))} is not valid JSON: .* at line 1, column \d+ \(a file cut short"
    with pytest.raises(TransformsFileError, match=pattern):
        parse(transforms)


@pytest.mark.parametrize("image_tracks", ["auto", "never"])
def test_nan_in_a_pose_names_the_frame_and_its_image(transforms: Path, image_tracks: str):
    """A NaN in frame 2's pose (it crashed in an SVD, or with ``--tracks False`` named element 0 of the normalized
    cameras, another frame): the file, frame 2, its file_path and the value; with and without the tracks."""
    meta = edit(transforms, lambda meta: meta["frames"][2]["transform_matrix"][1].__setitem__(3, float("nan")))
    file_path = meta["frames"][2]["file_path"]
    pattern = (
        rf"^{re.escape(str(transforms))}: frame 2 \('{re.escape(file_path)}'\) holds nan at \['transform_matrix'\]"
        r"\[1\]\[3\]; every number must be finite"
    )
    with pytest.raises(TransformsFileError, match=pattern):
        parse(transforms, image_tracks=image_tracks)
    with pytest.raises(TransformsFileError, match=pattern):
        parse(transforms, tracks=False)


def test_infinite_intrinsics_are_named(transforms: Path):
    """``Infinity`` in JSON, or a literal too large for a float, anywhere in the file."""
    text = transforms.read_text()
    transforms.write_text(re.sub(r'"fl_y": [^,]+,', '"fl_y": 1e999,', text, count=1))
    with pytest.raises(TransformsFileError, match=r"transforms\.json: 'fl_y' is inf; every number must be finite"):
        parse(transforms, tracks=False)
    edit(transforms, lambda meta: meta.update(fl_y=meta["fl_x"], frames=meta["frames"][:5] + [
        {**meta["frames"][5], "k1": float("-inf")}] + meta["frames"][6:]))  # fmt: skip
    with pytest.raises(TransformsFileError, match=r"frame 5 \('images/frame_00005\.png'\) holds -inf at \['k1'\]"):
        parse(transforms, tracks=False)


@pytest.mark.parametrize("image_tracks", ["auto", "never"])
def test_two_frames_of_one_image_are_refused(transforms: Path, image_tracks: str):
    """Frame 7 lists frame 3's image under its own pose: refused whether image tracks are made (they named no file)
    or not (it trained on one image under two poses)."""
    edit(transforms, lambda meta: meta["frames"][7].update(file_path="./images/frame_00003.png"))
    pattern = (
        rf"^{re.escape(str(transforms))}: frames 3 and 7 both list the image '\./images/frame_00003\.png': one image "
        "under two poses is ambiguous"
    )
    with pytest.raises(TransformsFileError, match=pattern):
        parse(transforms, image_tracks=image_tracks)


def test_two_images_of_one_file_name_are_refused(transforms: Path):
    """Two folders holding ``frame_00003.png``: the images' names (the export's, the tracks') and the downscaled
    folder's ``images_<k>/<file name>`` would be one for both."""
    other = transforms.parent / "other"
    other.mkdir()
    shutil.copy(transforms.parent / "images" / "frame_00004.png", other / "frame_00003.png")
    edit(transforms, lambda meta: meta["frames"][4].update(file_path="other/frame_00003.png"))
    pattern = r"frames 3 \('images/frame_00003\.png'\) and 4 \('other/frame_00003\.png'\) list images of one file name"
    with pytest.raises(TransformsFileError, match=pattern):
        parse(transforms, tracks=False)


@pytest.mark.parametrize(
    ("change", "pattern"),
    [
        (lambda meta: meta["frames"][3].pop("transform_matrix"),
         r"frame 3 \('images/frame_00003\.png'\) has no 'transform_matrix'; expected the camera-to-world matrix as 4 "
         "rows of 4 numbers"),
        (lambda meta: meta["frames"][1].update(transform_matrix=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
         r"frame 1 \('images/frame_00001\.png'\) has the transform_matrix \[\[1, 0, 0\], .*4 rows of 4 numbers"),
        (lambda meta: meta["frames"][6].pop("file_path"), r"frame 6 has no 'file_path'"),
        (lambda meta: meta.pop("fl_x"),
         r"frame 0 \('images/frame_00000\.png'\) has no fl_x, and the file gives none at the top level; every frame "
         "needs fl_x, fl_y, cx, cy, w, h"),
        (lambda meta: meta.update(cx="half"), r"the top level has cx = \"half\"; expected a number"),
        (lambda meta: meta.pop("frames"), r"holds an object without a 'frames' list; expected nerfstudio's"),
        (lambda meta: meta.update(frames=[]), r"lists no frames: the scene is empty"),
    ],
    ids=["no-transform-matrix", "3x3-matrix", "no-file-path", "no-focal-length", "text-centre", "no-frames", "empty"],
)  # fmt: skip
def test_missing_or_malformed_keys_are_named(transforms: Path, change, pattern: str):
    edit(transforms, change)
    with pytest.raises(TransformsFileError, match=rf"^{re.escape(str(transforms))}(: | ).*{pattern}"):
        parse(transforms, tracks=False)


# ------------------------------------------------------------------------------------------------------ COLMAP model
def test_truncated_colmap_model_is_named(scene: Path):
    """COLMAP binaries were already read strictly (tests/test_dataparser.py tries every file and damage): one case."""
    images = scene / "sparse" / "0" / "images.bin"
    cut_short(images, 0.7)
    with pytest.raises(ColmapModelError, match=rf"^{re.escape(str(images))} is corrupt or truncated"):
        parse(scene)


def test_two_colmap_images_of_one_name_are_refused(scene: Path):
    model = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    first, second = sorted(model.images)[:2]
    model.images[second].name = model.images[first].name
    model.write_binary(str(scene / "sparse" / "0"))
    images = scene / "sparse" / "0" / "images.bin"
    pattern = rf"^{re.escape(str(images))}: images {first} and {second} are both named 'frame_00000\.png'"
    with pytest.raises(ColmapModelError, match=pattern):
        parse(scene)


# ------------------------------------------------------------------------------------------------------------ images
@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_truncated_image_of_a_colmap_scene_is_named(scene: Path, suffix: str):
    """An image cut short keeps its header (its size checks pass); nerfstudio's loader failed on it later with
    ``OSError: image file is truncated`` and no file. PNG as the scene writes it, JPEG converted (the model renamed
    to match)."""
    folder = scene / "images_2"
    if suffix == ".jpg":
        model = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
        for image in model.images.values():
            path = folder / image.name
            Image.open(path).convert("RGB").save(path.with_suffix(".jpg"), quality=95)
            path.unlink()
            image.name = str(Path(image.name).with_suffix(".jpg"))
        model.write_binary(str(scene / "sparse" / "0"))
    damaged = folder / f"frame_00005{suffix}"
    with Image.open(damaged) as image:
        image.size  # noqa: B018 (the header still reads)
    cut_short(damaged)
    images_file = scene / "sparse" / "0" / "images.bin"
    pattern = (
        rf"^image {re.escape(str(damaged))}, listed by {re.escape(str(images_file))}, cannot be decoded: (image file "
        r"is truncated|Truncated File Read).*; expected a complete image file"
    )
    with pytest.raises(ImageFileError, match=pattern):
        parse(scene, downscale_factor=2, tracks=False)


def test_truncated_image_of_a_transforms_scene_is_named(transforms: Path):
    damaged = transforms.parent / "images" / "frame_00009.png"
    cut_short(damaged, 0.6)
    pattern = rf"^image {re.escape(str(damaged))}, listed by {re.escape(str(transforms))}, cannot be decoded"
    with pytest.raises(ImageFileError, match=pattern):
        parse(transforms, tracks=False)


def test_a_file_that_is_no_image_is_named(transforms: Path):
    damaged = transforms.parent / "images" / "frame_00002.png"
    damaged.write_bytes(b"not an image at all")
    with pytest.raises(ImageFileError, match=rf"^image {re.escape(str(damaged))}, listed by .*cannot identify image"):
        parse(transforms, tracks=False)


def test_truncated_full_size_image_read_by_the_image_tracks_is_named(scene: Path):
    """Trained on images_2, a scene's full-size images are read only by the image tracks' SIFT, which skips an image
    it cannot decode: the build decodes them first and names the damaged one."""
    damaged = scene / "images" / "frame_00004.png"
    cut_short(damaged)
    with pytest.raises(ImageFileError, match=rf"^image {re.escape(str(damaged))}, listed by the scene \(image tracks"):
        parse(scene, downscale_factor=2, image_tracks="always")


def test_decoding_a_large_scene_shows_progress_and_keeps_the_order(scene: Path, monkeypatch: pytest.MonkeyPatch):
    """From ``PROGRESS_MIN_IMAGES`` images on, a progress bar names the file whose images are decoded; the sizes come
    back in the order asked, whatever thread decoded each."""
    shown = io.StringIO()
    monkeypatch.setattr(image_check, "LOG", Console(file=shown, force_terminal=True, width=120))
    monkeypatch.setattr(image_check, "PROGRESS_MIN_IMAGES", 3)
    paths = sorted((scene / "images").iterdir()) + sorted((scene / "images_2").iterdir())
    sizes = image_check.decoded_sizes(paths, "the test's list")
    assert sizes == [(64, 48)] * 12 + [(32, 24)] * 12
    assert "Decoding the images of the test's list" in shown.getvalue()
    shown.truncate(0)
    image_check.decoded_sizes(paths[:2], "two images")
    assert "Decoding" not in shown.getvalue()


# -------------------------------------------------------------------------------------------------- damaged caches
@pytest.fixture
def builds(monkeypatch: pytest.MonkeyPatch) -> list[Path]:
    """The image tracks' builds replaced by one that returns the given cameras as the model (no points, accepted):
    an entry with every model file, in no time. The folders built in."""
    calls: list[Path] = []

    def build(given, image_root, work, *rest, **options):
        calls.append(work)
        return pycolmap.Reconstruction(given), None

    monkeypatch.setattr(image_tracks_module, "_build", build)
    return calls


def _damage_digest(entry: Path) -> str:
    path = entry / "points3D.bin"
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))
    return r"points3D\.bin is not the file the build wrote \(its SHA-256 differs\)"


def _damage_result(entry: Path) -> str:
    cut_short(entry / RESULT_FILE)
    return rf"{RESULT_FILE} is not valid JSON"


def _remove_images(entry: Path) -> str:
    (entry / "images.bin").unlink()
    return r"images\.bin is missing"


def _damage_old_entry(entry: Path) -> str:
    """An entry written before the digests, its points file cut short: read strictly instead."""
    result = json.loads((entry / RESULT_FILE).read_text())
    del result["files"]
    (entry / RESULT_FILE).write_text(json.dumps(result))
    (entry / "images.bin").write_bytes((entry / "images.bin").read_bytes()[:-5])
    return r"images\.bin is corrupt or truncated"


@pytest.mark.parametrize("damage", [_damage_digest, _damage_result, _remove_images, _damage_old_entry])
def test_a_damaged_image_track_entry_is_rebuilt_with_a_notice(
    given: pycolmap.Reconstruction,
    tiny_scene: Path,
    tmp_path: Path,
    builds: list[Path],
    damage,
    capsys: pytest.CaptureFixture,
):
    cache = tmp_path / "cache"
    first = image_tracks(given, tiny_scene / "images", cache)
    entry = cache / cache_key(given, tiny_scene / "images")
    assert first.model == entry and len(builds) == 1
    written = {name: (entry / name).read_bytes() for name in MODEL_FILES}
    capsys.readouterr()
    why = damage(entry)
    again = image_tracks(given, tiny_scene / "images", cache)
    notice = " ".join(capsys.readouterr().err.split())  # rich wraps long lines
    pattern = rf"Image tracks: the cache entry {re.escape(str(entry))} is damaged \(({re.escape(str(entry))}/)?{why}"
    assert re.search(pattern, notice), notice
    assert "it is not used, and is built again" in notice
    assert len(builds) == 2 and again.model == entry and again.reason is None
    assert {name: (entry / name).read_bytes() for name in MODEL_FILES} == written  # the rebuilt entry, whole
    image_tracks(given, tiny_scene / "images", cache)
    assert len(builds) == 2 and "damaged" not in capsys.readouterr().err  # and read from now on


def test_a_damaged_readjusted_points_entry_is_adjusted_again_with_a_notice(
    tiny_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    model = tiny_scene / "sparse" / "0"
    robust_adjustment._cached.cache_clear()
    points = robust_adjustment.readjusted_tracks(model).points
    (entry,) = (tmp_path / "xdg" / "s2camp-ns" / robust_adjustment.CACHE_KIND).glob("*.npz")
    cut_short(entry, 0.8)
    robust_adjustment._cached.cache_clear()
    capsys.readouterr()
    again = robust_adjustment.readjusted_tracks(model).points
    notice = " ".join(capsys.readouterr().err.split())
    assert f"Re-adjusted SfM points: the cache entry {entry} is damaged (" in notice, notice
    assert set(again) == set(points) and all(np.allclose(again[i], points[i], rtol=0, atol=1e-9) for i in points)
    robust_adjustment._cached.cache_clear()
    assert robust_adjustment._read(entry).points.keys() == points.keys()  # rewritten whole
    robust_adjustment._cached.cache_clear()
