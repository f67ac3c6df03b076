"""Method registration (`ns-train s2camp`, `ns-train s2camp-camp`) and the model wiring, on tiny inputs."""

from __future__ import annotations

import dataclasses
import io
import math
import re
import warnings
from contextlib import redirect_stdout
from importlib.metadata import entry_points

import pytest
import torch
import tyro
from conftest import lpips_offline, tiny_model_config
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.plugins.types import MethodSpecification

from s2camp_ns import method_config
from s2camp_ns.camera_optimizer import TRAIN_CAMERA_KEY, S2CampCameraOptimizerConfig
from s2camp_ns.core.preconditioner import SamplingConfig
from s2camp_ns.method.datamanager import S2CampDataManagerConfig
from s2camp_ns.method.model import S2CampModel, S2CampModelConfig
from s2camp_ns.method.pipeline import S2CampPipelineConfig
from s2camp_ns.method.rays import PIXEL_KEY
from s2camp_ns.method.trainer import S2CampTrainer, S2CampTrainerConfig


def test_method_specifications():
    for spec, name in ((method_config.s2camp_method, "s2camp"), (method_config.s2camp_camp_method, "s2camp-camp")):
        assert isinstance(spec, MethodSpecification) and isinstance(spec.config, S2CampTrainerConfig)
        assert spec.config._target is S2CampTrainer  # atomic checkpoints
        assert spec.config.method_name == name and spec.description
        pipeline = spec.config.pipeline
        assert isinstance(pipeline, S2CampPipelineConfig)
        assert isinstance(pipeline.datamanager, S2CampDataManagerConfig)
        assert isinstance(pipeline.model, S2CampModelConfig)
        assert isinstance(pipeline.model.camera_optimizer, S2CampCameraOptimizerConfig)
        assert "camera_opt" in spec.config.optimizers
        assert spec.config.machine.device_type == ("cuda" if torch.cuda.is_available() else "cpu")


def test_shipped_camera_optimizers_are_the_config_defaults():
    """s2camp ships the config's defaults (track prior on, common rotation removed); s2camp-splat changes only the
    refined groups, as its model config's own default does; the CamP baseline switches both off."""
    from s2camp_ns.method.splat_model import S2CampSplatModelConfig

    defaults = S2CampCameraOptimizerConfig()
    assert (defaults.track_prior, defaults.fix_common_rotation, defaults.pose_prior_exponent) == (True, True, 1.0)
    assert method_config.s2camp_method.config.pipeline.model.camera_optimizer == defaults
    assert S2CampModelConfig().camera_optimizer == defaults
    splat = S2CampCameraOptimizerConfig(parameters="pose+intrinsics")
    assert method_config.s2camp_splat_method.config.pipeline.model.camera_optimizer == splat
    assert S2CampSplatModelConfig().camera_optimizer == splat
    camp = method_config.s2camp_camp_method.config.pipeline.model.camera_optimizer
    assert (camp.track_prior, camp.fix_common_rotation) == (False, False)


def test_camp_baseline_differs_only_in_camera_sampling():
    s2camp = method_config.s2camp_method.config
    camp = method_config.s2camp_camp_method.config
    camp_camera = camp.pipeline.model.camera_optimizer
    s2camp_camera = s2camp.pipeline.model.camera_optimizer
    camp_sampling, s2camp_sampling = camp_camera.sampling, s2camp_camera.sampling
    assert (camp_sampling.sampler, camp_sampling.num_points, camp_camera.refresh_every) == ("camp-random", 5000, 0)
    assert (s2camp_sampling.sampler, s2camp_sampling.num_points, s2camp_sampling.transform) == (
        "frolov",
        500,
        "pyramid",
    )
    # S2CamP chooses its range from the scene (both ends unset, 0.4 / 1.5 without points); none of it leaks into
    # the baseline: CamP keeps its published, fixed ray distances and ladder.
    assert (s2camp_sampling.radial, s2camp_sampling.t_near, s2camp_sampling.t_far) == ("volume", None, None)
    assert s2camp_sampling.auto and s2camp_sampling.fixed_range() == (0.4, 1.5)
    assert (camp_sampling.t_near, camp_sampling.t_far, camp_sampling.ladder_p) == (0.4, 1000.0, -1.5)
    assert not camp_sampling.auto
    assert (camp_camera.damping.damping_abs, camp_camera.damping.damping_rel) == (1e-8, 0.1)
    # CamP refines intrinsics per image with the symmetric root per image; S2CamP's default shares them per camera.
    assert (camp_camera.intrinsics, s2camp_camera.intrinsics) == ("per-image", "per-camera")
    # s2camp keeps good cameras in place by default (track prior, common rotation removed); CamP's code has neither.
    assert (s2camp_camera.track_prior, s2camp_camera.fix_common_rotation) == (True, True)
    assert (camp_camera.track_prior, camp_camera.fix_common_rotation) == (False, False)
    aligned = dataclasses.replace(
        camp,
        method_name=s2camp.method_name,
        pipeline=dataclasses.replace(
            camp.pipeline,
            model=dataclasses.replace(camp.pipeline.model, camera_optimizer=s2camp_camera),
        ),
    )
    assert repr(aligned) == repr(s2camp)


def test_cli_help_documents_at_most_twelve_camera_optimizer_options():
    """What a user may set on the camera optimizer fits on a screen: nerfstudio's mode and L2 penalties and nine
    of S2CamP's; the proxy points and the damping are internal (CamP's sampling is the s2camp-camp method)."""
    config = method_config.s2camp_method.config
    out = io.StringIO()
    with redirect_stdout(out), pytest.raises(SystemExit) as exit_info:
        tyro.cli(type(config), default=config, args=["pipeline.model.camera-optimizer", "--help"], console_outputs=True)
    assert exit_info.value.code == 0
    text = out.getvalue()
    prefix = "--pipeline.model.camera-optimizer."
    flags = {flag.removeprefix("no-") for flag in re.findall(re.escape(prefix) + r"([a-z0-9_.-]+)", text)}
    assert flags - {"_target"} == {
        "mode", "trans-l2-penalty", "rot-l2-penalty", "parameters", "intrinsics", "precondition", "refresh-every",
        "track-prior", "pose-prior-exponent", "photometric", "fix-common-rotation",
    }  # fmt: skip
    assert "whitened" in text and "tracks" in text


def test_entry_points_registered():
    names = {ep.name: ep.value for ep in entry_points(group="nerfstudio.method_configs")}
    # Missing entry points mean a broken install (`ns-train s2camp` would not exist): fail, do not skip.
    assert "s2camp" in names, f"nerfstudio.method_configs holds {sorted(names)}: run `make venv` (pip install -e .)"
    assert names["s2camp"] == "s2camp_ns.method_config:s2camp_method"
    assert names["s2camp-camp"] == "s2camp_ns.method_config:s2camp_camp_method"
    assert names["s2camp-so3xr3"] == "s2camp_ns.method_config:s2camp_so3xr3_method"
    assert names["s2camp-splat"] == "s2camp_ns.method_config:s2camp_splat_method"
    assert names["s2camp-splat-so3xr3"] == "s2camp_ns.method_config:s2camp_splat_so3xr3_method"


def test_so3xr3_baseline_differs_only_in_the_camera_optimizer():
    s2camp = method_config.s2camp_method.config
    baseline = method_config.s2camp_so3xr3_method.config
    assert type(baseline.pipeline.model.camera_optimizer) is CameraOptimizerConfig
    # atomic checkpoints for the baseline too
    assert isinstance(baseline, S2CampTrainerConfig) and baseline._target is S2CampTrainer
    assert baseline.pipeline.model.camera_optimizer.mode == "SO3xR3"
    # nerfacto's own camera schedule for raw se(3) units
    assert baseline.optimizers["camera_opt"]["optimizer"].lr == 1e-3
    replaced = dataclasses.replace(baseline.pipeline.model, camera_optimizer=s2camp.pipeline.model.camera_optimizer)
    assert replaced == s2camp.pipeline.model


# --------------------------------------------------------------------------------------------------- model wiring
NUM_CAMERAS, WIDTH, HEIGHT = 3, 32, 24


def tiny_cameras() -> Cameras:
    c2w = torch.eye(4)[:3].expand(NUM_CAMERAS, 3, 4).clone()
    c2w[:, 0, 3] = torch.tensor([-0.2, 0.0, 0.2])
    c2w[:, 2, 3] = 1.0
    return Cameras(
        camera_to_worlds=c2w,
        fx=30.0,
        fy=30.0,
        cx=16.0,
        cy=12.0,
        width=WIDTH,
        height=HEIGHT,
        distortion_params=torch.tensor([-0.02, 0.0, 0.0, 0.0, 0.0, 0.0]).expand(NUM_CAMERAS, 6).clone(),
        camera_type=CameraType.PERSPECTIVE,
    )


@pytest.fixture(scope="module")
def tiny_model() -> S2CampModel:
    """A nerfacto-sized-down S2CampModel on the CPU with LPIPS made unavailable (offline behaviour)."""
    with lpips_offline():
        config = tiny_model_config(
            S2CampCameraOptimizerConfig(sampling=SamplingConfig(num_points=64, sampler="camp-random")),
            num_levels=4,
            log2_hashmap_size=12,
            hidden_dim=16,
        )
        model = config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=NUM_CAMERAS)
    model.camera_optimizer.set_train_cameras(tiny_cameras())
    return model


def test_every_param_group_receives_gradients(tiny_model: S2CampModel):
    """The grad scaler needs a gradient in every group (docs/DESIGN-NOTES.md sec. 9), camera_opt included."""
    tiny_model.train()
    generator = torch.Generator().manual_seed(0)
    num_rays = 64
    pixels = torch.rand(num_rays, 2, generator=generator) * torch.tensor([WIDTH, HEIGHT])
    bundle = RayBundle(
        origins=torch.zeros(num_rays, 3),
        directions=torch.tensor([0.0, 0.0, -1.0]).expand(num_rays, 3).clone(),
        pixel_area=torch.ones(num_rays, 1),
        camera_indices=torch.randint(0, NUM_CAMERAS, (num_rays, 1), generator=generator),
        metadata={PIXEL_KEY: pixels, "directions_norm": torch.ones(num_rays, 1)},
    )
    batch = {"image": torch.rand(num_rays, 3, generator=generator)}
    tiny_model.zero_grad()
    outputs = tiny_model(bundle)
    metrics = tiny_model.get_metrics_dict(outputs, batch)
    loss = sum(tiny_model.get_loss_dict(outputs, batch, metrics).values())
    loss.backward()
    groups = tiny_model.get_param_groups()
    assert set(groups) == {"proposal_networks", "fields", "camera_opt"}
    for name, params in groups.items():
        grads = [p.grad for p in params if p.grad is not None]
        assert grads and any(bool(g.abs().sum() > 0) for g in grads), name


def test_lpips_unavailable_is_omitted(tiny_model: S2CampModel):
    assert not tiny_model.lpips_available
    tiny_model.eval()
    camera = tiny_cameras()[0:1]
    camera.metadata = {TRAIN_CAMERA_KEY: 0}
    outputs = tiny_model.get_outputs_for_camera(camera)
    assert outputs["rgb"].shape == (HEIGHT, WIDTH, 3)
    metrics, images = tiny_model.get_image_metrics_and_images(outputs, {"image": torch.rand(HEIGHT, WIDTH, 3)})
    assert {"psnr", "ssim"} <= set(metrics) and "lpips" not in metrics
    assert "img" in images


def test_camera_errors_logged_with_reference_cameras(tiny_model: S2CampModel):
    """Reference cameras = the training cameras moved by a known similarity, focal lengths changed by known amounts:
    the aligned pose errors vanish, the raw ones are the similarity's, the focal errors are the changes."""
    cameras = tiny_cameras()
    angle, scale, shift = 0.3, 1.7, torch.tensor([0.5, -0.2, 0.1])
    rotation = torch.tensor(
        [[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0], [0.0, 0.0, 1.0]]
    )
    reference = tiny_cameras()
    reference.camera_to_worlds = torch.cat(
        [
            rotation @ cameras.camera_to_worlds[:, :, :3],
            (scale * rotation @ cameras.camera_to_worlds[:, :, 3:]) + shift[:, None],
        ],
        dim=-1,
    )
    reference.fx = cameras.fx + torch.tensor([[1.0], [-2.0], [0.5]])
    tiny_model.kwargs["metadata"] = {"reference_cameras": reference}
    try:
        errors = tiny_model.update_camera_errors()
        assert errors["camera_errors/aligned"] == 1.0
        assert errors["camera_errors/align_scale"] == pytest.approx(scale, rel=1e-5)
        assert errors["camera_errors/rot_err_max"] < 1e-5 and errors["camera_errors/pos_err_max"] < 1e-5
        assert errors["camera_errors/raw_rot_err_mean"] == pytest.approx(angle, rel=1e-5)
        assert errors["camera_errors/focal_err_mean"] == pytest.approx(3.5 / 3, rel=1e-6)
        assert errors["camera_errors/focal_err_max"] == pytest.approx(2.0, rel=1e-6)
        assert tiny_model._camera_errors == errors  # merged into the training metrics dict
    finally:
        tiny_model.kwargs["metadata"] = {}
        tiny_model._camera_errors = {}


def test_stock_optimizer_refined_cameras_follow_its_ray_correction():
    """s2camp-so3xr3: the camera the errors are computed for is the one nerfstudio's correction gives the rays."""
    with lpips_offline():
        model = tiny_model_config(
            CameraOptimizerConfig(mode="SO3xR3"), num_levels=4, log2_hashmap_size=12, hidden_dim=16
        ).setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=NUM_CAMERAS)
    cameras = tiny_cameras()
    model.set_train_cameras(cameras)
    assert not model.uses_s2camp_optimizer and not hasattr(model, "S2CamP")
    with torch.no_grad():
        model.camera_optimizer.pose_adjustment.copy_(
            torch.tensor([[0.01, -0.02, 0.03, 0.02, 0.01, -0.03], [0.0] * 6, [-0.05, 0.0, 0.01, 0.0, 0.04, 0.0]])
        )
    c2w, fx = model.refined_train_cameras()
    assert c2w.dtype == torch.float64 and torch.equal(fx, cameras.fx.reshape(-1).double())
    camera_indices = torch.arange(NUM_CAMERAS)[:, None].repeat(1, 4).reshape(-1, 1)
    directions = torch.nn.functional.normalize(
        torch.randn(camera_indices.shape[0], 3, generator=torch.Generator().manual_seed(1)), dim=-1
    )
    bundle = RayBundle(
        origins=cameras.camera_to_worlds[camera_indices[:, 0], :, 3].clone(),
        directions=directions.clone(),
        pixel_area=torch.ones(camera_indices.shape[0], 1),
        camera_indices=camera_indices,
    )
    with torch.no_grad():
        model.camera_optimizer.apply_to_raybundle(bundle)
    # a direction d_cam = R^T d in the camera frame leaves the refined camera as R' d_cam
    base = cameras.camera_to_worlds.double()[camera_indices[:, 0]]
    d_cam = (base[:, :, :3].transpose(1, 2) @ directions.double()[..., None])[..., 0]
    refined = c2w[camera_indices[:, 0]]
    expected = (refined[:, :, :3] @ d_cam[..., None])[..., 0]
    torch.testing.assert_close(bundle.directions.double(), expected, atol=1e-6, rtol=0)
    torch.testing.assert_close(bundle.origins.double(), refined[:, :, 3], atol=1e-6, rtol=0)
    assert model.update_camera_errors() == {}  # no reference cameras in this model's metadata


def test_mode_so3xr3_warns_that_it_means_se3_and_names_the_baseline():
    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig

    with pytest.warns(UserWarning, match=r"mode SO3xR3 means SE3 .* train s2camp-so3xr3"):
        S2CampCameraOptimizerConfig(mode="SO3xR3").setup(num_cameras=2, device="cpu")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        S2CampCameraOptimizerConfig(mode="SE3").setup(num_cameras=2, device="cpu")
