"""nerfstudio's VanillaPipeline that hands the training cameras to the S2CamP camera optimizer and owns DDP.

The model is built before it knows any camera, but the preconditioner and the ray regeneration need them; the
pipeline, owning data manager and model, hands them over. Where a full-image data manager (splatfacto's) undistorted
the training images, the model gets the pinhole cameras it wrote and the tracks moved into those images.

Only a pipeline built for training (``test_mode`` "val", as nerfstudio's Trainer builds it) makes the track evidence
and fits the anchors: a loaded run (``eval_setup``: export, evaluation, rendering, the viewer) has its refined cameras
and track prior in the checkpoint and the anchors' tracks in its folder (``core.anchor_tracks``), and its data parser
skips the tracks.

With several processes the pipeline wraps the model in DDP itself: ``broadcast_buffers=False`` (every rank computes
the same P; rank 0's P, P^-1 and Sigma would be sent every step, to ranks whose latent was not re-expressed with it)
and ``device_ids`` only on CUDA (a CPU module and gloo reject them; ``s2camp_ns.method.distributed``).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from jaxtyping import Float
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils import comms
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor
from torch.cuda.amp.grad_scaler import GradScaler
from torch.nn.parallel import DistributedDataParallel

from s2camp_ns.camera_optimizer import S2CampCameraOptimizer
from s2camp_ns.compat import OLD_CAMERA_COUNT_KEYS
from s2camp_ns.core.anchor_tracks import AnchorTracks, given_anchor_tracks
from s2camp_ns.data.camera_conversion import intrinsics_from_cameras
from s2camp_ns.data.camera_fields import has_distortion, replace_cameras
from s2camp_ns.data.scene_config import SceneConfig
from s2camp_ns.method.datamanager import PixelRayGenerator
from s2camp_ns.tracks.undistorted_tracks import undistorted_track_evidence

CAMERA_COUNT_KEYS = (
    "camera_optimizer.refiner.precond",  # S2CamP's P, one per training camera [N, K, K]
    *OLD_CAMERA_COUNT_KEYS,
    "camera_optimizer.pose_adjustment",  # nerfstudio's SO3xR3 / SE3 deltas [N, 6] (s2camp-so3xr3)
    "field.embedding_appearance.embedding.weight",  # nerfacto's appearance code per training image [N, d]
)
"""Pipeline state-dict entries (after any prefix) whose first dimension is the number of training cameras."""


class CheckpointCamerasError(ValueError):
    """A checkpoint trained on another number of training cameras than the data at hand."""


def checkpoint_camera_count(state: Mapping[str, Any]) -> int | None:
    """Number of training cameras a pipeline state dict was trained on; None without ``CAMERA_COUNT_KEYS``."""
    for suffix in CAMERA_COUNT_KEYS:
        for key, value in state.items():
            if (key == suffix or key.endswith("." + suffix)) and hasattr(value, "shape"):
                return int(value.shape[0])
    return None


def check_checkpoint_cameras(state: Mapping[str, Any], num_train_cameras: int, data: Path | None = None) -> None:
    """CheckpointCamerasError for a checkpoint of another scene or split (torch would list size mismatches)."""
    saved = checkpoint_camera_count(state)
    if saved is None or saved == num_train_cameras:
        return
    where = f" ({data})" if data is not None else ""
    raise CheckpointCamerasError(
        f"the checkpoint was trained on {saved} training cameras, but the data{where} has {num_train_cameras}: it is "
        "a checkpoint of another scene or of another train/eval split (eval_mode, eval_interval); load a checkpoint "
        "of this scene and split, or train without --load-dir / --load-checkpoint"
    )


def undistortion_scale(datamanager) -> tuple[Float[Tensor, "n 1"], Float[Tensor, "n 1"]]:
    """Undistorted over given fx and fy [n, 1] of each training camera (``S2CampSplatModel.set_undistortion_scale``)."""
    seen, given = datamanager.train_dataset.cameras, datamanager.train_dataparser_outputs.cameras
    return seen.fx / given.fx, seen.fy / given.fy


TRAINING_MODE = "val"
"""The ``test_mode`` nerfstudio's Trainer builds the pipeline with: the only one that makes tracks and fits anchors."""


def without_track_work(config: VanillaPipelineConfig) -> VanillaPipelineConfig:
    """``config`` with its data parser's tracks off (copies; the given config is unchanged)."""
    dataparser = getattr(config.datamanager, "dataparser", None)
    if not isinstance(dataparser, SceneConfig) or not dataparser.tracks:
        return config
    dataparser, datamanager, config = copy.copy(dataparser), copy.copy(config.datamanager), copy.copy(config)
    dataparser.tracks = False
    datamanager.dataparser = dataparser
    config.datamanager = datamanager
    return config


@dataclass
class S2CampPipelineConfig(VanillaPipelineConfig):
    """VanillaPipeline that gives the S2CamP camera optimizer its training cameras."""

    _target: type = field(default_factory=lambda: S2CampPipeline)


class S2CampPipeline(VanillaPipeline):
    """VanillaPipeline + training cameras handed to the model + its own DDP + ``check_checkpoint_cameras``."""

    def __init__(
        self,
        config: S2CampPipelineConfig,
        device: str,
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        grad_scaler: GradScaler | None = None,
    ):
        if str(device).startswith("cpu") and not torch.cuda.is_available():
            CONSOLE.print("[bold yellow]CUDA is not available: training on the CPU (expect about 1 s per iteration).")
        if test_mode != TRAINING_MODE:
            config = without_track_work(config)
        # world_size=1: VanillaPipeline must not wrap the model (its data manager uses it only for worker counts).
        super().__init__(config, device, test_mode, 1, local_rank, grad_scaler)
        assert self.datamanager.train_dataset is not None
        cameras = self.datamanager.train_dataset.cameras
        metadata = getattr(self.datamanager.train_dataset, "metadata", None) or {}
        points = metadata.get("points3D_xyz")
        tracks = {"track_rms_px": metadata.get("track_rms_px"), "track_evidence": metadata.get("track_evidence")}
        if has_distortion(cameras) and hasattr(type(self.datamanager), "cached_train"):
            # Caching undistorts the images and writes the undistorted K into the cameras; the tracks move with them.
            given = intrinsics_from_cameras(self.datamanager.train_dataparser_outputs.cameras)
            _ = self.datamanager.cached_train
            if hasattr(self.model, "set_undistortion_scale"):
                self.model.set_undistortion_scale(*undistortion_scale(self.datamanager))
            cameras = replace_cameras(cameras, distortion_params=None)
            if tracks["track_evidence"] is not None:
                tracks["track_evidence"] = undistorted_track_evidence(
                    tracks["track_evidence"], given, intrinsics_from_cameras(cameras)
                )
        if hasattr(self.model, "set_train_cameras"):
            self.model.set_train_cameras(cameras, points=points, **tracks)
        elif isinstance(getattr(self.model, "camera_optimizer", None), S2CampCameraOptimizer):
            self.model.camera_optimizer.set_train_cameras(cameras, points=points)
            self.model.camera_optimizer.set_track_prior(tracks["track_rms_px"], tracks["track_evidence"])
        training = test_mode == TRAINING_MODE
        self.anchor_tracks = self._anchor_tracks(cameras, tracks["track_evidence"]) if training else None
        """The tracks of the anchors (``core.anchor_tracks``); None where the pipeline was not built for training."""
        # The S2CamP camera optimizer casts the training rays itself, through the refined cameras.
        camera_optimizer = getattr(self.model, "camera_optimizer", None)
        generator = getattr(self.datamanager, "train_ray_generator", None)
        refining = isinstance(camera_optimizer, S2CampCameraOptimizer) and camera_optimizer.enabled
        if refining and isinstance(generator, PixelRayGenerator):
            generator.cast_by_model = True
        self.world_size = world_size
        if world_size > 1:
            on_cuda = torch.device(device).type == "cuda"
            # DDP's constructor sends rank 0's parameters to every rank; then only gradients are averaged.
            self._model = DistributedDataParallel(
                self._model,
                device_ids=[local_rank] if on_cuda else None,
                find_unused_parameters=True,
                broadcast_buffers=False,
            )
            comms.synchronize()

    def _anchor_tracks(self, cameras, evidence) -> AnchorTracks:
        """The camera optimizer's fitted anchor tracks, else the tracks at the given ``cameras``, else none."""
        fitted = getattr(getattr(self.model, "camera_optimizer", None), "anchor_tracks", None)
        if fitted is not None:
            return fitted
        if evidence is not None:
            return given_anchor_tracks(evidence, intrinsics_from_cameras(cameras))
        return AnchorTracks(cameras.shape[0])

    def load_pipeline(self, loaded_state: dict[str, Any], step: int) -> None:
        """VanillaPipeline's loading, after ``check_checkpoint_cameras``."""
        data = getattr(self.datamanager.config, "data", None) or getattr(
            getattr(self.datamanager.config, "dataparser", None), "data", None
        )
        check_checkpoint_cameras(loaded_state, self.model.num_train_data, data)
        super().load_pipeline(loaded_state, step)
