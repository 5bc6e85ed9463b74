"""A policy trained at another control rate records it, and evaluation flies it at that rate.

Before, a policy file kept only its observation layout: a 50 Hz policy was evaluated at the default 100 Hz
without a word (each action then lasts half as long as in training).
"""

from __future__ import annotations

import numpy as np

from quadswarm_mj import EnvConfig
from quadswarm_mj.policies import load_policy, save_policy
from quadswarm_mj.training.evaluation import evaluate, make_eval_config
from quadswarm_mj.training.learner import env_meta, obs_layout


def _policy_file(tmp_path, cfg: EnvConfig):
    d = cfg.obs_dim
    rng = np.random.default_rng(0)
    ks = [rng.normal(0, 1 / np.sqrt(d), (d, 8)), rng.normal(0, 0.1, (8, 8))]  # mean and std parameters
    meta = {"activation": "tanh", "obs_dim": d, "action_dim": 4, "env": env_meta(cfg), "obs_layout": obs_layout(cfg)}
    path = tmp_path / "p.npz"
    save_policy(path, ks, [np.zeros(8), np.zeros(8)], np.zeros(d), np.ones(d), meta)
    return load_policy(str(path))


def test_env_meta_records_a_non_default_control_rate_only():
    assert "control_hz" not in env_meta(EnvConfig()) and "sim_hz" not in env_meta(EnvConfig())
    meta = env_meta(EnvConfig(control_hz=50))
    assert meta["control_hz"] == 50 and "sim_hz" not in meta
    meta = env_meta(EnvConfig(control_hz=50, sim_hz=400))
    assert (meta["control_hz"], meta["sim_hz"]) == (50, 400)


def test_evaluation_flies_the_policy_at_its_recorded_rate(tmp_path):
    pol = _policy_file(tmp_path, EnvConfig(num_quads=1, control_hz=50))
    assert pol.env_kwargs["control_hz"] == 50
    cfg = make_eval_config(pol, "static_same_goal")
    assert cfg.control_hz == 50 and cfg.substeps == 4
    assert make_eval_config(pol, "static_same_goal", env={"control_hz": 100}).control_hz == 100  # override wins
    r = evaluate(pol, "static_same_goal", episodes=2, num_quads=1, seed=3, env={"episode_seconds": 0.5})
    assert r.episodes == 2 and np.isfinite(r.summary()["mean_distance"])
    assert make_eval_config(_policy_file(tmp_path, EnvConfig()), "static_same_goal").control_hz == 100


def test_c_export_states_the_rate_the_firmware_must_call_the_policy_at(tmp_path):
    from quadswarm_mj.export import generate_c

    _, hdr = generate_c(_policy_file(tmp_path, EnvConfig(num_quads=1, control_hz=50)))
    assert "#define QS_POLICY_CONTROL_HZ 50" in hdr
    _, hdr = generate_c(_policy_file(tmp_path, EnvConfig(num_quads=1)))
    assert "#define QS_POLICY_CONTROL_HZ 100" in hdr


def test_a_malformed_rate_in_a_policy_file_is_refused_at_load_naming_the_field(tmp_path):
    import pytest

    d = EnvConfig(num_quads=1).obs_dim
    ks, bs = [np.zeros((d, 8)), np.zeros((8, 8))], [np.zeros(8), np.zeros(8)]
    for field, bad in (("control_hz", "fast"), ("control_hz", 50.5), ("control_hz", 0), ("sim_hz", True)):
        path = tmp_path / f"bad_{field}.npz"
        meta = {"activation": "tanh", "obs_dim": d, "action_dim": 4, "env": {"num_quads": 1, field: bad}}
        save_policy(path, ks, bs, np.zeros(d), np.ones(d), meta)
        with pytest.raises(ValueError, match=f"meta env {field} must be a positive int"):
            load_policy(str(path))


def test_c_export_states_how_the_column_inputs_are_formed(tmp_path):
    from quadswarm_mj.config import ObstacleConfig
    from quadswarm_mj.export import generate_c

    for form, code in (("grid", 0), ("slopes", 1), ("near", 2)):
        cfg = EnvConfig(num_quads=2, obstacles=ObstacleConfig(density=0.2, size=0.6, feature_form=form))
        _, hdr = generate_c(_policy_file(tmp_path, cfg))
        assert f"#define QS_POLICY_OBSTACLE_FORM {code}  " in hdr and f": {form} (docs/model.md" in hdr
    _, hdr = generate_c(_policy_file(tmp_path, EnvConfig(num_quads=1)))
    assert "QS_POLICY_OBSTACLE_FORM" not in hdr  # no columns observed
