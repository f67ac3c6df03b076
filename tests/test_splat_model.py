"""``s2camp-splat``: splatfacto with the S2CamP camera optimizer (s2camp_ns/method/splat_model.py).

The view matrix of a refined training camera is checked against the core's projection of the refined camera
(``core.camera.project_with_delta``: pose and intrinsics deltas, no splatting code); the end-to-end test trains the
method on the CPU (reference rasterizer) on the tiny generated scene through nerfstudio's Trainer.
"""

from __future__ import annotations

import copy
import json
import math
import re
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.models.splatfacto import get_viewmat

from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
from s2camp_ns.core.camera import opengl_to_opencv, project_with_delta
from s2camp_ns.core.preconditioner import SamplingConfig
from s2camp_ns.method.splat_model import S2CampSplatModel, S2CampSplatModelConfig, world_to_camera

WIDTH, HEIGHT = 64, 48


def look_at_c2w(position: torch.Tensor) -> torch.Tensor:
    """OpenGL c2w (nerfstudio convention) looking from ``position`` at the origin."""
    backward = position / position.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), backward)
    right = right / right.norm()
    up = torch.linalg.cross(backward, right)
    return torch.cat([torch.stack([right, up, backward], dim=-1), position[:, None]], dim=-1)


def two_cameras() -> Cameras:
    positions = torch.tensor([[2.0, 0.3, 0.5], [-0.4, 2.1, 0.6]])
    return Cameras(
        camera_to_worlds=torch.stack([look_at_c2w(p) for p in positions]),
        fx=torch.tensor([[60.0], [61.0]]),
        fy=torch.tensor([[59.0], [62.0]]),
        cx=torch.tensor([[32.0], [31.0]]),
        cy=torch.tensor([[24.0], [24.5]]),
        width=WIDTH,
        height=HEIGHT,
        camera_type=CameraType.PERSPECTIVE,
    )


def test_world_to_camera_is_splatfactos_view_matrix_without_refinement():
    c2w = two_cameras().camera_to_worlds
    torch.testing.assert_close(world_to_camera(opengl_to_opencv(c2w.double())).float(), get_viewmat(c2w))


def test_view_matrix_projects_like_the_refined_camera():
    """K [A R' | A t'] X / z (what the rasterizer computes) = the refined camera's pixels from the core."""
    cameras = two_cameras()
    config = S2CampCameraOptimizerConfig(
        parameters="pose+intrinsics", intrinsics="per-image", sampling=SamplingConfig(num_points=64)
    )
    optimizer = config.setup(num_cameras=2, device="cpu")
    optimizer.set_train_cameras(cameras)
    with torch.no_grad():
        generator = torch.manual_seed(0)
        for latent in optimizer.parameters():
            latent.copy_(3e-3 * torch.randn(latent.shape, generator=generator))
    deltas = optimizer.refiner.deltas().detach()
    assert float(deltas[:, 6:10].abs().min()) > 0.05, "focal, principal point and skew must all be refined"
    model = SimpleNamespace(training=True, uses_s2camp_optimizer=True, camera_optimizer=optimizer)
    world = torch.randn(30, 3, dtype=torch.float64, generator=torch.manual_seed(1)) * 0.4
    for i in range(2):
        camera = cameras[i : i + 1]
        camera.metadata = {"cam_idx": i}
        viewmat = S2CampSplatModel.view_matrix(model, camera).double()
        y = (viewmat[0, :3, :3] @ world.T).T + viewmat[0, :3, 3]
        k = camera.get_intrinsics_matrices()[0].double()
        pixels = (k @ y.T).T
        pixels = pixels[:, :2] / pixels[:, 2:]
        base_w2c = world_to_camera(opengl_to_opencv(camera.camera_to_worlds.double()))[0]
        points_cam = (base_w2c[:3, :3] @ world.T).T + base_w2c[:3, 3]
        base = optimizer.refiner.base_intrinsics_struct()
        expected = project_with_delta(points_cam[None], base.to(dtype=torch.float64)[i : i + 1], deltas[i : i + 1])[0]
        torch.testing.assert_close(pixels, expected, rtol=1e-6, atol=1e-4)
        # A held-out or viewer camera (no cam_idx) renders as given.
        camera.metadata = None
        torch.testing.assert_close(S2CampSplatModel.view_matrix(model, camera), get_viewmat(camera.camera_to_worlds))


def test_distortion_refinement_is_refused_by_name():
    config = S2CampSplatModelConfig(camera_optimizer=S2CampCameraOptimizerConfig(parameters="all"))
    with pytest.raises(ValueError, match="parameters 'all' is not supported by s2camp-splat.*undistorted"):
        config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=2, metadata={})


@pytest.mark.slow
def test_s2camp_splat_trains_on_the_cpu(tiny_scene: Path, tmp_path: Path):
    """The method's own config, on the CPU, from CamP-perturbed cameras: training runs, splatfacto's densification
    acts on the refined cameras' projected-mean gradients, and pose and intrinsics move."""
    from s2camp_ns.method_config import s2camp_splat_method

    config = copy.deepcopy(s2camp_splat_method.config)
    config.data = tiny_scene
    config.pipeline.datamanager.data = tiny_scene
    config.pipeline.datamanager.dataparser.perturbation.enabled = True
    config.output_dir = tmp_path
    config.machine.device_type = "cpu"
    config.max_num_iterations = 40
    config.vis = "tensorboard"
    config.steps_per_eval_image = 1000
    config.steps_per_eval_all_images = 1000
    config.steps_per_save = 1000
    model_config = config.pipeline.model
    model_config.warmup_length = 10
    model_config.refine_every = 10
    model_config.camera_error_every = 10
    model_config.camera_optimizer.refresh_every = 20
    start = time.perf_counter()
    config.set_timestamp()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model
    assert isinstance(model, S2CampSplatModel)
    seeds = model.num_points
    base_fx = model.camera_optimizer.refiner.refined_intrinsics().fx.detach().clone()
    trainer.train()
    elapsed = time.perf_counter() - start
    optimizer = model.camera_optimizer
    # Growth (split / duplicate) needs the projected means' accumulated gradients above splatfacto's threshold.
    assert model.num_points > seeds, "the densification strategy must have grown Gaussians from means2d gradients"
    assert int(optimizer.refiner.num_refreshes) >= 2  # the initial P and the scheduled refresh at step 20
    deltas = optimizer.refiner.deltas().detach()
    assert float(deltas[:, :6].abs().amax()) > 0, "the pose must be refined"
    assert float((optimizer.refiner.refined_intrinsics().fx.detach() - base_fx).abs().amax()) > 1e-3
    assert float(deltas[:, 7:10].abs().amax()) > 0, "principal point and skew must be refined"
    errors = model.update_camera_errors()
    assert {"camera_errors/rot_err_mean", "camera_errors/pos_err_mean", "camera_errors/focal_err_mean"} <= set(errors)
    assert all(math.isfinite(v) for v in errors.values())
    # The export path of s2camp-export-cameras: the refined cameras of the splatting run, refined intrinsics included.
    from s2camp_ns.scripts.export_cameras import refined_training_cameras

    exported = refined_training_cameras(trainer.pipeline)
    torch.testing.assert_close(
        exported.fx.reshape(-1).double(), optimizer.refiner.refined_intrinsics().fx.detach().cpu(), rtol=1e-6, atol=1e-4
    )
    print(f"s2camp-splat, 40 CPU steps: {elapsed:.1f} s, {seeds} -> {model.num_points} Gaussians, {errors}")
    # s2camp-eval on the run's config.yml and final checkpoint: test-time alignment of the held-out views.
    from s2camp_ns.scripts.eval_aligned import EvalAlignedConfig
    from s2camp_ns.scripts.eval_aligned import main as eval_aligned
    from s2camp_ns.scripts.test_time_alignment import AlignmentConfig

    config.save_config()  # what ns-train writes before training
    output = tmp_path / "aligned.json"
    start = time.perf_counter()
    result = eval_aligned(
        EvalAlignedConfig(trainer.base_dir / "config.yml", output, alignment=AlignmentConfig(steps=5))
    )
    payload = json.loads(output.read_text())
    held_out = len(range(0, 12, 8))  # the tiny scene's 12 images, every 8th held out
    assert result["step"] == 39 and len(payload["views"]) == held_out and payload["alignment"]["steps"] == 5
    for view in payload["views"]:
        assert 5.0 < view["psnr"] < 60.0 and 0.0 < view["ssim"] <= 1.0
        assert view["focal_scale"] != 1.0 and any(value != 0.0 for value in view["twist"]), "the camera must move"
    print(f"s2camp-eval of the splat run, 5 steps: {time.perf_counter() - start:.1f} s, {payload['mean']}")


def test_declared_method_entry_points_resolve():
    """Every method pyproject.toml declares for ``ns-train`` imports as a MethodSpecification (the installed
    metadata follows pyproject.toml after ``pip install -e .``)."""
    import importlib

    from nerfstudio.plugins.types import MethodSpecification

    text = (Path(__file__).parents[1] / "pyproject.toml").read_text()
    section = text.split('[project.entry-points."nerfstudio.method_configs"]')[1].split("\n[")[0]
    methods = dict(re.findall(r'^(\S+) = "(\S+)"$', section, flags=re.MULTILINE))
    assert methods["s2camp-splat"] == "s2camp_ns.method_config:s2camp_splat_method"
    for name, target in methods.items():
        module, attribute = target.split(":")
        specification = getattr(importlib.import_module(module), attribute)
        assert isinstance(specification, MethodSpecification), name
        assert specification.config.method_name == name


def test_splat_baseline_differs_only_in_the_camera_optimizer():
    from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig

    from s2camp_ns.method_config import s2camp_splat_method, s2camp_splat_so3xr3_method

    splat, baseline = s2camp_splat_method.config, s2camp_splat_so3xr3_method.config
    assert splat.pipeline.model.camera_optimizer.parameters == "pose+intrinsics"
    # The measured splat defaults (docs/SPLAT.md sec. 6): the shared rotation removed, the track prior on.
    assert splat.pipeline.model.camera_optimizer.fix_common_rotation is True
    assert splat.pipeline.model.camera_optimizer.track_prior is True
    assert type(baseline.pipeline.model.camera_optimizer) is CameraOptimizerConfig
    assert baseline.pipeline.model.camera_optimizer.mode == "SO3xR3"
    assert baseline.optimizers["camera_opt"]["optimizer"].lr == 1e-4  # splatfacto's own camera schedule
    replaced = copy.deepcopy(baseline.pipeline.model)
    replaced.camera_optimizer = splat.pipeline.model.camera_optimizer
    assert replaced == splat.pipeline.model
    assert {k: v for k, v in baseline.optimizers.items() if k != "camera_opt"} == {
        k: v for k, v in splat.optimizers.items() if k != "camera_opt"
    }


def test_held_out_alignment_refuses_foreign_splatfacto_models_by_name_and_takes_ours():
    from nerfstudio.models.splatfacto import SplatfactoModel

    from s2camp_ns.scripts.splat_alignment import SplatRenderer
    from s2camp_ns.scripts.test_time_alignment import AlignmentConfig, evaluate_held_out_views, renderer_for

    pipeline = SimpleNamespace(model=object.__new__(SplatfactoModel))
    with pytest.raises(ValueError, match="is SplatfactoModel, a splatfacto model it does not support: use ns-eval"):
        evaluate_held_out_views(pipeline)
    assert isinstance(renderer_for(object.__new__(S2CampSplatModel), AlignmentConfig()), SplatRenderer)


def test_splat_training_step_on_emulated_cuda(tiny_scene: Path):
    """The s2camp-splat pipeline built on "cuda" (tests/fake_cuda.py: every op's devices checked by CUDA's rules)
    runs a training step with the reference rasterizer forced (gsplat's kernels need a real GPU): the refined
    camera's view matrix, the rasterizer, splatfacto's strategy hook, backward and the optimizers' step; then the
    held-out views of s2camp-eval (mapped, rendered and measured; no alignment steps)."""
    from fake_cuda import fake_cuda, is_fake_cuda, values
    from nerfstudio.engine.callbacks import TrainingCallbackAttributes
    from nerfstudio.engine.optimizers import Optimizers

    from s2camp_ns.method.trainer import with_run_length
    from s2camp_ns.method_config import s2camp_splat_method
    from s2camp_ns.scripts.test_time_alignment import AlignmentConfig, evaluate_held_out_views

    config = copy.deepcopy(s2camp_splat_method.config)
    config.pipeline.datamanager.data = tiny_scene
    config.pipeline.datamanager.dataparser.data = tiny_scene
    config.pipeline.datamanager.dataparser.perturbation.enabled = True
    config.pipeline.model.rasterizer = "reference"
    config.pipeline.model.camera_error_every = 1
    with fake_cuda():
        pipeline = config.pipeline.setup(device="cuda", test_mode="val")
        model = pipeline.model
        optimizers = Optimizers(with_run_length(config.optimizers, 100), pipeline.get_param_groups())
        callbacks = model.get_training_callbacks(TrainingCallbackAttributes(optimizers, None, pipeline, None))
        for callback in callbacks:  # splatfacto's step_cb (before the iteration) hands the strategy the optimizers
            if callback.where_to_run[0].name == "BEFORE_TRAIN_ITERATION":
                callback.run_callback_at_location(1, callback.where_to_run[0])
        camera, batch = pipeline.datamanager.next_train(1)
        outputs = model(camera)
        loss_dict = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))
        optimizers.zero_grad_all()
        sum(loss_dict.values()).backward()
        grad = model.camera_optimizer.refiner.whitened_intrinsics.grad
        means2d_grad = model.info["means2d"].grad
        latent_before = values(model.camera_optimizer.refiner.whitened_intrinsics).clone()
        optimizers.optimizer_step_all()
        # s2camp-eval's view construction, renders and metrics on "cuda"; steps=0: the emulation cannot run the
        # backward pass of the reference rasterizer's chained per-tile index_put (autograd's C++ zeros carry the
        # fake tensors' CPU options), which real CUDA does; the CUDA gradients are checked with gsplat in
        # tests/test_splat_alignment.py (marked cuda).
        aligned = evaluate_held_out_views(pipeline, AlignmentConfig(steps=0))
    assert is_fake_cuda(outputs["rgb"]) and is_fake_cuda(grad) and is_fake_cuda(means2d_grad)
    assert float(values(grad).abs().sum()) > 0, "the intrinsics get a gradient through the view matrix"
    assert float(values(means2d_grad).abs().sum()) > 0, "the strategy reads the projected means' gradient"
    assert not torch.equal(values(model.camera_optimizer.refiner.whitened_intrinsics), latent_before)
    assert len(aligned) == len(pipeline.datamanager.eval_dataset) and all(math.isfinite(v.psnr) for v in aligned)


def test_camera_errors_of_undistorted_training_cameras_use_the_undistorted_reference_focal():
    """Reference cameras come with the distorted K (fx 36), the model refines the undistorted images' K (fx 36.72):
    unrefined cameras equal to the reference have no focal error once the undistortion scale is known, and the
    0.72 px of the two units' difference without it."""
    from test_splat_alignment import splat_model

    model = splat_model(50, (1.0, 1.0, 1.0))
    c2w = two_cameras().camera_to_worlds

    def cameras(focal: float, distortion: torch.Tensor | None) -> Cameras:
        return Cameras(
            camera_to_worlds=c2w.float(), fx=focal, fy=focal, cx=20.0, cy=15.0, width=40, height=30,
            distortion_params=distortion, camera_type=CameraType.PERSPECTIVE,
        )  # fmt: skip

    distortion = torch.tensor([[0.05, 0.0, 0.0, 0.0, 0.0, 0.0]]).expand(2, 6)
    model.kwargs["metadata"] = {"reference_cameras": cameras(36.0, distortion)}
    model.set_train_cameras(cameras(36.72, None))
    assert model.update_camera_errors()["camera_errors/focal_err_mean"] == pytest.approx(0.72, abs=1e-4)
    model.set_undistortion_scale(torch.full((2,), 1.02), torch.full((2,), 1.02))
    reference = model.reference_cameras()
    assert reference.distortion_params is None and torch.allclose(reference.fx, torch.full((2, 1), 36.72))
    assert model.update_camera_errors()["camera_errors/focal_err_mean"] == pytest.approx(0.0, abs=1e-4)


def test_undistorted_cameras_keep_the_given_anchor_and_the_tracks_standard_error():
    """Distorted SfM cameras: the model refines the undistorted pinhole camera, which the tracks' (distorted) pixels
    do not fit, so no refit anchor; the poses and the shared intrinsics still count each image's tracks for their
    standard errors, r_i / sqrt(2 O_i) and sqrt(sum O_i r_i^2) / (sqrt(2) sum O_i) (here 30 and 10 tracks of RMS
    0.4 and 0.8 px, width 40)."""
    from test_splat_alignment import splat_model

    from s2camp_ns.core.track_fit import TrackEvidence
    from s2camp_ns.core.tracks import Tracks

    model = splat_model(50, (1.0, 1.0, 1.0))
    model.camera_optimizer.config.track_prior = True
    c2w = two_cameras().camera_to_worlds
    distortion = torch.tensor([[0.05, 0.0, 0.0, 0.0, 0.0, 0.0]]).expand(2, 6)
    cameras = Cameras(
        camera_to_worlds=c2w.float(), fx=36.0, fy=36.0, cx=20.0, cy=15.0, width=40, height=30,
        distortion_params=distortion, camera_type=CameraType.PERSPECTIVE,
    )  # fmt: skip
    image = torch.cat([torch.zeros(30, dtype=torch.long), torch.ones(10, dtype=torch.long)])
    tracks = Tracks(torch.zeros(40, 3), image, torch.arange(40), torch.zeros(40, 2))
    evidence = TrackEvidence(tracks, c2w.double(), 1.0)
    rms = torch.tensor([0.4, 0.8], dtype=torch.float64)
    model.set_train_cameras(cameras, track_rms_px=rms, track_evidence=evidence)
    optimizer = model.camera_optimizer
    assert bool((optimizer.refiner.prior_anchor == 0).all())  # the given cameras: no refit against the distorted pixels
    # Each pose the standard error of its own tracks, r_i / sqrt(2 O_i).
    poses = [0.4 / 40 / math.sqrt(2 * 30), 0.8 / 40 / math.sqrt(2 * 10)]
    assert optimizer.refiner.prior_radius.tolist() == pytest.approx(poses, rel=1e-12)
    expected = math.sqrt(30 * 0.4**2 + 10 * 0.8**2) / (math.sqrt(2) * 40) / 40
    assert optimizer.refiner.prior_radius_intrinsics.tolist() == pytest.approx([expected], rel=1e-12)


def test_undistortion_scale_is_the_data_managers_focal_over_the_dataparsers():
    from s2camp_ns.method.pipeline import undistortion_scale

    given = SimpleNamespace(fx=torch.tensor([[36.0], [36.0]]), fy=torch.tensor([[30.0], [30.0]]))
    seen = SimpleNamespace(fx=torch.tensor([[36.72], [36.0]]), fy=torch.tensor([[30.3], [30.0]]))
    datamanager = SimpleNamespace(
        train_dataset=SimpleNamespace(cameras=seen), train_dataparser_outputs=SimpleNamespace(cameras=given)
    )
    fx_scale, fy_scale = undistortion_scale(datamanager)
    torch.testing.assert_close(fx_scale, torch.tensor([[1.02], [1.0]]))
    torch.testing.assert_close(fy_scale, torch.tensor([[1.01], [1.0]]))


def _built_splat_model(tiny_scene: Path, lpips) -> S2CampSplatModel:
    """The s2camp-splat model of the tiny scene's training split, torchmetrics' LPIPS class replaced by ``lpips``
    while it is built (the test's stand-in for the weights being or not being in torch's cache)."""
    import torchmetrics.image.lpip as lpip_module

    from s2camp_ns.data.dataparser import S2CampDataParserConfig

    outputs = S2CampDataParserConfig(data=tiny_scene).setup().get_dataparser_outputs("train")
    xyz, rgb = outputs.metadata["points3D_xyz"], outputs.metadata["points3D_rgb"]
    config = S2CampSplatModelConfig(use_bilateral_grid=True)
    original = lpip_module.LearnedPerceptualImagePatchSimilarity
    lpip_module.LearnedPerceptualImagePatchSimilarity = lpips
    try:
        torch.manual_seed(0)
        return config.setup(
            scene_box=outputs.scene_box, num_train_data=len(outputs.image_filenames), metadata=outputs.metadata,
            seed_points=(xyz, rgb),
        )  # fmt: skip
    finally:
        lpip_module.LearnedPerceptualImagePatchSimilarity = original


def test_without_lpips_the_splat_model_is_what_splatfacto_builds_with_it(tiny_scene: Path):
    """Where LPIPS cannot load its weights, the splat model builds what nerfstudio 1.1.5's splatfacto builds after
    LPIPS (``splat_model.finish_without_lpips``): the same step, crop box, background, bilateral grids, densification
    strategy and state; its ``lpips`` is None and its image metrics leave LPIPS out."""

    def offline(*args, **kwargs):
        raise OSError("no network (simulated)")

    online = _built_splat_model(tiny_scene, lambda *args, **kwargs: torch.nn.Identity())
    without = _built_splat_model(tiny_scene, offline)
    assert without.lpips is None and not without.lpips_available and online.lpips_available
    assert (without.step, without.crop_box) == (online.step, online.crop_box) == (0, None)
    assert torch.equal(without.background_color, online.background_color)
    assert type(without.strategy) is type(online.strategy) and vars(without.strategy) == vars(online.strategy)
    assert without.strategy_state.keys() == online.strategy_state.keys()
    assert type(without.bil_grids) is type(online.bil_grids)
    assert without.state_dict().keys() == online.state_dict().keys()
    for name, value in online.state_dict().items():
        assert without.state_dict()[name].shape == value.shape, name
