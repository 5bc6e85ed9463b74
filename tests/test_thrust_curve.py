"""Static thrust curve of the airframe presets against Bitcraze's measured PWM-to-thrust table
(tests/reference_data/crazyflie2_thrust.json), through the motor model's own command -> thrust map
(steady state of the lag, noise off), and the size of the paper's linear model's gap."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from quadswarm_mj.actuation import (
    hover_motor_state,
    hover_motor_state_mapped,
    inverse_thrust_map,
    rotor_positions,
    substep_wrench,
    thrust_map,
)
from quadswarm_mj.config import QUAD_PRESETS, EnvConfig, QuadParams
from quadswarm_mj.randomization import nominal_draws, params_from_draws

DATA = json.loads((Path(__file__).parent / "reference_data" / "crazyflie2_thrust.json").read_text())
G0 = 9.80665  # m/s^2, grams-force -> N


def _table() -> tuple[np.ndarray, np.ndarray]:
    t = DATA["pwm_to_thrust_table"]
    rows = np.array(t["rows"], float)
    cols = t["columns"]
    return rows[:, cols.index("pwm_percent")] / 100.0, rows[:, cols.index("thrust_g")] * G0 / 1000.0


def static_total_thrust(quad: QuadParams, pwm: np.ndarray, substeps: int = 400) -> np.ndarray:
    """Total thrust (N) of the four rotors at constant command ``pwm`` after the motor lag has
    settled, computed by the actuation chain (substep_wrench) with noise off."""
    cfg = EnvConfig(num_quads=len(pwm), quad=quad).without_noise()
    p = params_from_draws(cfg, nominal_draws(cfg, np.zeros(1)))
    cmd = np.repeat(pwm[:, None], 4, axis=1)
    u, R, rp = np.zeros_like(cmd), np.broadcast_to(np.eye(3), (len(pwm), 3, 3)), rotor_positions(quad)
    for _ in range(substeps):
        u, _, force, _ = substep_wrench(u, cmd, np.zeros_like(cmd), p, R, rp,
                                        thrust_quadratic=quad.thrust_map_quadratic)
    return force[:, 2]


def _rel_gap(quad: QuadParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pwm, meas = _table()
    model = static_total_thrust(quad, pwm)
    nz = meas > 0
    return pwm[nz], (model[nz] - meas[nz]) / meas[nz], np.abs(model - meas) / meas.max()


def test_identified_preset_matches_the_table() -> None:
    """Within 10 % of every measured thrust from 12.5 % to 93.75 % PWM (the fitted range); at the
    first point, 6.25 % PWM = 1.6 g, the motors are starting up (thrust far below the quadratic
    trend of the rest of the table) and the gap there is bounded in absolute terms instead: within
    3 % of the table's full scale (as every point). At 0 PWM the model gives 0 like the table."""
    quad = QuadParams.preset("crazyflie21_identified")
    pwm, rel, abs_fs = _rel_gap(quad)
    fitted = pwm >= 0.125
    assert np.abs(rel[fitted]).max() < 0.10
    assert abs_fs.max() < 0.03
    assert static_total_thrust(quad, np.array([0.0]))[0] == 0.0


def test_gap_of_the_paper_linear_model() -> None:
    """Documents the gap of the paper's linear model (thrust_max * cmd, thrust-to-weight 1.9 at
    28 g) against the same table, taking the command as the PWM fraction: it is large at low PWM
    (the measured curve is convex) and under-predicts the top of the range. The figures asserted
    here are quoted in the README section "Beyond the paper"."""
    pwm, rel, abs_fs = _rel_gap(QuadParams.preset("quadswarm"))
    assert 1.0 < rel[0] < 1.2  # +108 % at 6.25 % PWM
    assert 0.35 < rel[1] < 0.42  # +38 % at 12.5 %
    assert -0.16 < rel[-1] < -0.12  # -14 % at 93.75 %
    fitted = pwm >= 0.125
    assert np.abs(rel[fitted]).max() > 0.3  # fails the 10 % criterion the identified preset meets
    assert 0.12 < abs_fs.max() < 0.16  # ~14 % of full scale


def test_gap_of_the_firmware_quadratic() -> None:
    """The firmware's own pwm -> thrust fit (a p^2 + b p per rotor, identified on a 2.1 in 2021)
    against the 2015 table: within 4 % of full scale but up to 18 % relative at low PWM; why the
    preset uses a fit to the table instead."""
    c = DATA["firmware_constants"]
    pwm, meas = _table()
    fw = 4.0 * (c["pwm_to_thrust_a_n"] * pwm**2 + c["pwm_to_thrust_b_n"] * pwm)
    nz = meas > 0
    rel = (fw[nz] - meas[nz]) / meas[nz]
    assert 0.15 < np.abs(rel).max() < 0.20
    assert np.abs(fw - meas).max() / meas.max() < 0.04
    assert np.abs(rel[pwm[nz] >= 0.5]).max() < 0.06


def test_preset_values_and_sources() -> None:
    q = QuadParams.preset("crazyflie21_identified")
    c, fit = DATA["firmware_constants"], DATA["preset_fit"]
    assert q.mass == c["mass_kg"] and q.arm == c["arm_length_m"]
    assert q.inertia == tuple(DATA["foerster_2015"]["inertia_kg_m2_diag"])
    assert q.torque_to_thrust == c["thrust_to_torque_m"] == 0.005964552
    np.testing.assert_allclose(q.thrust_max, fit["thrust_max_n_per_rotor"], rtol=1e-12)
    assert q.thrust_map_quadratic == fit["q"]
    assert q.motor_settling_time == DATA["motor_response"]["settling_time_s"]
    assert QuadParams.preset("quadswarm") == QuadParams()
    assert EnvConfig(quad="crazyflie21_identified").quad == q
    assert QuadParams.preset("crazyflie21_identified", mass=0.03).mass == 0.03
    assert set(QUAD_PRESETS) == {"quadswarm", "crazyflie21_identified"}
    with pytest.raises(ValueError, match="quad preset must be one of"):
        EnvConfig(quad="crazyflie3")
    with pytest.raises(ValueError, match=r"quad.thrust_map_quadratic must be .*<= 1"):
        QuadParams(thrust_map_quadratic=1.5)


def test_thrust_map_inverse_and_hover() -> None:
    f = np.linspace(0.0, 1.0, 101)
    for qv in (0.0, 0.4302, 1.0):
        t = thrust_map(f, qv)
        assert t[0] == 0.0 and t[-1] == 1.0 and np.all(np.diff(t) > 0)
        np.testing.assert_allclose(inverse_thrust_map(t, qv), f, atol=1e-12)
    np.testing.assert_array_equal(thrust_map(f, 0.0), f)
    # hover: the mapped hover state balances gravity through the map
    quad = QuadParams.preset("crazyflie21_identified")
    cfg = EnvConfig(num_quads=1, quad=quad)
    p = params_from_draws(cfg, nominal_draws(cfg, np.zeros(1)))
    u = hover_motor_state_mapped(p, quad.thrust_map_quadratic)
    total = np.sum(p["thrust_max"] * thrust_map(u * u, quad.thrust_map_quadratic))
    np.testing.assert_allclose(total, quad.mass * quad.gravity, rtol=1e-12)
    np.testing.assert_allclose(u[0, 0] ** 2, quad.hover_command, rtol=1e-12)
    np.testing.assert_array_equal(hover_motor_state_mapped(p, 0.0), hover_motor_state(p))
