"""DAgger distillation into a small encoder on the JAX engine (quadswarm_mj.training.distill)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("flax")
pytest.importorskip("optax")

from quadswarm_mj import EnvConfig  # noqa: E402
from quadswarm_mj.policies import load_policy, save_policy  # noqa: E402
from quadswarm_mj.training.distill import DistillConfig, Distiller  # noqa: E402
from quadswarm_mj.training.ppo import env_meta  # noqa: E402


def _teacher(tmp_path):
    """A random (but smooth) MLP teacher for 2 quads: distillation must be able to fit it."""
    cfg = EnvConfig(num_quads=2, scenario="static_diff_goal")
    rng = np.random.default_rng(0)
    d = cfg.obs_dim
    ks = [rng.normal(0, 1 / np.sqrt(d), (d, 16)), rng.normal(0, 0.25, (16, 8))]
    bs = [np.zeros(16), np.zeros(8)]
    meta = {"activation": "tanh", "obs_dim": d, "action_dim": 4, "env": env_meta(cfg)}
    path = tmp_path / "teacher.npz"
    save_policy(path, ks, bs, np.zeros(d), np.full(d, 2.0), meta)
    return path


def test_config_errors_name_the_field():
    with pytest.raises(ValueError, match="DistillConfig.batch_size"):
        DistillConfig(batch_size=0)
    with pytest.raises(ValueError, match="DistillConfig.learning_rate"):
        DistillConfig(learning_rate=float("nan"))


@pytest.mark.slow
def test_student_learns_the_teacher_and_is_a_loadable_deployable_policy(tmp_path):
    teacher_path = _teacher(tmp_path)
    teacher = load_policy(str(teacher_path))
    d = Distiller(str(teacher_path), "deepsets_deployable", "static_diff_goal",
                  DistillConfig(num_worlds=4, unroll_length=16, buffer_size=4096, sgd_steps=100, batch_size=256,
                                beta_iterations=2), seed=0)
    assert d.num_params <= 2000
    obs = np.asarray(d.carry["env"].obs).reshape(-1, teacher.obs_dim)
    err0 = np.mean((d.policy()(obs) - teacher(obs)) ** 2)
    rows = [d.step() for _ in range(6)]
    assert rows[-1]["samples"] == 6 * 4 * 16 * 2
    obs = np.asarray(d.carry["env"].obs).reshape(-1, teacher.obs_dim)
    student = d.policy()
    err = np.mean((student(obs) - teacher(obs)) ** 2)
    assert err < 0.3 * err0, (err, err0)
    path = tmp_path / "student.npz"
    d.save(path)
    loaded = load_policy(str(path))
    assert loaded.env_kwargs == teacher.env_kwargs and loaded.num_params == d.num_params
    np.testing.assert_allclose(loaded(obs), student(obs), atol=1e-6)
    assert loaded.meta["train"]["method"] == "dagger_distillation"
    # continuing from the file starts from exactly its policy
    d2 = Distiller(str(teacher_path), "deepsets_deployable", "static_diff_goal",
                   DistillConfig(num_worlds=4, unroll_length=16, buffer_size=4096, sgd_steps=100, batch_size=256,
                                 beta_iterations=0), seed=1, init_from=str(path))
    np.testing.assert_allclose(d2.policy()(obs), loaded(obs), atol=1e-6)
    with pytest.raises(ValueError, match="init_from"):
        Distiller(str(teacher_path), "deepsets_large", "static_diff_goal", DistillConfig(num_worlds=2), width=8,
                  init_from=str(path))


@pytest.mark.slow
def test_controller_teacher_with_obstacles_labels_the_true_state_and_estimates_a_normalizer():
    """The privileged teacher flies the env itself (beta = 1: the student is never used) and its
    labels are the controller's actions on the true state; the student's normalizer comes from the
    teacher-flown warm-up (finite, positive std for all 63 inputs, obstacle features included)."""
    from quadswarm_mj.config import ObstacleConfig

    env = {"num_quads": 3, "obstacles": ObstacleConfig(), "downwash": True}
    d = Distiller("controller", "deepsets_deployable", "o_random",
                  DistillConfig(num_worlds=2, unroll_length=8, buffer_size=512, sgd_steps=2, batch_size=32,
                                beta_iterations=1000), seed=0, env=env)
    assert d.teacher is None and d.obs_std.shape == (d.env_cfg.obs_dim,) and np.all(d.obs_std >= 1e-3)
    assert np.all(np.isfinite(d.obs_mean))
    d.step()
    labels = np.asarray(d.carry["buf_act"][: 2 * 8 * 3])
    assert np.all(np.abs(labels) <= 1.0) and np.abs(labels).max() > 0.05
    student = d.policy()
    assert student.env_kwargs["downwash"] is True and student.env_kwargs["obstacles"]["density"] == 0.2
    assert student.meta["train"]["teacher"] == "controller"


@pytest.mark.slow
def test_student_of_the_multiranger_without_column_features():
    """The sensed-columns env (issue 36): the teacher reads the column map, the student's tail is the
    multi-ranger's 10 readings, and the student file rebuilds that env."""
    from quadswarm_mj.config import ObstacleConfig
    from quadswarm_mj.sensor_config import SensorConfig

    env = {"num_quads": 3, "obstacles": ObstacleConfig(observe_features=False), "downwash": True,
           "sensors": SensorConfig(multiranger=True)}
    d = Distiller("controller", "deepsets_deployable", "o_random",
                  DistillConfig(num_worlds=2, unroll_length=8, buffer_size=512, sgd_steps=2, batch_size=32,
                                beta_iterations=1000), seed=0, env=env)
    assert d.layout["obstacle_dim"] == 10 and d.env_cfg.obs_dim == 18 + 12 + 10
    d.step()
    student = d.policy()
    assert student.obs_layout["obstacle_dim"] == 10
    assert student.env_kwargs["obstacles"]["observe_features"] is False
    assert student.env_kwargs["sensors"]["multiranger"] is True
    rebuilt = EnvConfig(**{**student.env_kwargs, "scenario": "o_random"})
    assert rebuilt.obs_dim == student.obs_dim == d.env_cfg.obs_dim


@pytest.mark.slow
def test_cli_run_resumes_with_optimizer_normalizer_and_counters(tmp_path):
    import json

    from quadswarm_mj.training import distill

    teacher = str(_teacher(tmp_path))
    out = tmp_path / "run"
    base = ["--teacher", teacher, "--arch", "deepsets_deployable", "--scenario", "static_diff_goal", "--out", str(out),
            "--num-worlds", "2", "--checkpoint-minutes", "0"]
    assert distill.main(base + ["--iterations", "2"]) == 0
    first = load_policy(str(out / "student.npz"))
    assert distill.main(base + ["--iterations", "3", "--resume"]) == 0
    rows = json.loads((out / "progress.json").read_text())
    assert [r["iteration"] for r in rows] == [1, 2, 3]
    assert rows[-1]["wall_s"] >= rows[1]["wall_s"]
    second = load_policy(str(out / "student.npz"))
    assert second.meta["train"]["iterations"] == 3
    np.testing.assert_array_equal(second.obs_mean, first.obs_mean)
    with pytest.raises(SystemExit, match="no "):
        distill.main(["--teacher", teacher, "--out", str(tmp_path / "empty"), "--resume"])
