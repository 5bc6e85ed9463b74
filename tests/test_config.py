"""EnvConfig validation: errors name the field and the allowed values."""

from __future__ import annotations

import dataclasses

import pytest

from quadswarm_mj import EnvConfig


def test_defaults_match_the_issue():
    c = EnvConfig()
    assert (c.num_quads, c.scenario, c.room_size, c.control_hz, c.sim_hz, c.episode_seconds) == (
        8, "static_same_goal", (10.0, 10.0, 10.0), 100, 200, 15)
    assert (c.downwash, c.collision_model, c.collision_decay, c.num_neighbors, c.motor_start, c.randomize) == (
        False, "paper", (0.2, 0.8), None, "zero", False)
    assert c.neighbors == 6 and EnvConfig(num_quads=3).neighbors == 2 and EnvConfig(num_quads=1).neighbors == 0
    assert c.episode_steps == 1500 and c.substeps == 2


def test_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        EnvConfig().num_quads = 3


@pytest.mark.parametrize("kwargs,words", [
    ({"collision_model": "bullet"}, ["collision_model", "paper", "mujoco", "blend"]),
    ({"num_quads": 0}, ["num_quads", ">= 1"]),
    ({"num_quads": 4, "num_neighbors": 4}, ["neighbor", "3"]),
    ({"room_size": (10, -1, 10)}, ["room"]),
    ({"room_size": (10, 10)}, ["room"]),
    ({"control_hz": 100, "sim_hz": 250}, ["hz"]),
    ({"motor_start": "spinning"}, ["motor_start", "zero", "hover"]),
    ({"scenario": "warp_drive"}, ["warp_drive", "static_same_goal"]),
    ({"collision_decay": (0.9, 0.1)}, ["collision_decay"]),
    ({"episode_seconds": 0}, ["episode_seconds"]),
    ({"noise": {"sensor_pos_std": -1}}, ["noise.sensor_pos_std"]),
    ({"rewards": {"pos": -1}}, ["rewards.pos"]),
    ({"randomization": {"mass_scale": (1.2, 0.8)}}, ["randomization.mass_scale"]),
])
def test_bad_config_names_field(kwargs, words):
    with pytest.raises(ValueError) as e:
        EnvConfig(**kwargs)
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def test_without_noise_switches_everything_off():
    c = EnvConfig(randomize=True).without_noise()
    n = c.noise
    assert not c.randomize and n.motor_noise_ratio == 0 and n.sensor_pos_std == 0 and n.sensor_vel_std == 0
    assert n.sensor_omega_std == 0 and not n.stochastic_collisions and not n.stochastic_downwash
    assert c.collision_model == "paper"  # unchanged otherwise


def test_nested_dicts_become_dataclasses():
    c = EnvConfig(noise={"sensor_pos_std": 0.0}, rewards={"pos": 2.0})
    assert c.noise.sensor_pos_std == 0.0 and c.rewards.pos == 2.0 and c.rewards.effort == 0.05
