"""The viewer's S2CamP panel and training-camera frusta.

Fast tests drive the panel against a real viser server with a stand-in for nerfstudio's ``Viewer``; the slow
end-to-end test trains ``ns-train s2camp`` with the viewer on and reads the panel in headless Chromium, as a person
would: it waits for the panel, checks its values and that they change while training, presses "Refresh P now",
takes a screenshot (kept in the test's tmp_path; ``S2CAMP_UPDATE_SCREENSHOT=1`` also writes
docs/viewer-screenshot.png) and stops training cleanly.
"""

from __future__ import annotations

import base64
import contextlib
import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from conftest import lpips_offline, tiny_model_config
from hang_guard import HANG_GUARD_S
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.engine.callbacks import TrainingCallbackAttributes
from nerfstudio.viewer.utils import parse_object
from nerfstudio.viewer.viewer_elements import ViewerControl, ViewerElement

from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
from s2camp_ns.core.camera import vertical_field_of_view
from s2camp_ns.core.preconditioner import SamplingConfig
from s2camp_ns.method.model import S2CampModel
from s2camp_ns.viewer.panel import FRUSTUM_COLORS, MAX_DRAWN_FOV, DisplayText, S2CampViewerPanel

REPO_ROOT = Path(__file__).resolve().parents[1]
SCREENSHOT = REPO_ROOT / "docs" / "viewer-screenshot.png"
UPDATING_SCREENSHOT = os.environ.get("S2CAMP_UPDATE_SCREENSHOT") == "1"
SCREENSHOT_STEPS = 1000
"""Training steps before the screenshot written with ``S2CAMP_UPDATE_SCREENSHOT=1``."""
SCREENSHOT_SCENE = {"num_cameras": 24, "width": 160, "height": 120, "points_per_image": 150, "seed": 0}
"""The screenshot's scene: larger images than the test's 64x48 one, whose field renders as grey-brown fog. With
``SCREENSHOT_SETUP`` the view after the jump to a training camera shows the scene's large white sphere on the ground,
blurred (docs/viewer-screenshot.png)."""
SCREENSHOT_SETUP = (
    "--pipeline.datamanager.train-num-rays-per-batch", "1024",
    "--pipeline.model.hidden-dim", "32",
    "--pipeline.model.hidden-dim-color", "32",
    "--pipeline.model.num-levels", "12",
    "--pipeline.model.log2-hashmap-size", "15",
    "--pipeline.model.num-nerf-samples-per-ray", "24",
    "--pipeline.model.num-proposal-samples-per-ray", "32", "24",
    "--pipeline.model.camera-optimizer.fix-common-rotation", "True",
    "--pipeline.model.camera-optimizer.track-prior", "True",
)  # fmt: skip
"""Options of the screenshot's runs, in place of the test's ``TEST_SETUP``: a larger field, and cameras anchored
where the scene's tracks put them (s2camp's defaults, stated), so the field trains on consistent cameras while the
panel still draws the perturbed initial ones. Tried before: with the method's own defaults the perturbation (focal
12 px off at 160x120) stays inside the camera warm-up for the 1200 steps a CPU allows, and with the test's camera
learning rate and no warm-up the focal length ran 19.5 px off in 2000 steps; the field was a blur in both."""

VIEW_MOVED = 20.0
"""Mean change of the view's pixel values (0-255) that a jump of the viewer camera to a training camera exceeds."""
NUM_CAMERAS, WIDTH, HEIGHT = 4, 32, 24


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


# ----------------------------------------------------------------------------------------------- fast: the panel
def tiny_cameras(shift: float = 0.0, focal: float = 30.0, camera_type: CameraType = CameraType.PERSPECTIVE) -> Cameras:
    c2w = torch.eye(4)[:3].expand(NUM_CAMERAS, 3, 4).clone()
    c2w[:, 0, 3] = torch.linspace(-0.3, 0.3, NUM_CAMERAS) + shift
    c2w[:, 1, 3] = torch.tensor([0.0, 0.1, -0.1, 0.05])
    c2w[:, 2, 3] = 1.0
    return Cameras(
        camera_to_worlds=c2w,
        fx=focal,
        fy=focal,
        cx=WIDTH / 2,
        cy=HEIGHT / 2,
        width=WIDTH,
        height=HEIGHT,
        camera_type=camera_type,
    )


def build_model(
    viewer_update_period: float = 0.0, initial: Cameras | None = None, reference: Cameras | None = None
) -> S2CampModel:
    """A sized-down S2CampModel whose reference cameras differ from its initial ones (as with the perturbation)."""
    with lpips_offline():
        config = tiny_model_config(
            S2CampCameraOptimizerConfig(
                sampling=SamplingConfig(num_points=64, sampler="camp-random"),
                parameters="pose+focal",
                intrinsics="per-image",
            ),
            samples_per_ray=4,
            viewer_update_period=viewer_update_period,
        )
        model = config.setup(
            scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])),
            num_train_data=NUM_CAMERAS,
            metadata={"reference_cameras": reference if reference is not None else tiny_cameras()},
        )
    model.camera_optimizer.set_train_cameras(initial if initial is not None else tiny_cameras(0.02, 31.0))
    return model


class FakeClientCamera:
    fov = 1.0
    wxyz = (1.0, 0.0, 0.0, 0.0)
    position = (0.0, 0.0, 0.0)


def fake_click():
    return SimpleNamespace(client=SimpleNamespace(camera=FakeClientCamera()))


@contextlib.contextmanager
def viewer_with(model: S2CampModel, training: bool = True) -> Iterator[SimpleNamespace]:
    """Install the model's viewer elements and controls the way nerfstudio's Viewer does, on a real viser server.

    ``training=False`` stands for ``ns-viewer`` (a viewer without a trainer).
    """
    import viser

    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    trainer = object() if training else None
    header_steps: list[int] = []  # what nerfstudio's Viewer.update_step would write as "Step: N"
    viewer = SimpleNamespace(
        viser_server=server,
        config=ViewerConfig(),
        camera_handles={},
        current_camera_idx=0,
        trainer=trainer,
        update_step=header_steps.append,
        header_steps=header_steps,
    )
    try:
        for _, element in parse_object(model, ViewerElement, "Custom Elements/model"):
            element.install(server)
        for _, control in parse_object(model, ViewerControl, "Custom Elements/model"):
            control._setup(viewer)
        yield viewer
    finally:
        server.stop()


def panel_text(panel: S2CampViewerPanel) -> dict[str, str]:
    return {name: getattr(panel, name).value for name in dir(panel) if isinstance(getattr(panel, name), DisplayText)}


def test_panel_is_declared_with_nerfstudio_viewer_elements():
    model = build_model()
    paths = dict(parse_object(model, ViewerElement, "Custom Elements/model"))
    panel = model.S2CamP
    assert paths["Custom Elements/model/S2CamP/a_status"] is panel.a_status
    for name in ("c_rotation_error", "g_condition_sigma", "h_condition_whitened", "i_since_refresh", "j_refresh_now"):
        assert f"Custom Elements/model/S2CamP/{name}" in paths
    assert [control for _, control in parse_object(model, ViewerControl, "")] == [panel.viewer_control]
    # Nothing of the panel enters checkpoints, and the panel does not hold the model as a submodule.
    assert not any("S2CamP" in key for key in model.state_dict())
    assert list(panel.children()) == [] and list(panel.parameters()) == []


def test_no_panel_callback_and_no_update_without_the_viewer():
    model = build_model()
    attributes = TrainingCallbackAttributes(optimizers=None, grad_scaler=None, pipeline=None, trainer=None)
    assert not model.S2CamP.attached
    assert model.viewer_panel_callbacks() == []
    with_panel = len(model.get_training_callbacks(attributes))
    model.S2CamP = None
    assert len(model.get_training_callbacks(attributes)) == with_panel
    assert not hasattr(build_model(viewer_update_period=-1.0), "S2CamP")


def test_panel_values_frusta_refresh_and_click_with_a_viser_server():
    model = build_model(viewer_update_period=0.0)
    panel: S2CampViewerPanel = model.S2CamP
    optimizer = model.camera_optimizer
    with viewer_with(model) as viewer:
        assert panel.attached and panel.num_updates == 1
        first = panel_text(panel)
        assert first["a_status"] == f"step 0 · {NUM_CAMERAS} cams"
        assert first["b_errors"] == "mean / max" and first["f_conditioning"] == "mean / worst"
        number = r"[0-9.e+-]+"
        for name in ("c_rotation_error", "d_position_error", "e_focal_error", "g_condition_sigma"):
            assert re.fullmatch(rf"{number} / {number}", first[name]), (name, first[name])
        # Initial focal 31 px against the reference's 30 px.
        assert first["e_focal_error"] == "1 / 1"
        # The whitened Gram is much better conditioned than the Gram itself.
        sigma_mean = float(first["g_condition_sigma"].split(" / ")[0])
        whitened_mean = float(first["h_condition_whitened"].split(" / ")[0])
        assert whitened_mean < sigma_mean / 10
        assert first["i_since_refresh"].startswith("0 steps ago")

        # Three frustum sets, in their colours; the reference differs from the initial cameras here.
        for name in FRUSTUM_COLORS:
            assert sorted(panel._handles[name]) == list(range(NUM_CAMERAS)), name
        assert panel.l_show_initial.gui_handle.visible and panel.m_show_reference.gui_handle.visible
        assert not panel.j_refresh_now.gui_handle.disabled

        attributes = TrainingCallbackAttributes(optimizers=None, grad_scaler=None, pipeline=None, trainer=None)
        callbacks = model.viewer_panel_callbacks()
        assert len(callbacks) == 1
        (callback,) = callbacks
        initial_positions = {i: p[0].copy() for i, p in panel._poses["initial"].items()}
        refined_fov = panel._poses["refined"][1][2]
        with torch.no_grad():
            optimizer.refiner.whitened_delta.add_(0.05)
        callback.func(step=7)
        moved = panel_text(panel)
        assert moved["a_status"].startswith("step 7 ")
        assert viewer.header_steps == [0, 7]  # nerfstudio's "Step: N" header follows the panel's step
        assert moved["c_rotation_error"] != first["c_rotation_error"]
        assert moved["i_since_refresh"].startswith("7 steps ago")
        assert all((panel._poses["initial"][i][0] == p).all() for i, p in initial_positions.items())
        refined = optimizer.refiner.refined_intrinsics().detach()
        expected_fov = float(vertical_field_of_view(refined)[1])  # tested against closed forms in test_camera_models
        assert panel._poses["refined"][1][2] == pytest.approx(expected_fov) and expected_fov != refined_fov
        refined_position = optimizer.refiner.refined_c2w().detach()[1, :, 3].numpy() * 10.0
        assert panel._poses["refined"][1][0] == pytest.approx(refined_position)

        # The button only passes the request on; the model refreshes P in its own training callback, and the
        # panel shows the refresh at its next update whatever its update period.
        (refresh,) = [
            c for c in model.get_training_callbacks(attributes) if c.func.__name__ == "refresh_preconditioner"
        ]
        panel.request_refresh()
        assert int(optimizer.refiner.last_refresh_step) == 0
        refresh.func(step=9)
        assert int(optimizer.refiner.last_refresh_step) == 9
        refresh.func(step=10)  # a request is applied once
        assert int(optimizer.refiner.last_refresh_step) == 9
        panel.update_period = 1e9
        callback.func(step=9)
        assert panel.i_since_refresh.value.startswith("0 steps ago")
        panel.update_period = 0.0

        panel.set_frusta_visible("initial", False)
        assert not any(handle.visible for handle in panel._handles["initial"].values())
        assert all(handle.visible for handle in panel._handles["reference"].values())

        # Clicking a refined frustum moves the view there with the refined focal length.
        event = fake_click()
        panel._go_to_camera(event, "refined", 2)
        position, wxyz, fov = panel._poses["refined"][2]
        assert event.client.camera.fov == pytest.approx(float(vertical_field_of_view(refined)[2]))
        assert event.client.camera.position == pytest.approx(position)
        assert event.client.camera.wxyz == pytest.approx(wxyz)
        assert viewer.current_camera_idx == 2

        # nerfstudio's own image frusta (drawn when training starts) get the refined field of view on click too.
        handle = viewer.viser_server.scene.add_camera_frustum("/cameras/camera_00003", fov=1.0, aspect=1.0)
        viewer.camera_handles = {3: handle}
        callback.func(step=10)
        assert len(handle._impl.click_cb) == 1
        event = fake_click()
        handle._impl.click_cb[0](event)
        assert event.client.camera.fov == pytest.approx(panel._poses["refined"][3][2])
        assert not panel._failed


def test_unperturbed_cameras_hide_the_initial_and_reference_sets_and_ns_viewer_has_no_refresh():
    model = build_model(initial=tiny_cameras())
    panel: S2CampViewerPanel = model.S2CamP
    with viewer_with(model, training=False) as viewer:
        assert panel.j_refresh_now.gui_handle.disabled  # ns-viewer: no training step would apply it
        assert viewer.header_steps == []  # ns-viewer keeps nerfstudio's own header (the checkpoint's step)
        assert not panel.l_show_initial.gui_handle.visible and not panel.m_show_reference.gui_handle.visible
        assert panel._handles["initial"] == {} and panel._handles["reference"] == {}
        assert sorted(panel._handles["refined"]) == list(range(NUM_CAMERAS))
        assert float(panel.c_rotation_error.value.split(" / ")[1]) < 1e-4


def test_fisheye_frusta_get_the_fisheye_field_of_view_capped_for_drawing():
    """Equidistant fisheyes (no distortion): the vertical field of view is height / f. f = 12 px gives 2 rad, wider
    than a pinhole's 2 atan(12 / 12) = pi / 2; f = 7 px gives 3.43 rad, past 180 degrees, drawn and shown at
    MAX_DRAWN_FOV."""
    fisheye = CameraType.FISHEYE
    model = build_model(initial=tiny_cameras(0.02, 12.0, fisheye), reference=tiny_cameras(0.0, 7.0, fisheye))
    panel: S2CampViewerPanel = model.S2CamP
    with viewer_with(model):
        assert panel._poses["initial"][0][2] == pytest.approx(2.0)
        assert panel._poses["refined"][0][2] == pytest.approx(2.0)
        assert HEIGHT / 7.0 > MAX_DRAWN_FOV == pytest.approx(math.radians(170.0))
        assert all(pose[2] == pytest.approx(MAX_DRAWN_FOV) for pose in panel._poses["reference"].values())
        event = fake_click()
        panel._go_to_camera(event, "reference", 1)
        assert event.client.camera.fov == pytest.approx(MAX_DRAWN_FOV)


def test_a_panel_failure_never_stops_training(capsys):
    model = build_model()
    panel: S2CampViewerPanel = model.S2CamP
    with viewer_with(model):
        panel._guard(lambda: 1 / 0)
        assert not panel.attached
        assert model.viewer_panel_callbacks() == []
    assert "S2CamP viewer panel disabled" in capsys.readouterr().out


# ---------------------------------------------------------------------------------------- slow: a real browser
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--hide-scrollbars",
    "--mute-audio",
]
VIEWPORT = (1400, 1400)
PANEL_JS = """(() => {
  const out = {};
  for (const label of document.querySelectorAll('label')) {
    const row = label.closest('.mantine-Flex-root');
    const input = row && row.querySelector('input');
    if (input) out[label.innerText.trim()] = input.type === 'checkbox' ? String(input.checked) : input.value;
  }
  out.__text__ = document.body.innerText;
  return JSON.stringify(out);
})()"""


@pytest.fixture(scope="session")
def chromium() -> str:
    """Debian's chromium; installed with apt-get when missing and running as root (as on CI)."""
    found = shutil.which("chromium")
    if found:
        return found
    if not hasattr(os, "geteuid") or os.geteuid() != 0 or shutil.which("apt-get") is None:
        pytest.skip("chromium is not installed and cannot be installed here (needs root and apt-get)")
    environment = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    output = ""
    for command in (
        ["apt-get", "install", "-y", "chromium"],
        ["apt-get", "update"],
        ["apt-get", "install", "-y", "chromium"],
    ):
        result = subprocess.run(command, capture_output=True, text=True, env=environment, timeout=HANG_GUARD_S)
        output = result.stdout[-1500:] + result.stderr[-1500:]
        if command[1] == "install" and result.returncode == 0 and shutil.which("chromium"):
            return str(shutil.which("chromium"))
    pytest.skip(f"chromium could not be installed with apt-get: {output.strip()[-600:]}")


def stop_process_group(process: subprocess.Popen, name: str) -> signal.Signals | None:
    """SIGINT (ns-train's Ctrl+C), then SIGTERM, then SIGKILL to the process's group; assert nothing is left.

    Returns the signal that ended the process (None if it had already exited).
    """
    stopped_by = None
    for sig, wait in ((signal.SIGINT, 60), (signal.SIGTERM, 20), (signal.SIGKILL, 10)):
        if process.poll() is not None:
            break
        stopped_by = sig
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, sig)
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=wait)
    process.wait(timeout=10)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        try:
            os.killpg(process.pid, 0)
        except ProcessLookupError:
            return stopped_by
        time.sleep(0.2)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGKILL)
    pytest.fail(f"{name} left processes behind in its process group")


TEST_SETUP = (
    "--pipeline.datamanager.train-num-rays-per-batch", "256",
    "--pipeline.model.hidden-dim", "16",
    "--pipeline.model.hidden-dim-color", "16",
    "--pipeline.model.num-levels", "4",
    "--pipeline.model.log2-hashmap-size", "12",
    "--pipeline.model.num-nerf-samples-per-ray", "8",
    "--pipeline.model.num-proposal-samples-per-ray", "8", "8",
    "--pipeline.model.camera-optimizer.parameters", "pose+focal",
    "--pipeline.model.camera-optimizer.refresh-every", "0",
    "--optimizers.camera-opt.optimizer.lr", "5e-4",
    "--optimizers.camera-opt.scheduler.warmup-steps", "0",
    "--pipeline.model.camera-optimizer.track-prior", "False",
)  # fmt: skip
"""The test's field (small enough for a CPU test) and cameras (moving from the first step, so the panel's errors
change within seconds; the default track prior would put them at the generated scene's exact tracks at once)."""


def s2camp_command(
    scene: Path, output_dir: Path, run_arguments: Sequence[str], setup_arguments: Sequence[str]
) -> list[str]:
    """``ns-train s2camp`` on ``scene`` from perturbed cameras."""
    ns_train = Path(sys.executable).with_name("ns-train")
    return [
        str(ns_train) if ns_train.exists() else "ns-train",
        "s2camp",
        "--data", str(scene),
        "--output-dir", str(output_dir),
        *run_arguments,
        "--steps-per-eval-batch", "0",
        "--steps-per-eval-image", "0",
        "--steps-per-eval-all-images", "0",
        "--mixed-precision", "False",
        "--pipeline.model.implementation", "torch",
        *setup_arguments,
        "--pipeline.model.viewer-update-period", "0.5",
        "s2camp-data",
        "--perturbation.enabled", "True",
    ]  # fmt: skip


def train_for_screenshot(scene: Path, output_dir: Path) -> Path:
    """Train ``SCREENSHOT_STEPS`` steps without the viewer (a headless browser drawing the viewer would take a CPU
    core from the training it waits for); return the checkpoint folder the viewer run continues from."""
    timestamp = "screenshot-training"
    run_arguments = (
        "--timestamp", timestamp,
        "--max-num-iterations", str(SCREENSHOT_STEPS),
        "--steps-per-save", str(SCREENSHOT_STEPS),
        "--vis", "tensorboard",
    )  # fmt: skip
    log_path = output_dir / f"{timestamp}.log"
    with open(log_path, "w") as log:
        command = s2camp_command(scene, output_dir, run_arguments, SCREENSHOT_SETUP)
        result = subprocess.run(command, stdout=log, stderr=subprocess.STDOUT, cwd=output_dir)
    checkpoints = sorted(output_dir.glob(f"*/s2camp/{timestamp}/nerfstudio_models"))
    assert result.returncode == 0 and checkpoints, f"the screenshot's training run failed: {log_path}"
    return checkpoints[0]


@contextlib.contextmanager
def ns_train_with_viewer(
    scene: Path,
    output_dir: Path,
    port: int,
    log_path: Path,
    setup_arguments: Sequence[str] = TEST_SETUP,
    load_dir: Path | None = None,
) -> Iterator[subprocess.Popen]:
    run_arguments = (
        "--timestamp", "viewer-test",
        "--max-num-iterations", "100000",
        "--steps-per-save", "100000",
        *(("--load-dir", str(load_dir)) if load_dir is not None else ()),
        "--vis", "viewer",
        "--viewer.websocket-host", "127.0.0.1",
        "--viewer.websocket-port", str(port),
        "--viewer.quit-on-train-completion", "True",
        "--viewer.camera-frustum-scale", "0.6",
    )  # fmt: skip
    command = s2camp_command(scene, output_dir, run_arguments, setup_arguments)
    environment = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with open(log_path, "w") as log:
        process = subprocess.Popen(
            command, stdout=log, stderr=subprocess.STDOUT, env=environment, start_new_session=True, cwd=output_dir
        )
        try:
            yield process
        finally:
            process.stopped_by = stop_process_group(process, "ns-train")  # type: ignore[attr-defined]


def wait_for_http(url: str, process: subprocess.Popen, log_path: Path, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            pytest.fail(f"ns-train exited with {process.returncode}:\n{log_path.read_text()[-3000:]}")
        with contextlib.suppress(OSError), urllib.request.urlopen(url, timeout=2) as response:
            if response.status == 200:
                return
        time.sleep(0.5)
    pytest.fail(f"the viewer did not answer at {url} within {timeout:.0f} s:\n{log_path.read_text()[-3000:]}")


class DevTools:
    """The few Chrome DevTools Protocol calls the test needs, over the page's websocket."""

    def __init__(self, url: str) -> None:
        from websockets.sync.client import connect

        self._socket = connect(url, max_size=None, open_timeout=30)
        self._next_id = 0

    def call(self, method: str, timeout: float = 60, **params) -> dict:
        self._next_id += 1
        self._socket.send(json.dumps({"id": self._next_id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout
        while True:
            message = json.loads(self._socket.recv(timeout=max(deadline - time.monotonic(), 0.1)))
            if message.get("id") == self._next_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]

    def evaluate(self, expression: str):
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True)["result"].get("value")

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.call("Browser.close", timeout=10)
        self._socket.close()


@contextlib.contextmanager
def headless_chromium(chromium: str, url: str, profile: Path) -> Iterator[DevTools]:
    profile.mkdir(parents=True, exist_ok=True)
    port_file = profile / "DevToolsActivePort"
    port_file.unlink(missing_ok=True)
    command = [chromium, *CHROMIUM_FLAGS, "--remote-debugging-port=0", f"--user-data-dir={profile}"]
    command += [f"--window-size={VIEWPORT[0]},{VIEWPORT[1]}", url]
    process = subprocess.Popen(
        command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True, text=True
    )
    devtools = None
    try:
        deadline = time.monotonic() + 60
        while not port_file.exists() or not port_file.read_text().strip():
            if process.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"chromium did not start: {process.stderr.read()[-2000:] if process.stderr else ''}")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as response:
            pages = [target for target in json.load(response) if target["type"] == "page"]
        devtools = DevTools(pages[0]["webSocketDebuggerUrl"])
        width, height = VIEWPORT
        devtools.call(
            "Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False
        )
        yield devtools
    finally:
        if devtools is not None:
            devtools.close()
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=15)
        if process.stderr is not None:
            process.stderr.close()
        stop_process_group(process, "chromium")


def read_panel(devtools: DevTools) -> dict[str, str]:
    """Label -> value of the page's GUI rows (empty while the page is still loading)."""
    value = devtools.evaluate(PANEL_JS)
    return json.loads(value) if isinstance(value, str) else {}


def wait_for(devtools: DevTools, condition, timeout: float, what: str) -> dict[str, str]:
    deadline = time.monotonic() + timeout
    values: dict[str, str] = {}
    while time.monotonic() < deadline:
        values = read_panel(devtools)
        if condition(values):
            return values
        time.sleep(1.0)
    shown = {key: value for key, value in values.items() if key != "__text__"}
    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}; the panel showed {shown}")


def click_button(devtools: DevTools, text: str) -> bool:
    """Click the page's button labelled ``text``; False if there is none."""
    return bool(
        devtools.evaluate(
            "(() => { const b = Array.from(document.querySelectorAll('button'))"
            f".find(b => b.innerText.trim() === {json.dumps(text)}); if (b) b.click(); return !!b; }})()"
        )
    )


def click_checkbox(devtools: DevTools, label: str) -> bool:
    """Click the checkbox of the GUI row labelled ``label``; False if there is none."""
    return bool(
        devtools.evaluate(
            "(() => { const l = Array.from(document.querySelectorAll('label'))"
            f".find(l => l.innerText.trim() === {json.dumps(label)});"
            " const i = l && l.closest('.mantine-Flex-root').querySelector('input[type=checkbox]');"
            " if (i) i.click(); return !!i; })()"
        )
    )


def render_width(values: dict[str, str]) -> int:
    """Width of the last image nerfstudio rendered into the view ("Resolution: WxHpx"; 0 if none)."""
    match = re.search(r"Resolution: (\d+)[x×]", values.get("__text__", ""))
    return int(match.group(1)) if match else 0


def panel_step(values: dict[str, str]) -> int:
    match = re.match(r"step (\d+) ", values.get("Status", ""))
    return int(match.group(1)) if match else -1


def steps_since_refresh(values: dict[str, str]) -> int:
    match = re.match(r"(\d+) steps ago", values.get("P refreshed", ""))
    return int(match.group(1)) if match else -1


def last_refresh_step(values: dict[str, str]) -> int:
    """Training step of the last refresh of P that the panel shows (-1 if it shows none)."""
    since = steps_since_refresh(values)
    return panel_step(values) - since if since >= 0 and panel_step(values) >= 0 else -1


def header_step(values: dict[str, str]) -> int:
    """The step in nerfstudio's "Step: N" line above its controls (-1 if absent)."""
    match = re.search(r"Step: (\d+)", values.get("__text__", ""))
    return int(match.group(1)) if match else -1


def capture(devtools: DevTools) -> bytes:
    return base64.b64decode(devtools.call("Page.captureScreenshot", format="png")["data"])


def view_pixels(png: bytes):
    """RGB array of the 3D view (the page left of nerfstudio's control panel, below its header)."""
    import io

    import numpy as np
    from PIL import Image

    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)
    return pixels[60:, : int(VIEWPORT[0] * 0.76)]


def wait_for_still_view(devtools: DevTools, timeout: float) -> bytes:
    """A screenshot once two in a row, two seconds apart, are identical (the view's renders have finished; the last
    one taken when ``timeout`` runs out)."""
    previous, deadline = capture(devtools), time.monotonic() + timeout
    while time.monotonic() < deadline:
        time.sleep(2.0)
        current = capture(devtools)
        if current == previous:
            return current
        previous = current
    return previous


def frustum_click_points(png: bytes) -> list[tuple[int, int]]:
    """Page points inside the panel's drawn frusta (amber, red, green, drawn over each other), largest frustum first:
    the centre of each one's bounding box and the mean of its pixels (one of them lies on nerfstudio's image plane
    at the frustum's base)."""
    import numpy as np
    from scipy import ndimage

    pixels = view_pixels(png)
    drawn = np.zeros(pixels.shape[:2], dtype=bool)
    for color in FRUSTUM_COLORS.values():  # anti-aliased lines: their colour blended with the view's
        drawn |= np.abs(pixels - np.array(color)).sum(axis=-1) < 150
    drawn &= (pixels.max(axis=-1) - pixels.min(axis=-1)) > 60  # saturated: not the grey or brown of the render
    drawn[-160:, :160] = False  # viser's axes gizmo in the bottom-left corner
    labels, count = ndimage.label(ndimage.binary_dilation(drawn, iterations=12))
    points = []
    for index in sorted(range(1, count + 1), key=lambda i: -int((labels == i).sum())):
        rows, cols = np.nonzero((labels == index) & drawn)
        if rows.size < 150:  # a few stray pixels, not a frustum
            continue
        for row, col in ((rows.min() + rows.max()) / 2, (cols.min() + cols.max()) / 2), (rows.mean(), cols.mean()):
            points.append((int(col), int(row) + 60))
    return points


def go_to_a_training_camera(devtools: DevTools, save_to: Path) -> list[tuple[int, int, float]]:
    """Click nerfstudio's image frusta where the refined frusta are drawn until the view jumps to a training camera
    (it then shows what the model learned from that image). The frusta are found in a screenshot of the view
    (written to ``save_to``) taken before nerfstudio's image frusta are shown over them. Returns each click (x, y,
    mean change of the view); the last one moved the view if its change exceeds ``VIEW_MOVED``."""
    before = wait_for_still_view(devtools, 30)
    save_to.write_bytes(before)
    assert click_button(devtools, "Show Train Cams")
    clicks = []
    for x, y in dict.fromkeys(frustum_click_points(before)):
        for kind in ("mousePressed", "mouseReleased"):
            devtools.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", buttons=1, clickCount=1)
        after = wait_for_still_view(devtools, 30)
        clicks.append((x, y, float(abs(view_pixels(after) - view_pixels(before)).mean())))
        if clicks[-1][2] > VIEW_MOVED or len(clicks) == 6:
            break
    return clicks


@pytest.mark.slow
# A hang guard, not a speed check. It includes installing chromium on a fresh machine; the test itself takes 1-2
# minutes. The screenshot's training run (``S2CAMP_UPDATE_SCREENSHOT=1``, not part of `make test`) comes on top: 7 to
# 35 minutes on a 2-core CPU, idle to busy, hence twice the guard.
@pytest.mark.timeout(2 * HANG_GUARD_S if UPDATING_SCREENSHOT else HANG_GUARD_S)
def test_viewer_panel_in_headless_chromium(chromium: str, tiny_scene: Path, tmp_path: Path):
    port = free_port()
    log_path = tmp_path / "ns-train.log"
    url = f"http://127.0.0.1:{port}/"
    screenshot = tmp_path / "viewer-screenshot.png"
    errors = ("Rotation °", "Position", "Focal px")
    number_pair = re.compile(r"[0-9.e+-]+ / [0-9.e+-]+")
    scene, setup_arguments, load_dir = tiny_scene, TEST_SETUP, None
    if UPDATING_SCREENSHOT:  # a scene, a field and a training run that show the scene in the viewer
        from s2camp_bench.scene.make_scene import MakeSceneConfig, make_scene

        scene = make_scene(MakeSceneConfig(output_dir=tmp_path / "data" / "screenshot-scene", **SCREENSHOT_SCENE))
        setup_arguments, load_dir = SCREENSHOT_SETUP, train_for_screenshot(scene, tmp_path)
    with ns_train_with_viewer(scene, tmp_path, port, log_path, setup_arguments, load_dir) as process:
        wait_for_http(url, process, log_path, timeout=180)
        with headless_chromium(chromium, url, tmp_path / "chromium-profile") as devtools:
            # On a CPU, pick nerfstudio's "Fast" train speed (256 px renders hold the training lock less long) and
            # zoom out to see the cameras.
            wait_for(devtools, lambda v: "Fast" in v.get("__text__", ""), 120, "the viewer's controls")
            assert click_button(devtools, "Fast")
            for _ in range(8):
                devtools.call("Input.dispatchMouseEvent", type="mouseWheel", x=500, y=600, deltaX=0, deltaY=200)

            first = wait_for(devtools, lambda v: panel_step(v) > 0, 120, "the S2CamP panel to show a training step")
            # Training runs, so nerfstudio has drawn its image frusta: hide them, they cover the panel's coloured
            # ones (before that, nerfstudio 1.1.5's button raises inside viser's atomic() and freezes the viewer),
            # and draw the frusta over the rendered image rather than depth-composited into it.
            assert click_button(devtools, "Hide Train Cams") and click_checkbox(devtools, "Composite depth")
            assert "S2CamP" in first["__text__"] and "Refresh P now" in first["__text__"]
            assert first["Cam. error"] == "mean / max" and first["Precond."] == "mean / worst"
            for label in (*errors, "cond Σ", "cond P⁻¹ΣP⁻¹"):
                assert number_pair.fullmatch(first[label]), (label, first[label])
            for label in ("Refined (amber)", "Initial (red)", "Reference (green)"):
                assert first[label] == "true", label

            # The values follow training: a later step, and the camera errors move (not checked for the screenshot:
            # its cameras sit at the track prior's anchor, where they move less than the panel's digits show).
            later = wait_for(
                devtools,
                lambda v: (
                    panel_step(v) > panel_step(first)
                    and (UPDATING_SCREENSHOT or any(v[key] != first[key] for key in errors))
                ),
                150,
                "the panel's step and camera errors to change",
            )
            assert steps_since_refresh(later) > steps_since_refresh(first) >= 0

            # "Refresh P now": the refresh happens at a training step after the click. Compared as the step of the
            # last refresh, not as the "steps ago" count: on a fast machine more steps pass between two polls of the
            # panel than passed between the initial refresh and the click (seen in CI: refresh at step 10, never
            # "fewer steps ago" than the 8 read before the click).
            clicked_after = panel_step(later)
            assert last_refresh_step(later) < clicked_after
            assert click_button(devtools, "Refresh P now")
            wait_for(devtools, lambda v: last_refresh_step(v) >= clicked_after, 150, "P to be refreshed")

            assert click_button(devtools, "Pause Training")
            # nerfstudio's "Step: N" line agrees with the panel (nerfstudio alone would still say 0 here): the panel
            # sets it, and nerfstudio's own training-step renders only ever set a later step.
            paused = wait_for(
                devtools, lambda v: header_step(v) >= panel_step(v) > 0, 30, "the header's step to follow the panel"
            )
            assert header_step(paused) >= panel_step(paused) >= panel_step(later)

            # For the screenshot (not part of what is tested): the view is rendered again only when the camera moves
            # (or every thousand or more steps at "Fast" on a CPU), so it still shows the model of the first steps,
            # a grey fog. Moving to a training camera renders the trained model from a view it has learned.
            if UPDATING_SCREENSHOT:
                clicks = go_to_a_training_camera(devtools, tmp_path / "before-click.png")
                assert clicks and clicks[-1][2] > VIEW_MOVED, f"no click moved the view to a camera: {clicks}"
                assert click_button(devtools, "Hide Train Cams")
                # No step forward from there: the wheel's dolly towards the orbit target took the view down to the
                # ground (a blur of terrain in the screenshot of that version). The full-size render follows the
                # quick low-resolution one of the jump.
                time.sleep(3.0)
                with contextlib.suppress(pytest.fail.Exception):
                    wait_for(devtools, lambda v: render_width(v) >= 100, 120, "a full-size render")
            screenshot.write_bytes(wait_for_still_view(devtools, 90 if UPDATING_SCREENSHOT else 20))
        assert process.poll() is None, "ns-train exited while the viewer was open"
    # Ctrl+C, or else SIGTERM, stopped it and left no process behind (stop_process_group checks). Once a viewer client
    # has been rendered to, ns-train may end with "terminate called without an active exception", exit status -6
    # (seen with the S2CamP panel disabled too), or, seen once in a full-suite run and not when run alone, not react
    # to SIGINT within a minute while paused; both are nerfstudio's shutdown path, not what this test checks.
    assert process.stopped_by in (signal.SIGINT, signal.SIGTERM), process.stopped_by
    assert screenshot.stat().st_size > 10_000
    print(f"viewer screenshot: {screenshot}")
    if UPDATING_SCREENSHOT:
        SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(screenshot, SCREENSHOT)
