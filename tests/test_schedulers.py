"""The camera learning-rate schedule that follows the run's length (s2camp_ns/method/schedulers.py)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

from s2camp_ns.method.schedulers import RunLengthScheduleConfig
from s2camp_ns.method.trainer import S2CampTrainer, plain_numbers, with_run_length
from s2camp_ns.method_config import s2camp_method, s2camp_so3xr3_method


def learning_rates(scheduler_config, steps: int, lr: float = 1e-4) -> list[float]:
    """Learning rate used at each step 0..steps-1."""
    parameter = torch.nn.Parameter(torch.zeros(1))
    optimizer = torch.optim.Adam([parameter], lr=lr)
    scheduler = scheduler_config.setup().get_scheduler(optimizer, lr)
    rates = []
    for _ in range(steps):
        rates.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    return rates


def test_a_600_step_run_gets_the_schedule_compressed_without_the_warmup_floor():
    config = RunLengthScheduleConfig(lr_pre_warmup=1e-8, lr_final=1e-5, run_steps=600, min_warmup_steps=0)
    rates = learning_rates(config, 601)
    # 2500/30000 of 600 steps = 50 warm-up steps, decay to the end at 25000/30000 of 600 = 500.
    assert rates[0] == pytest.approx(1e-8, rel=1e-9)
    assert rates[25] == pytest.approx(1e-8 + (1e-4 - 1e-8) * math.sin(math.pi / 4), rel=1e-9)  # cosine ramp half way
    assert rates[50] == pytest.approx(1e-4, rel=1e-12)
    assert rates[275] == pytest.approx(math.sqrt(1e-4 * 1e-5), rel=1e-9)  # half way through the decay, log-linear
    assert rates[500] == pytest.approx(1e-5, rel=1e-12)
    assert rates[600] == pytest.approx(1e-5, rel=1e-12)


def test_the_warmup_never_gets_shorter_than_the_floor():
    # 600 steps: 1/12 would be 50 warm-up steps; the floor keeps CamP's 2500, so the run stays in the warm-up.
    rates = learning_rates(RunLengthScheduleConfig(run_steps=600), 600)
    assert rates[599] == pytest.approx(1e-8 + (1e-4 - 1e-8) * math.sin(0.5 * math.pi * 599 / 2500), rel=1e-9)
    assert RunLengthScheduleConfig(run_steps=600).step_counts() == (2500, 2501)
    assert RunLengthScheduleConfig(run_steps=60000).step_counts() == (5000, 50000)


def test_under_the_floor_the_decay_keeps_its_share_of_the_steps_after_the_warmup():
    # CamP decays over 22.5k of the 27.5k steps after its warm-up (9/11): 10k steps end at 2500 + 9/11 * 7500.
    assert RunLengthScheduleConfig(run_steps=10000).step_counts() == (2500, 2500 + 6136)
    assert RunLengthScheduleConfig(run_steps=4000).step_counts() == (2500, 2500 + 1227)
    assert RunLengthScheduleConfig(run_steps=2600).step_counts() == (2500, 2500 + 82)
    assert RunLengthScheduleConfig(run_steps=2501).step_counts() == (2500, 2501)
    # The end of the decay moves with the run length, without the jump of "5/6 of the run, at least the warm-up".
    ends = [RunLengthScheduleConfig(run_steps=steps).step_counts()[1] for steps in range(2400, 12001, 50)]
    assert all(0 <= later - earlier <= 41 for earlier, later in zip(ends, ends[1:], strict=False))
    rates = learning_rates(RunLengthScheduleConfig(run_steps=3000), 3000)
    assert rates[2500] == pytest.approx(1e-4, rel=1e-12)
    assert rates[2501] > 0.99 * 1e-4  # decays over 409 steps, not at once
    assert rates[2909] == pytest.approx(1e-5, rel=1e-12)


def test_the_default_30k_run_keeps_camps_step_counts():
    compressed = learning_rates(RunLengthScheduleConfig(run_steps=30000), 30000)
    fixed = learning_rates(
        ExponentialDecaySchedulerConfig(lr_pre_warmup=1e-8, warmup_steps=2500, lr_final=1e-5, max_steps=25000),
        30000,
    )
    assert compressed == fixed


def test_absolute_step_counts_override_the_fractions():
    rates = learning_rates(RunLengthScheduleConfig(warmup_steps=0, max_steps=10, lr_final=1e-6), 12, lr=1e-3)
    assert rates[0] == pytest.approx(1e-3, rel=1e-12)
    assert rates[5] == pytest.approx(math.sqrt(1e-3 * 1e-6), rel=1e-9)
    assert rates[10] == rates[11] == pytest.approx(1e-6, rel=1e-12)


@pytest.mark.parametrize(
    ("fields", "named"),
    [
        ({}, "run_steps"),
        ({"run_steps": 0}, "run_steps"),
        ({"run_steps": 100, "warmup_fraction": 1.0}, "warmup_fraction"),
        ({"run_steps": 100, "decay_end_fraction": 0.0}, "decay_end_fraction"),
        ({"run_steps": 100, "decay_end_fraction": 0.05}, "decay_end_fraction"),
        ({"run_steps": 100, "lr_final": -1e-5}, "lr_final"),
        ({"warmup_steps": 10, "max_steps": 10}, "max_steps"),
        ({"run_steps": 100, "min_warmup_steps": -1}, "min_warmup_steps"),
    ],
)
def test_bad_settings_name_the_parameter(fields, named):
    with pytest.raises(ValueError, match=named):
        RunLengthScheduleConfig(**fields).step_counts()


def test_with_run_length_fills_only_missing_run_lengths():
    given = RunLengthScheduleConfig(run_steps=77)
    optimizers = {
        "camera_opt": {"optimizer": None, "scheduler": RunLengthScheduleConfig()},
        "given": {"optimizer": None, "scheduler": given},
        "fields": {"optimizer": None, "scheduler": ExponentialDecaySchedulerConfig(max_steps=9)},
    }
    resolved = with_run_length(optimizers, 600)
    assert resolved["camera_opt"]["scheduler"].run_steps == 600
    assert resolved["given"]["scheduler"] is given
    assert resolved["fields"]["scheduler"].max_steps == 9
    assert optimizers["camera_opt"]["scheduler"].run_steps is None  # the config itself is not modified


def test_the_trainer_gives_s2camp_a_schedule_over_max_num_iterations():
    config = s2camp_method.config
    trainer = S2CampTrainer.__new__(S2CampTrainer)
    trainer.config = SimpleNamespace(optimizers=config.optimizers, max_num_iterations=36000)
    groups = {name: [torch.nn.Parameter(torch.zeros(2))] for name in ("proposal_networks", "fields", "camera_opt")}
    trainer.pipeline = SimpleNamespace(get_param_groups=lambda: groups)
    optimizers = trainer.setup_optimizers()
    camera, scheduler = optimizers.optimizers["camera_opt"], optimizers.schedulers["camera_opt"]
    rates = []
    for _ in range(30001):
        rates.append(camera.param_groups[0]["lr"])
        camera.step()
        scheduler.step()
    assert rates[3000] == pytest.approx(1e-4, rel=1e-12)  # warm-up over 3000 of 36000 steps
    assert rates[2999] < 1e-4
    assert rates[30000] == pytest.approx(1e-5, rel=1e-12)  # decay ends at step 30000 of 36000


def test_nerfstudios_stock_optimizer_keeps_its_own_schedule():
    scheduler = s2camp_so3xr3_method.config.optimizers["camera_opt"]["scheduler"]
    assert isinstance(scheduler, ExponentialDecaySchedulerConfig)
    assert (scheduler.max_steps, scheduler.lr_final) == (5000, 1e-4)


def test_checkpoints_hold_the_schedules_rates_as_python_floats(tmp_path):
    parameter = torch.nn.Parameter(torch.zeros(1))
    optimizer = torch.optim.Adam([parameter], lr=1e-3)
    scheduler = RunLengthScheduleConfig(run_steps=50).setup().get_scheduler(optimizer, 1e-3)
    for _ in range(3):
        optimizer.step()
        scheduler.step()
    state = {"optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict()}
    torch.save(state, tmp_path / "numpy.pt")
    with pytest.raises(Exception, match="numpy"):  # nerfstudio's rates are numpy scalars: torch refuses them
        torch.load(tmp_path / "numpy.pt", weights_only=True)
    torch.save(plain_numbers(state), tmp_path / "plain.pt")
    loaded = torch.load(tmp_path / "plain.pt", weights_only=True)
    assert type(loaded["optimizer"]["param_groups"][0]["lr"]) is float
    assert loaded["optimizer"]["param_groups"][0]["lr"] == optimizer.param_groups[0]["lr"]
    assert loaded["scheduler"]["_last_lr"] == scheduler.state_dict()["_last_lr"]
