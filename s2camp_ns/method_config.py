"""The ``ns-train`` methods, registered through the ``nerfstudio.method_configs`` entry point.

Nerfacto with joint pose + intrinsics refinement, differing only in the camera optimizer:

- ``s2camp``: deterministic Frolov-lattice points in each camera's frustum, P refreshed during training (paper
  sec. 4), the common rotation removed and the track prior on (``S2CAMP_CAMERA_OPTIMIZER``);
- ``s2camp-camp``: the CamP baseline: random points, P computed once, no track prior, no common-rotation removal;
- ``s2camp-so3xr3``: nerfstudio's stock SO3xR3 pose optimizer with nerfacto's camera learning rate.

``s2camp-splat`` and ``s2camp-splat-so3xr3`` are the same for splatfacto. All train with ``S2CampTrainer`` in the
S2CamP pipeline, on the CPU where CUDA is missing.
"""

from __future__ import annotations

import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanagerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.plugins.types import MethodSpecification

import s2camp_ns.compat  # noqa: F401  (earlier runs' config.yml name classes by their old module paths)
from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
from s2camp_ns.core.preconditioner import CAMP_SAMPLING, DampingConfig
from s2camp_ns.data.dataparser import S2CampDataParserConfig
from s2camp_ns.method.datamanager import S2CampDataManagerConfig
from s2camp_ns.method.model import S2CampModelConfig
from s2camp_ns.method.pipeline import S2CampPipelineConfig
from s2camp_ns.method.schedulers import RunLengthScheduleConfig
from s2camp_ns.method.splat_model import S2CampSplatModelConfig
from s2camp_ns.method.trainer import S2CampTrainerConfig

DEFAULT_DEVICE_TYPE = "cuda" if torch.cuda.is_available() else "cpu"
"""nerfstudio's Trainer asserts CUDA for a "cuda" device: the CPU without CUDA."""


def camera_schedule_for(camera_optimizer: CameraOptimizerConfig) -> dict:
    """The "camera_opt" optimizer and schedule of a method: S2CamP's in whitened units, nerfacto's otherwise."""
    if isinstance(camera_optimizer, S2CampCameraOptimizerConfig):
        # Whitened units (a unit step moves the proxy projections by max(W, H) px RMS): rates hold at any
        # resolution. CamP's camera schedule, as fractions of the run.
        camera_schedule = {
            "optimizer": AdamOptimizerConfig(lr=1e-4, eps=1e-15),
            "scheduler": RunLengthScheduleConfig(lr_pre_warmup=1e-8, lr_final=1e-5),
        }
    else:
        # nerfacto's own camera schedule for its stock optimizer (raw se(3) units).
        camera_schedule = {
            "optimizer": AdamOptimizerConfig(lr=1e-3, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=5000),
        }
    return camera_schedule


def make_trainer_config(method_name: str, camera_optimizer: CameraOptimizerConfig) -> S2CampTrainerConfig:
    """Nerfacto's trainer settings with the S2CamP pipeline; only ``camera_optimizer`` differs between methods."""
    camera_schedule = camera_schedule_for(camera_optimizer)
    return S2CampTrainerConfig(
        method_name=method_name,
        steps_per_eval_batch=500,
        steps_per_save=2000,
        max_num_iterations=30000,
        mixed_precision=True,
        machine=MachineConfig(device_type=DEFAULT_DEVICE_TYPE),
        pipeline=S2CampPipelineConfig(
            datamanager=S2CampDataManagerConfig(
                dataparser=S2CampDataParserConfig(),
                train_num_rays_per_batch=4096,
                eval_num_rays_per_batch=4096,
            ),
            model=S2CampModelConfig(
                eval_num_rays_per_chunk=1 << 15,
                average_init_density=0.01,
                camera_optimizer=camera_optimizer,
            ),
        ),
        optimizers={
            "proposal_networks": {
                "optimizer": AdamOptimizerConfig(lr=1e-2, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=0.0001, max_steps=200000),
            },
            "fields": {
                "optimizer": AdamOptimizerConfig(lr=1e-2, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=0.0001, max_steps=200000),
            },
            "camera_opt": camera_schedule,
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )


S2CAMP_CAMERA_OPTIMIZER = S2CampCameraOptimizerConfig()
"""s2camp's camera optimizer, the config's defaults: every parameter group, the common rotation removed after
every step and the track prior on (a no-op without SfM tracks)."""

s2camp_method = MethodSpecification(
    config=make_trainer_config("s2camp", S2CAMP_CAMERA_OPTIMIZER),
    description="S2CamP: nerfacto + pose/intrinsics refinement preconditioned with deterministic frustum samples.",
)

s2camp_camp_method = MethodSpecification(
    config=make_trainer_config(
        "s2camp-camp",
        # CamP's published configuration: its random proxy points and damping, P computed once, per-image intrinsics
        # (P the symmetric root per image), no track prior, no common-rotation removal.
        S2CampCameraOptimizerConfig(
            sampling=CAMP_SAMPLING,
            damping=DampingConfig(),
            refresh_every=0,
            intrinsics="per-image",
            track_prior=False,
            fix_common_rotation=False,
        ),
    ),
    description=(
        "CamP baseline: as s2camp, but P from CamP's published sampling (5000 random points), computed once, "
        "intrinsics per image, no track prior, no common-rotation removal."
    ),
)

s2camp_so3xr3_method = MethodSpecification(
    config=make_trainer_config("s2camp-so3xr3", CameraOptimizerConfig(mode="SO3xR3")),
    description="nerfacto baseline: nerfstudio's stock SO3xR3 pose optimizer in the S2CamP pipeline (no intrinsics).",
)


def make_splat_trainer_config(method_name: str, camera_optimizer: CameraOptimizerConfig) -> S2CampTrainerConfig:
    """splatfacto's trainer settings with the S2CamP pipeline and data parser; S2CamP's camera schedule as
    ``camera_schedule_for``, splatfacto's own for the stock optimizer."""
    if isinstance(camera_optimizer, S2CampCameraOptimizerConfig):
        camera_schedule = camera_schedule_for(camera_optimizer)
    else:
        camera_schedule = {
            "optimizer": AdamOptimizerConfig(lr=1e-4, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(
                lr_final=5e-7, max_steps=30000, warmup_steps=1000, lr_pre_warmup=0
            ),
        }

    def adam(lr: float) -> dict:
        return {"optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15), "scheduler": None}

    return S2CampTrainerConfig(
        method_name=method_name,
        steps_per_eval_image=100,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=1000,
        max_num_iterations=30000,
        mixed_precision=False,
        machine=MachineConfig(device_type=DEFAULT_DEVICE_TYPE),
        pipeline=S2CampPipelineConfig(
            datamanager=FullImageDatamanagerConfig(dataparser=S2CampDataParserConfig(), cache_images_type="uint8"),
            model=S2CampSplatModelConfig(camera_optimizer=camera_optimizer),
        ),
        optimizers={
            "means": {
                "optimizer": AdamOptimizerConfig(lr=1.6e-4, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=30000),
            },
            "features_dc": adam(0.0025),
            "features_rest": adam(0.0025 / 20),
            "opacities": adam(0.05),
            "scales": adam(0.005),
            "quats": adam(0.001),
            "camera_opt": camera_schedule,
            "bilateral_grid": {
                "optimizer": AdamOptimizerConfig(lr=2e-3, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(
                    lr_final=1e-4, max_steps=30000, warmup_steps=1000, lr_pre_warmup=0
                ),
            },
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )


SPLAT_CAMERA_OPTIMIZER = S2CampCameraOptimizerConfig(parameters="pose+intrinsics")
"""s2camp-splat's camera optimizer: distortion fixed (splatfacto trains on undistorted images), otherwise the
config's defaults."""

s2camp_splat_method = MethodSpecification(
    config=make_splat_trainer_config("s2camp-splat", SPLAT_CAMERA_OPTIMIZER),
    description=(
        "S2CamP for 3D Gaussian Splatting: splatfacto + preconditioned pose, focal, principal point and skew "
        "refinement through gsplat's view matrix (distortion fixed: images are undistorted)."
    ),
)

s2camp_splat_so3xr3_method = MethodSpecification(
    config=make_splat_trainer_config("s2camp-splat-so3xr3", CameraOptimizerConfig(mode="SO3xR3")),
    description="splatfacto baseline: nerfstudio's stock SO3xR3 pose optimizer in the S2CamP pipeline (no intrinsics).",
)
