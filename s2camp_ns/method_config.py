"""``ns-train s2camp`` and ``ns-train s2camp-camp``, registered through the ``nerfstudio.method_configs`` entry point.

Both are nerfacto (nerfstudio's proposal sampling, field and losses) with joint pose + intrinsics refinement;
they differ only in the camera optimizer:

- ``s2camp``: 500 deterministic Frolov-lattice points in each camera's frustum, P refreshed during training
  (paper sec. 4), the rotation all cameras share removed and the track prior on (``S2CAMP_CAMERA_OPTIMIZER``);
- ``s2camp-camp``: the CamP baseline, 5000 random points, P computed once at the start, neither the track prior nor
  the common-rotation removal (docs/DESIGN-NOTES.md sec. 5);
- ``s2camp-so3xr3``: the nerfacto baseline, nerfstudio's stock SO3xR3 pose optimizer (no intrinsics) with
  nerfacto's camera learning rate, in the same pipeline (data manager, offline LPIPS, camera-error logging), so
  the three are compared with everything else equal.

Without CUDA the machine defaults to the CPU (``--machine.device-type cpu``), with one message at start-up.
All three train with ``S2CampTrainer``: nerfstudio's Trainer with atomic checkpoints (``nerfstudio/trainer.py``).
"""

from __future__ import annotations

import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanagerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.plugins.types import MethodSpecification

from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
from s2camp_ns.core.preconditioner import CAMP_SAMPLING, DampingConfig
from s2camp_ns.nerfstudio.datamanager import S2CampDataManagerConfig
from s2camp_ns.nerfstudio.dataparser import S2CampDataParserConfig
from s2camp_ns.nerfstudio.model import S2CampModelConfig
from s2camp_ns.nerfstudio.pipeline import S2CampPipelineConfig
from s2camp_ns.nerfstudio.schedulers import FloatExponentialDecaySchedulerConfig, RunLengthScheduleConfig
from s2camp_ns.nerfstudio.splat_model import S2CampSplatModelConfig
from s2camp_ns.nerfstudio.trainer import S2CampTrainerConfig

DEFAULT_DEVICE_TYPE = "cuda" if torch.cuda.is_available() else "cpu"
"""nerfstudio's Trainer takes the device from the config and asserts CUDA; fall back to the CPU here instead."""


def camera_schedule_for(camera_optimizer: CameraOptimizerConfig) -> dict:
    """The "camera_opt" optimizer and schedule of a method: S2CamP's in whitened units, nerfacto's otherwise."""
    if isinstance(camera_optimizer, S2CampCameraOptimizerConfig):
        # Whitened units: a unit step of the latent moves the proxy projections by max(W, H) pixels RMS (Gram matrix
        # normalized by the image size, docs/EQUATIONS.md eq. 5), so the rates are fractions of the image size and
        # hold at any resolution. CamP's camera schedule (1e-4 -> 1e-5, warm-up 2.5k and decay to 25k of 30k
        # steps), stated as fractions of the run so that any --max-num-iterations gets it compressed.
        camera_schedule = {
            "optimizer": AdamOptimizerConfig(lr=1e-4, eps=1e-15),
            "scheduler": RunLengthScheduleConfig(lr_pre_warmup=1e-8, lr_final=1e-5),
        }
    else:
        # nerfacto's own camera schedule for its stock optimizer (raw se(3) units).
        camera_schedule = {
            "optimizer": AdamOptimizerConfig(lr=1e-3, eps=1e-15),
            "scheduler": FloatExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=5000),
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
                "scheduler": FloatExponentialDecaySchedulerConfig(lr_final=0.0001, max_steps=200000),
            },
            "fields": {
                "optimizer": AdamOptimizerConfig(lr=1e-2, eps=1e-15),
                "scheduler": FloatExponentialDecaySchedulerConfig(lr_final=0.0001, max_steps=200000),
            },
            "camera_opt": camera_schedule,
        },
        # Float learning rates: nerfstudio's numpy ones make checkpoints unloadable with torch >= 2.6 defaults.
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )


S2CAMP_CAMERA_OPTIMIZER = S2CampCameraOptimizerConfig()
"""s2camp's camera optimizer, the config's defaults: every parameter group, the rotation all cameras share removed
after every step and the track prior on (a no-op for cameras without SfM tracks). Without these, in the regime real
runs train in (each pixel seen about once), good SfM cameras ended much further off in rotation and further off in
position; with them they end where SfM's own tracks put them, re-adjusted with a robust loss, closer to the truth
than SfM left them (measured in docs/RESULTS.md, "The real-training regime"; docs/benchmarks/regime.md;
docs/DESIGN-NOTES.md sec. 6-7). The CamP baseline switches both off, as CamP's code has neither."""

s2camp_method = MethodSpecification(
    config=make_trainer_config("s2camp", S2CAMP_CAMERA_OPTIMIZER),
    description="S2CamP: nerfacto + pose/intrinsics refinement preconditioned with deterministic frustum samples.",
)

s2camp_camp_method = MethodSpecification(
    config=make_trainer_config(
        "s2camp-camp",
        # CamP's published camera-optimisation configuration (docs/benchmarks/camp-check.md): 5000 random pixels
        # at power-ladder distances in [0.4, 1000], no contraction; damping 1e-8 / 0.1; P computed once; intrinsics
        # per image with P the symmetric root per image, as CamP (not S2CamP's per-camera block factor); no track
        # prior and no common-rotation removal (CamP's code has neither).
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
    """splatfacto's trainer settings (nerfstudio 1.1.5's, float learning rates) with the S2CamP pipeline and data
    parser. S2CamP's camera schedule is the nerfacto methods' (``camera_schedule_for``); nerfstudio's stock
    optimizer gets splatfacto's own (1e-4 after a 1000-step warm-up, decaying to 5e-7)."""
    if isinstance(camera_optimizer, S2CampCameraOptimizerConfig):
        camera_schedule = camera_schedule_for(camera_optimizer)
    else:
        camera_schedule = {
            "optimizer": AdamOptimizerConfig(lr=1e-4, eps=1e-15),
            "scheduler": FloatExponentialDecaySchedulerConfig(
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
                "scheduler": FloatExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=30000),
            },
            "features_dc": adam(0.0025),
            "features_rest": adam(0.0025 / 20),
            "opacities": adam(0.05),
            "scales": adam(0.005),
            "quats": adam(0.001),
            "camera_opt": camera_schedule,
            "bilateral_grid": {
                "optimizer": AdamOptimizerConfig(lr=2e-3, eps=1e-15),
                "scheduler": FloatExponentialDecaySchedulerConfig(
                    lr_final=1e-4, max_steps=30000, warmup_steps=1000, lr_pre_warmup=0
                ),
            },
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )


SPLAT_CAMERA_OPTIMIZER = S2CampCameraOptimizerConfig(parameters="pose+intrinsics")
"""s2camp-splat's camera optimizer: distortion fixed (splatfacto trains on undistorted images), otherwise the config's
defaults: the rotation all cameras share removed after every step and the track prior on (splatfacto starts from SfM
points, so its scenes have tracks). From the CamP perturbation without these the rotation error grew in every seed,
and from true or SfM cameras every refining variant moved them (measured in docs/SPLAT.md sec. 6,
docs/benchmarks/splat.md)."""

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
