"""Atomic checkpoints: a save that fails or is killed midway never replaces the last good checkpoint; resuming
restores the random state."""

from __future__ import annotations

import random
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from hang_guard import HANG_GUARD_S
from nerfstudio.configs.base_config import MachineConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig, Optimizers
from nerfstudio.model_components.ray_samplers import ProposalNetworkSampler
from nerfstudio.utils.eval_utils import eval_load_checkpoint

from s2camp_ns.method import trainer as trainer_module
from s2camp_ns.method.trainer import S2CampTrainer, S2CampTrainerConfig, partial_dir, set_sampler_state


class TinyModel(torch.nn.Module):
    """A layer and nerfstudio's proposal sampler, whose step counters live outside the state dict."""

    def __init__(self) -> None:
        super().__init__()
        self.layer = torch.nn.Linear(3, 2)
        self.proposal_sampler = ProposalNetworkSampler()


class TinyPipeline(torch.nn.Module):
    """What the trainer and nerfstudio's checkpoint loader use of a pipeline: its model, state dict and
    load_pipeline."""

    def __init__(self) -> None:
        super().__init__()
        self.model = TinyModel()
        self.loaded_step: int | None = None

    def load_pipeline(self, state: dict, step: int) -> None:
        self.load_state_dict(state)
        self.loaded_step = step


def make_trainer(output_dir: Path) -> S2CampTrainer:
    config = S2CampTrainerConfig(
        method_name="s2camp", output_dir=output_dir, timestamp="run", machine=MachineConfig(device_type="cpu")
    )
    trainer = config.setup()
    assert isinstance(trainer, S2CampTrainer)
    trainer.pipeline = TinyPipeline()
    optimizer_config = {"fields": {"optimizer": AdamOptimizerConfig(lr=0.1), "scheduler": None}}
    trainer.optimizers = Optimizers(optimizer_config, {"fields": list(trainer.pipeline.parameters())})
    return trainer


def train_step(trainer: S2CampTrainer) -> None:
    adam = trainer.optimizers.optimizers["fields"]
    adam.zero_grad()
    trainer.pipeline.model.layer(torch.ones(1, 3)).sum().backward()
    adam.step()


def snapshot(trainer: S2CampTrainer) -> dict[str, torch.Tensor]:
    return {name: value.clone() for name, value in trainer.pipeline.state_dict().items()}


def assert_latest_checkpoint_is(checkpoint_dir: Path, step: int, weights: dict[str, torch.Tensor]) -> None:
    """Only ``step-{step}.ckpt`` exists, nerfstudio's own loader picks and loads it, and it holds ``weights``."""
    assert sorted(p.name for p in checkpoint_dir.iterdir()) == [f"step-{step:09d}.ckpt"]
    assert not list(partial_dir(checkpoint_dir).glob("*.ckpt"))
    pipeline = TinyPipeline()
    config = SimpleNamespace(load_dir=checkpoint_dir, load_step=None)
    path, loaded_step = eval_load_checkpoint(config, pipeline)
    assert loaded_step == step and pipeline.loaded_step == step
    for name, value in weights.items():
        assert torch.equal(pipeline.state_dict()[name], value), name


def test_checkpoint_holds_the_state_and_replaces_older_ones(tmp_path: Path):
    trainer = make_trainer(tmp_path)
    train_step(trainer)
    trainer.save_checkpoint(10)
    train_step(trainer)
    trainer.save_checkpoint(20)
    assert_latest_checkpoint_is(trainer.checkpoint_dir, 20, snapshot(trainer))
    state = torch.load(trainer.checkpoint_dir / "step-000000020.ckpt", map_location="cpu")
    assert state["step"] == 20 and set(state) == {
        "step",
        "pipeline",
        "optimizers",
        "schedulers",
        "scalers",
        "random_state",
        "sampler_state",
    }
    adam_state = state["optimizers"]["fields"]["state"]
    assert int(adam_state[0]["step"]) == 2  # Adam's moments after two steps, saved with the weights
    assert not list(partial_dir(trainer.checkpoint_dir).iterdir())


def test_failed_write_keeps_the_previous_checkpoint(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    trainer = make_trainer(tmp_path)
    train_step(trainer)
    trainer.save_checkpoint(10)
    good = snapshot(trainer)
    train_step(trainer)
    real_save = torch.save

    def fail_midway(state, file, *args, **kwargs):
        real_save(state, file, *args, **kwargs)
        file.truncate(file.tell() // 2)  # half of the checkpoint reached the disk
        raise OSError(28, "No space left on device (simulated)")

    monkeypatch.setattr(trainer_module.torch, "save", fail_midway)
    with pytest.raises(OSError, match="No space left"):
        trainer.save_checkpoint(20)
    assert_latest_checkpoint_is(trainer.checkpoint_dir, 10, good)
    assert not list(partial_dir(trainer.checkpoint_dir).iterdir())  # the partial file is removed


def test_killed_write_keeps_the_previous_checkpoint(tmp_path: Path):
    """SIGKILL in the middle of writing step 20: step 10 stays the newest checkpoint and still loads."""
    script = textwrap.dedent(
        f"""
        import os, signal, sys
        from pathlib import Path
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        import torch
        from test_trainer import make_trainer, snapshot, train_step
        from s2camp_ns.method import trainer as trainer_module

        trainer = make_trainer(Path({str(tmp_path)!r}))
        train_step(trainer)
        trainer.save_checkpoint(10)
        torch.save(snapshot(trainer), Path({str(tmp_path)!r}) / "good.pt")
        train_step(trainer)
        real_save = torch.save

        def killed_midway(state, file, *args, **kwargs):
            real_save(state, file, *args, **kwargs)
            file.truncate(file.tell() // 2)
            file.flush()
            os.kill(os.getpid(), signal.SIGKILL)

        trainer_module.torch.save = killed_midway
        trainer.save_checkpoint(20)
        """
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert result.returncode == -signal.SIGKILL, result.stderr[-3000:]
    checkpoint_dir = make_trainer(tmp_path).checkpoint_dir
    leftovers = list(partial_dir(checkpoint_dir).iterdir())
    assert len(leftovers) == 1 and leftovers[0].stat().st_size > 0  # the killed write, outside nerfstudio_models/
    assert_latest_checkpoint_is(checkpoint_dir, 10, torch.load(tmp_path / "good.pt"))
    # The next save clears what the killed one left behind.
    trainer = make_trainer(tmp_path)
    trainer.save_checkpoint(30)
    assert not list(partial_dir(checkpoint_dir).iterdir())


def test_resume_restores_weights_adam_step_random_state_and_sampler_counters(tmp_path: Path):
    """--load-dir: the highest step-N.ckpt is loaded (other files ignored), training continues at N + 1 with the
    weights, Adam's state, the random generators' state and the proposal sampler's counters of the save, so its next
    draws, and its choice of updating the proposal networks, are the ones the uninterrupted run makes. The resumed
    run's config.yml names the checkpoint it loaded, without load_dir and load_step (which eval_setup would look for
    in the resumed run's own folder)."""
    import yaml

    torch.manual_seed(0)
    np.random.seed(0)  # noqa: NPY002 (the global generator nerfstudio seeds)
    random.seed(0)
    trainer = make_trainer(tmp_path)
    train_step(trainer)
    trainer.save_checkpoint(10)
    train_step(trainer)
    sampler = trainer.pipeline.model.proposal_sampler
    sampler._step, sampler._steps_since_update = 20, 3
    trainer.save_checkpoint(20)
    weights = snapshot(trainer)
    adam_state = {k: v.clone() for k, v in trainer.optimizers.optimizers["fields"].state_dict()["state"][0].items()}
    uninterrupted_draws = (torch.rand(4), np.random.rand(4), random.random())  # noqa: NPY002
    (trainer.checkpoint_dir / "notes.txt").write_text("not a checkpoint")

    torch.manual_seed(123)  # a new process seeds afresh (nerfstudio's train.py)
    np.random.seed(123)  # noqa: NPY002
    random.seed(123)
    resumed = make_trainer(tmp_path / "other")
    resumed.config.load_dir = trainer.checkpoint_dir
    resumed._load_checkpoint()
    assert resumed._start_step == 21
    restored = resumed.pipeline.model.proposal_sampler
    assert (restored._step, restored._steps_since_update) == (20, 3)
    recorded = yaml.load((resumed.base_dir / "config.yml").read_text(), Loader=yaml.Loader)
    assert recorded.load_checkpoint == (trainer.checkpoint_dir / "step-000000020.ckpt").resolve()
    assert recorded.load_dir is None and recorded.load_step is None
    for name, value in weights.items():
        assert torch.equal(resumed.pipeline.state_dict()[name], value), name
    loaded_adam = resumed.optimizers.optimizers["fields"].state_dict()["state"][0]
    assert all(torch.equal(loaded_adam[k], v) for k, v in adam_state.items())
    draws = (torch.rand(4), np.random.rand(4), random.random())  # noqa: NPY002
    assert torch.equal(draws[0], uninterrupted_draws[0])
    assert np.array_equal(draws[1], uninterrupted_draws[1]) and draws[2] == uninterrupted_draws[2]


def test_sampler_counters_of_another_model_are_refused():
    """Counters saved for samplers the model does not have (another model's checkpoint) are refused by name."""
    model = TinyModel()
    with pytest.raises(ValueError, match=r"proposal samplers \['other'\] are not the model's \['proposal_sampler'\]"):
        set_sampler_state(model, {"other": {"_step": 1, "_steps_since_update": 1}})


def test_several_processes_keep_their_own_random_streams_on_resume(tmp_path: Path):
    """A checkpoint holds rank 0's random state only: with several processes each rank keeps its own seeding
    (nerfstudio's seed + rank), so the ranks still draw different rays after a resume."""
    torch.manual_seed(0)
    trainer = make_trainer(tmp_path)
    train_step(trainer)
    trainer.save_checkpoint(5)
    rank0_draws = torch.rand(4)

    torch.manual_seed(1001)  # rank 1 of a new two-process run: seed + rank
    resumed = make_trainer(tmp_path / "rank1")
    resumed.world_size = 2
    resumed.config.load_dir = trainer.checkpoint_dir
    expected = torch.random.get_rng_state()
    resumed._load_checkpoint()
    assert torch.equal(torch.random.get_rng_state(), expected)
    assert not torch.equal(torch.rand(4), rank0_draws)


def _tiny_pipeline(scene: Path, eval_interval: int, test_mode: str = "val"):
    from conftest import lpips_offline, tiny_model_config

    from s2camp_ns.camera_optimizer import S2CampCameraOptimizerConfig
    from s2camp_ns.core.preconditioner import SamplingConfig
    from s2camp_ns.data.dataparser import S2CampDataParserConfig
    from s2camp_ns.method.datamanager import S2CampDataManagerConfig
    from s2camp_ns.method.pipeline import S2CampPipelineConfig

    config = S2CampPipelineConfig(
        datamanager=S2CampDataManagerConfig(
            dataparser=S2CampDataParserConfig(data=scene, eval_interval=eval_interval),
            train_num_rays_per_batch=64,
            eval_num_rays_per_batch=64,
        ),
        model=tiny_model_config(S2CampCameraOptimizerConfig(sampling=SamplingConfig(num_points=32))),
    )
    with lpips_offline():
        return config.setup(device="cpu", test_mode=test_mode)


@pytest.mark.parametrize("test_mode", ["test", "inference"])
def test_a_loaded_pipeline_makes_no_tracks_and_fits_no_anchor(tiny_scene: Path, test_mode: str, monkeypatch):
    """eval_setup's modes (ns-eval, ns-viewer: test; ns-render, the export: inference) skip the data parser's tracks and
    the anchor fit; the checkpoint gives the same refined cameras as the trained pipeline had."""
    import s2camp_ns.camera_optimizer as camera_optimizer
    import s2camp_ns.tracks.track_evidence as track_evidence

    trained = _tiny_pipeline(tiny_scene, eval_interval=8)
    assert trained.anchor_tracks is not None and trained.anchor_tracks.tracks is not None
    with torch.no_grad():
        trained.model.camera_optimizer.refiner.whitened_delta.add_(0.01)

    def refuse(*args, **kwargs):
        raise AssertionError("track work in a loaded pipeline")

    for module, name in ((track_evidence, "scene_track_evidence"), (track_evidence, "image_track_evidence"),
                         (camera_optimizer, "fit_anchor")):  # fmt: skip
        monkeypatch.setattr(module, name, refuse)
    loaded = _tiny_pipeline(tiny_scene, eval_interval=8, test_mode=test_mode)
    assert loaded.anchor_tracks is None
    assert trained.datamanager.config.dataparser.tracks  # the config it was given is unchanged
    loaded.load_pipeline(trained.state_dict(), step=5)
    refined = loaded.model.camera_optimizer.refiner.deltas().detach()
    assert torch.equal(refined, trained.model.camera_optimizer.refiner.deltas().detach())
    with pytest.raises(AssertionError, match="track work"):  # a pipeline built for training does it
        _tiny_pipeline(tiny_scene, eval_interval=8)


def test_checkpoint_of_another_scene_is_refused_with_both_camera_counts(tiny_scene: Path, tmp_path: Path):
    """A checkpoint trained on 10 training cameras (the 12-image scene, every 8th held out) loaded onto 9 (every 4th
    held out): ``--load-dir`` / ``--load-checkpoint`` (the trainer) and nerfstudio's ``eval_setup`` loader (ns-render,
    ns-eval) stop with both counts instead of torch's list of size mismatches; the same split still loads."""
    from s2camp_ns.method.pipeline import CheckpointCamerasError

    trained = _tiny_pipeline(tiny_scene, eval_interval=8)
    assert trained.model.num_train_data == 10
    checkpoint_dir = tmp_path / "nerfstudio_models"
    checkpoint_dir.mkdir()
    path = checkpoint_dir / "step-000000005.ckpt"
    torch.save({"step": 5, "pipeline": trained.state_dict()}, path)

    other = _tiny_pipeline(tiny_scene, eval_interval=4)
    assert other.model.num_train_data == 9
    trainer = make_trainer(tmp_path / "run")
    trainer.pipeline = other
    trainer.config.load_checkpoint = path
    counts = rf"the checkpoint was trained on 10 training cameras, but the data \({re.escape(str(tiny_scene))}\) has 9"
    with pytest.raises(CheckpointCamerasError, match=rf"^checkpoint {re.escape(str(path))}: {counts}: it is a "):
        trainer._load_checkpoint()
    with pytest.raises(CheckpointCamerasError, match=counts):
        eval_load_checkpoint(SimpleNamespace(load_dir=checkpoint_dir, load_step=None), other)

    # The same split loads: the check passes the checkpoint on to nerfstudio's loader.
    saved_precond = trained.state_dict()["_model.camera_optimizer.refiner.precond"].clone()
    trained.model.camera_optimizer.refiner.precond.zero_()
    eval_load_checkpoint(SimpleNamespace(load_dir=checkpoint_dir, load_step=None), trained)
    assert torch.equal(trained.model.camera_optimizer.refiner.precond, saved_precond)


def test_checkpoint_camera_count_reads_every_method_state():
    """s2camp (P), s2camp-so3xr3 (nerfstudio's pose deltas) and a model without camera optimizer (nerfacto's
    appearance codes), with the pipeline's and DDP's prefixes."""
    from s2camp_ns.method.pipeline import check_checkpoint_cameras, checkpoint_camera_count

    assert checkpoint_camera_count({"_model.camera_optimizer.refiner.precond": torch.zeros(4, 6, 6)}) == 4
    assert checkpoint_camera_count({"_model.module.camera_optimizer.pose_adjustment": torch.zeros(3, 6)}) == 3
    assert checkpoint_camera_count({"_model.field.embedding_appearance.embedding.weight": torch.zeros(2, 32)}) == 2
    assert checkpoint_camera_count({"_model.field.mlp.weight": torch.zeros(8, 8)}) is None
    check_checkpoint_cameras({"_model.camera_optimizer.pose_adjustment": torch.zeros(3, 6)}, 3)
    with pytest.raises(ValueError, match=r"trained on 3 training cameras, but the data has 4"):
        check_checkpoint_cameras({"_model.camera_optimizer.pose_adjustment": torch.zeros(3, 6)}, 4)
