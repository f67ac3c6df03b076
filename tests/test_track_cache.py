"""Where the image tracks' cache lives and who builds an entry (``s2camp_ns.tracks.track_cache``): a scene
folder that cannot be written has new tracks built in the user's cache folder and its shipped tracks read; of
processes that ask for one entry at once exactly one builds, the others wait and read the same entry, and a waiter
whose builder dies builds itself.

Read-only folders: tests run as root in CI, and root ignores permission bits, so ``_read_only`` sets mode 0o555 and,
only where the tests run as root, makes the writability probe answer as the kernel answers a non-root user
(PermissionError). As another user the real probe meets the real read-only folder. The probe itself is tested on a
path nobody can create, below a regular file (``test_the_probe_creates_a_file_to_tell_whether_a_folder_is_writable``).

Builds are fakes (``_build`` replaced: a second each, so that builds that are not serialized overlap) except in
``test_two_processes_asking_for_one_entry_at_once_build_it_once_and_read_the_same_tracks``, which runs COLMAP's.
"""

from __future__ import annotations

import errno
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pycolmap
import pytest
from hang_guard import HANG_GUARD_S

from s2camp_ns.tracks import image_tracks as module
from s2camp_ns.tracks import track_cache
from s2camp_ns.tracks.image_tracks import cache_key, image_tracks
from s2camp_ns.tracks.track_cache import user_cache_folder, write_error

REPOSITORY = Path(__file__).resolve().parents[1]
WAITING = "Image tracks: waiting for process"
"""The start of the notice of a process that waits for another's build."""
CHILD = r"""
import json, os, sys, time
from pathlib import Path

args = json.loads(sys.argv[1])
import pycolmap
from s2camp_ns.tracks import image_tracks as module

real_build = module._build


def counted_build(given, image_root, work, *rest, **options):
    with open(args["marker"], "a") as file:
        file.write(json.dumps({"pid": os.getpid(), "after_kill": os.path.exists(args["killed"])}) + "\n")
    if args["build"] == "hang":
        time.sleep(600)
    time.sleep(1.0)  # long enough for builds that are not serialized to overlap
    if args["build"] == "real":
        return real_build(given, image_root, work, *rest, **options)
    return pycolmap.Reconstruction(), f"fake build by process {os.getpid()}"


module._build = counted_build
given = pycolmap.Reconstruction(args["given"])
Path(args["ready"]).touch()
while not os.path.exists(args["go"]):
    time.sleep(0.01)
result = module.image_tracks(given, Path(args["images"]), Path(args["cache"]))
print(json.dumps([None if result.model is None else str(result.model), result.summary, result.reason]))
"""
"""A process that asks for the tracks of ``args['given']`` (cameras of a written model) once ``args['go']`` exists,
with a build that appends a line to ``args['marker']`` and then hangs (``hang``), or after a second makes no tracks
(``fake``) or COLMAP's (``real``); prints the model, summary and reason as JSON."""


@pytest.fixture(autouse=True)
def user_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The user's cache folder of every test: in ``tmp_path``, never the real ``~/.cache``."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    return tmp_path / "xdg" / "s2camp-ns" / "image_tracks"


@pytest.fixture
def scene(tiny_scene: Path, tmp_path: Path) -> Iterator[Path]:
    """A scene folder of its own (links to the tiny scene's files, not to the image tracks' cache that other tests of
    the session may have built in the shared tiny scene), writable again after the test."""
    folder = tmp_path / "scene"
    folder.mkdir()
    for entry in tiny_scene.iterdir():
        if entry.name == "s2camp_image_tracks":
            continue
        (folder / entry.name).symlink_to(entry, target_is_directory=entry.is_dir())
    yield folder
    folder.chmod(0o755)


def _read_only(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Make ``folder`` read-only: mode 0o555, and, as root, whom modes do not bind, the probe's answer for a non-root
    user below it (module docstring)."""
    folder.chmod(0o555)
    if os.geteuid() != 0:
        return
    probe = track_cache.write_error

    def as_non_root(path: Path) -> OSError | None:
        if path == folder or folder in path.parents:
            return PermissionError(errno.EACCES, "Permission denied", str(path))
        return probe(path)

    monkeypatch.setattr(track_cache, "write_error", as_non_root)


def _fake_builds(monkeypatch: pytest.MonkeyPatch, reason: str = "fake build") -> list[Path]:
    """Replace the build by one that makes no tracks (``reason``); the folders it was asked to build in."""
    calls: list[Path] = []

    def fake(given, image_root, work, *rest, **options):
        calls.append(work)
        return pycolmap.Reconstruction(), reason

    monkeypatch.setattr(module, "_build", fake)
    return calls


def _parse(scene: Path) -> dict:
    """The data parser's training metadata of ``scene`` with tracks made from its images (default cache)."""
    from s2camp_ns.data.dataparser import S2CampDataParserConfig

    config = S2CampDataParserConfig(data=scene, downscale_factor=2, image_tracks="always")
    return config.setup()._generate_dataparser_outputs("train").metadata


def test_the_probe_creates_a_file_to_tell_whether_a_folder_is_writable(tmp_path: Path):
    assert write_error(tmp_path / "new" / "cache") is None
    assert list((tmp_path / "new" / "cache").iterdir()) == []  # created, the probe file removed
    (tmp_path / "file").write_text("not a folder")
    assert isinstance(write_error(tmp_path / "file" / "cache"), NotADirectoryError)  # for root too


def test_the_user_cache_folder_follows_xdg_cache_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    assert user_cache_folder() == tmp_path / "xdg" / "s2camp-ns" / "image_tracks"
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    for ignored in ("", "relative/cache"):  # the XDG specification ignores relative paths
        monkeypatch.setenv("XDG_CACHE_HOME", ignored)
        assert user_cache_folder() == tmp_path / "home" / ".cache" / "s2camp-ns" / "image_tracks"


def test_a_read_only_scene_gets_its_tracks_built_in_the_user_cache_folder(
    scene: Path, user_cache: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
):
    builds = _fake_builds(monkeypatch)
    before = sorted(path.name for path in scene.iterdir())
    _read_only(scene, monkeypatch)
    assert "track_evidence" not in _parse(scene)  # no tracks: the fake build makes none
    (entry,) = user_cache.iterdir()  # nothing else: no lock file, no temporary folder
    assert [work.parent for work in builds] == [user_cache]
    assert json.loads((entry / "result.json").read_text())["reason"] == "fake build"
    assert sorted(path.name for path in scene.iterdir()) == before
    err = " ".join(capsys.readouterr().err.split())  # rich wraps long lines
    assert "cannot be written" in err and f"building them in the user's cache folder {user_cache}" in err
    _parse(scene)  # a second run reads the user's entry
    assert len(builds) == 1


def test_a_read_only_scene_that_ships_its_cache_has_it_read(
    scene: Path, user_cache: Path, monkeypatch: pytest.MonkeyPatch
):
    """A regression guard of the fallback (the code before it read a shipped cache as well): the entry in the
    scene folder is read first, nothing is built or written, not even in the user's cache folder."""
    _fake_builds(monkeypatch, reason="shipped with the scene")
    _parse(scene)
    (shipped,) = (scene / "s2camp_image_tracks").iterdir()
    _read_only(scene / "s2camp_image_tracks", monkeypatch)
    _read_only(scene, monkeypatch)
    monkeypatch.setattr(module, "_build", lambda *args, **options: pytest.fail("the shipped cache was rebuilt"))
    _parse(scene)
    assert not user_cache.parent.exists()
    assert list((scene / "s2camp_image_tracks").iterdir()) == [shipped]
    (scene / "s2camp_image_tracks").chmod(0o755)


def test_an_unwritable_cache_is_named_with_what_to_do(
    given: pycolmap.Reconstruction, tiny_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    _fake_builds(monkeypatch)
    (tmp_path / "file").write_text("not a folder")
    blocked = tmp_path / "file" / "cache"
    with pytest.raises(OSError, match=rf"cache folder {re.escape(str(blocked))} \(image_tracks_cache; .*-cache DIR"):
        image_tracks(given, tiny_scene / "images", blocked)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "file"))  # the user's cache folder blocked too
    with pytest.raises(OSError, match=r"nor the user's cache folder .*file/s2camp-ns.*set XDG_CACHE_HOME"):
        image_tracks(given, tiny_scene / "images", blocked, user_fallback=True)


def _child(args: dict, stderr=subprocess.PIPE) -> subprocess.Popen:
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-c", CHILD, json.dumps(args)]
    return subprocess.Popen(command, cwd=REPOSITORY, env=environment, stdout=subprocess.PIPE, stderr=stderr, text=True)


def _child_args(given: pycolmap.Reconstruction, tiny_scene: Path, tmp_path: Path, name: str, build: str) -> dict:
    model = tmp_path / "given"
    if not model.exists():
        model.mkdir()
        given.write(model)
    files = {key: str(tmp_path / f"{key}") for key in ("marker", "killed", "go")}
    return {**files, "build": build, "ready": str(tmp_path / f"ready-{name}"), "given": str(model),
            "images": str(tiny_scene / "images"), "cache": str(tmp_path / "cache")}  # fmt: skip


def _wait_for(condition, what: str, running: list[subprocess.Popen], timeout: float = HANG_GUARD_S) -> None:
    """Poll ``condition`` until it holds; fail, with its stderr, as soon as one of the ``running`` processes ends."""
    deadline = time.monotonic() + timeout
    while not condition():
        for process in running:
            if process.poll() is not None:
                ended = f"process {process.pid} ended ({process.returncode})"
                pytest.fail(f"{ended} before {what}: {process.stderr.read()}")
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def _builds(tmp_path: Path) -> list[dict]:
    marker = tmp_path / "marker"
    return [json.loads(line) for line in marker.read_text().splitlines()] if marker.exists() else []


@pytest.mark.timeout(HANG_GUARD_S)
def test_two_processes_asking_for_one_entry_at_once_build_it_once_and_read_the_same_tracks(
    given: pycolmap.Reconstruction, tiny_scene: Path, tmp_path: Path
):
    """COLMAP's build of the tiny scene (it triangulates no point: a cached failure, as real as a model)."""
    runs = [_child(_child_args(given, tiny_scene, tmp_path, name, "real")) for name in ("a", "b")]
    try:
        _wait_for(lambda: all((tmp_path / f"ready-{name}").exists() for name in ("a", "b")), "both processes", runs)
        (tmp_path / "go").touch()
        outputs = [run.communicate(timeout=HANG_GUARD_S) for run in runs]
    finally:
        for run in runs:
            run.kill()
    assert [run.returncode for run in runs] == [0, 0], [err for _, err in outputs]
    results = [json.loads(out.splitlines()[-1]) for out, _ in outputs]
    assert len(_builds(tmp_path)) == 1
    assert results[0] == results[1]
    assert results[0][2].startswith("no point could be triangulated")
    key = cache_key(given, tiny_scene / "images")
    assert [path.name for path in (tmp_path / "cache").iterdir()] == [key]  # no lock file left
    (builder,) = (build["pid"] for build in _builds(tmp_path))
    (waiter,) = (err for (_, err), run in zip(outputs, runs, strict=True) if run.pid != builder)
    assert f"{WAITING} {builder} " in waiter  # the other one waited, and said so


@pytest.mark.timeout(HANG_GUARD_S)
def test_a_waiter_whose_builder_dies_builds_itself(given: pycolmap.Reconstruction, tiny_scene: Path, tmp_path: Path):
    (tmp_path / "go").touch()
    builder = _child(_child_args(given, tiny_scene, tmp_path, "a", "hang"))
    waiter = None
    try:
        _wait_for(lambda: len(_builds(tmp_path)) == 1, "the first process's build", [builder])
        with open(tmp_path / "waiter.err", "w") as err:
            waiter = _child(_child_args(given, tiny_scene, tmp_path, "b", "fake"), stderr=err)
        _wait_for(
            lambda: waiter.poll() is not None or WAITING in (tmp_path / "waiter.err").read_text(),
            "the second process to wait",
            [builder],
        )
        assert waiter.poll() is None, "the second process did not wait for the first one's build"
        (tmp_path / "killed").touch()  # before the kill: the waiter may build as soon as the builder is dead
        builder.send_signal(signal.SIGKILL)  # dies holding the lock, its temporary folder left behind
        builder.wait(timeout=30)
        out, _ = waiter.communicate(timeout=HANG_GUARD_S)
    finally:
        for run in (builder, waiter):
            if run is not None:
                run.kill()
    assert waiter.returncode == 0, (tmp_path / "waiter.err").read_text()
    first, second = _builds(tmp_path)
    assert (first["pid"], second["pid"]) == (builder.pid, waiter.pid)
    assert second["after_kill"]
    assert json.loads(out.splitlines()[-1])[2].startswith(f"fake build by process {waiter.pid} ")
    assert f"{WAITING} {builder.pid} " in (tmp_path / "waiter.err").read_text()
    key = cache_key(given, tiny_scene / "images")
    assert [path.name for path in (tmp_path / "cache").iterdir()] == [key]  # the dead build's folder removed


def test_a_waiter_names_a_holder_that_writes_its_name_after_taking_the_lock(
    tmp_path: Path, capsys: pytest.CaptureFixture
):
    """The holder writes its name just after it takes the lock: a waiter that reads the file in between (a loaded
    machine) reads it again instead of naming the holder "?"."""
    import threading

    path = tmp_path / ".entry.lock"
    handle = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    late = threading.Timer(0.3, lambda: path.write_text("4242 builder-host\n"))
    late.start()
    try:
        track_cache._notice_wait(handle, tmp_path / "entry", "Image tracks")
    finally:
        late.join()
        os.close(handle)
    err = " ".join(capsys.readouterr().err.split())
    assert f"{WAITING} 4242 on builder-host, which builds them in {tmp_path / 'entry'}" in err
