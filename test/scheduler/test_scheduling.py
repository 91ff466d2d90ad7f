"""GSCLO scheduler: link closed forms, channel model, exact knapsack vs brute force, baselines, extremes, CLI."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import hypothesis as hyp
from hypothesis import strategies as st
import numpy as np
import pytest

from gsrmr_common import link_model as link
from gsrmr_common.channel import ChannelModel, paper_route_distances
from gsrmr_scheduler import cli, rate_allocation
from gsrmr_scheduler.baselines import relaxed_solution
from gsrmr_scheduler.problem import Problem, ProblemError
from gsrmr_scheduler.solve import METHODS, method_options, solve

FAST_METHODS = [m for m in METHODS if m != "apo"]


def paper_problem(T: int, seed: int, lth: float = 0.03, **kw) -> Problem:
    rng = np.random.default_rng(seed + 1000)
    gains = ChannelModel(seed=seed).gains(paper_route_distances(T))
    return Problem(channel_gain=gains, gs_loss=rng.uniform(0, 0.096, T), loss_threshold=lth, **kw)


def brute_force_energy(p: Problem) -> float | None:
    """Minimum energy over all 2^T binary schedules (vectorised enumeration)."""
    T = p.slots
    X = (np.arange(2**T)[:, None] >> np.arange(T)) & 1
    if np.any(~p.key_ok):
        return None
    X = X[~np.any((X == 1) & ~p.image_ok, axis=1)]
    loss = (1 - X) @ p.gs_loss
    near = np.abs(loss - p.loss_budget) <= 1e-9 * max(p.loss_budget, 1e-300)
    ok = loss <= p.loss_budget
    for r in np.flatnonzero(near):  # settle boundary cases with the exact test every method uses
        ok[r] = p.budget_ok(X[r])
    if not ok.any():
        return None
    energy = X[ok] @ p.energy_image_j + (1 - X[ok]) @ p.energy_key_j
    return float(energy.min())


def check_invariants(p: Problem, s) -> None:
    assert s.x.dtype == np.int8 and s.x.shape == (p.slots,)
    assert set(np.unique(s.x)) <= {0, 1}
    assert np.all(np.isfinite(s.power_w)) and np.all(s.power_w >= 0)
    assert math.isfinite(s.energy_j) and math.isfinite(s.mean_loss)
    assert s.energy_j == pytest.approx(p.slot_s * float(np.sum(s.power_w)), rel=1e-9, abs=1e-300)
    if s.feasible:
        assert s.mean_loss <= p.loss_threshold * (1 + 1e-12) + 1e-15
    assert len(s.delivered) == p.slots
    json.dumps(s.to_json(), allow_nan=False)


# ---- link -----------------------------------------------------------------------------------------------
def test_required_power_matches_formula_and_rate_inverts_it():
    g = np.array([1e-6, 3e-5, 2.0])
    p = link.required_power_w(67_200, g, 0.1, 1e6, 1e-9)
    direct = 1e-9 / g * (2 ** (67_200 / (0.1 * 1e6)) - 1)
    np.testing.assert_allclose(p, direct, rtol=1e-12)
    bits = link.slot_bits(p, g, 0.1, 1e6, 1e-9)
    np.testing.assert_allclose(bits, 67_200, rtol=1e-12)
    assert link.required_power_w(192, 1e-6, 0.1, 1e6, 1e-9) == pytest.approx(1e-3 * math.expm1(192 * math.log(2) / 1e5))
    assert link.energy_j(np.array([1.0, 2.0]), 0.1) == pytest.approx(0.3)
    assert link.energy_j(2.0, 0.1) == pytest.approx(0.2)


def test_required_power_is_inf_not_nan_at_overflow_and_dead_channel():
    assert link.required_power_w(67_200, 1e-6, 0.1, 1.0, 1e-9) == math.inf  # 2^(672000) overflows
    assert link.required_power_w(67_200, 0.0, 0.1, 1e6, 1e-9) == math.inf
    assert link.required_power_w(0.0, 0.0, 0.1, 1e6, 1e-9) == 0.0
    lp = link.log_required_power_w(67_200, 1e-6, 0.1, 1.0, 1e-9)
    assert math.isfinite(lp) and lp == pytest.approx(math.log(1e-3) + 672_000 * math.log(2), rel=1e-12)


# ---- channel --------------------------------------------------------------------------------------------
def test_channel_is_seeded_and_has_paper_mean_gain():
    d = np.full(40_000, 10.0)
    g1 = ChannelModel(seed=3).gains(d)
    g2 = ChannelModel(seed=3).gains(d)
    np.testing.assert_array_equal(g1, g2)
    assert not np.array_equal(g1, ChannelModel(seed=4).gains(d))
    # E|h|² = ρ0·d^−α (unit-power small-scale fading): −30 dB · 10^−3 = 1e-6.
    assert float(np.mean(g1)) == pytest.approx(1e-6, rel=0.03)
    pos = np.array([[0.0, 0.0], [7.0, 0.0]])
    gp = ChannelModel(seed=1, k_factor=1e12).gains_from_positions(pos, np.array([10.0, 0.0]))
    # Pure LoS: |h|² equals the path loss exactly.
    np.testing.assert_allclose(gp, [1e-3 * 10.0**-3, 1e-3 * 3.0**-3], rtol=1e-4)
    with pytest.raises(ValueError):
        ChannelModel().gains(np.array([0.0]))


# ---- exact ----------------------------------------------------------------------------------------------
def test_exact_equals_brute_force_on_small_random_instances():
    rng = np.random.default_rng(5)
    for trial in range(120):
        T = int(rng.integers(1, 17)) if trial % 10 else 16
        gains = ChannelModel(seed=trial).gains(rng.uniform(3, 20, T))
        losses = rng.uniform(0, 0.1, T)
        if trial % 4 == 0:
            losses = np.round(losses, 2)  # ties and zeros
        if trial % 7 == 0:
            gains[:] = gains[0]  # equal gains (ranking optimal, Prop. 2)
        p = Problem(channel_gain=gains, gs_loss=losses, loss_threshold=float(rng.uniform(0, 0.08)))
        s = solve(p, "exact")
        best = brute_force_energy(p)
        assert best is not None and s.feasible
        assert s.energy_j == pytest.approx(best, rel=1e-9), trial
        assert s.optimality_gap == 0.0
        check_invariants(p, s)


def test_exact_not_worse_than_any_feasible_method():
    for seed in range(4):
        for lth in (0.0, 0.02, 0.03, 0.04, 0.06):
            p = paper_problem(200, seed, lth)
            ex = solve(p, "exact")
            assert ex.feasible and ex.optimality_gap == 0.0
            lb = relaxed_solution(p)[1]
            assert lb <= ex.energy_j * (1 + 1e-9)
            for m in ("ranking", "rounding", "search", "robomr", "robogs"):
                s = solve(p, m)
                check_invariants(p, s)
                if s.feasible:
                    assert ex.energy_j <= s.energy_j * (1 + 1e-12), (m, lth)
            if lth == 0.03:
                assert solve(p, "search").energy_j <= solve(p, "ranking").energy_j * (1 + 1e-12)


def test_exact_time_limit_returns_certified_gap():
    p = paper_problem(3000, 7, 0.03)
    opt = solve(p, "exact")
    s = solve(p, "exact", time_limit_s=1e-9)
    check_invariants(p, s)
    assert s.feasible and s.optimality_gap is not None and s.optimality_gap >= 0
    lb = s.extras["energy_lower_bound_j"]
    assert lb <= opt.energy_j * (1 + 1e-9) <= s.energy_j * (1 + 2e-9)
    if s.energy_j > opt.energy_j * (1 + 1e-9):
        assert s.optimality_gap > 0 and any("time limit" in n for n in s.notes)


def test_exact_100k_slots():
    p = paper_problem(100_000, 11, 0.03)
    s = solve(p, "exact", time_limit_s=30.0)
    check_invariants(p, s)
    assert s.feasible and s.optimality_gap == 0.0
    assert s.energy_j <= solve(p, "ranking").energy_j
    assert s.energy_j <= solve(p, "rounding").energy_j * (1 + 1e-12)
    assert s.energy_j >= relaxed_solution(p)[1] * (1 - 1e-9)


# ---- extremes -------------------------------------------------------------------------------------------
def _all_methods(p: Problem, **kw):
    return {m: solve(p, m, **kw.get(m, {})) for m in FAST_METHODS}


def test_single_slot():
    for lth, expect in ((0.0, 1), (0.05, 0)):
        p = Problem(channel_gain=[1e-6], gs_loss=[0.05], loss_threshold=lth)
        for _m, s in _all_methods(p).items():
            check_invariants(p, s)
        assert int(solve(p, "exact").x[0]) == expect


def test_zero_threshold_means_all_images_and_big_threshold_all_keys():
    p = paper_problem(150, 2, 0.0)
    ex = solve(p, "exact")
    assert ex.feasible and np.all(ex.x == 1) and ex.mean_loss == 0.0
    assert ex.energy_j == pytest.approx(solve(p, "robomr").energy_j)
    p2 = paper_problem(150, 2, 1.0)
    p2 = Problem(channel_gain=p2.channel_gain, gs_loss=p2.gs_loss, loss_threshold=float(np.mean(p2.gs_loss)))
    for m in ("exact", "ranking", "rounding", "search", "apo"):
        s = solve(p2, m, **({"iterations": 1} if m == "apo" else {}))
        assert s.feasible and np.all(s.x == 0), m
    for s in _all_methods(p).values():
        check_invariants(p, s)


def test_zero_threshold_keeps_zero_loss_slots_as_keys():
    p = Problem(channel_gain=[1e-6, 2e-6, 3e-6], gs_loss=[0.0, 0.02, 0.0], loss_threshold=0.0)
    assert solve(p, "exact").x.tolist() == [0, 1, 0]
    assert solve(p, "ranking").x.tolist() == [0, 1, 0]


def test_all_losses_equal_and_all_zero():
    rng = np.random.default_rng(1)
    gains = ChannelModel(seed=1).gains(rng.uniform(8, 12, 5000))
    p = Problem(channel_gain=gains, gs_loss=np.full(5000, 0.05), loss_threshold=0.03)
    s = solve(p, "exact")
    k = int(np.sum(s.x == 0))
    assert k == math.floor(5000 * 0.03 / 0.05 + 1e-9) or k == math.floor(5000 * 0.03 / 0.05 + 1e-9) - 1
    # Equal weights: keys go to the slots that save most (worst channels).
    sav = p.saving_j
    assert sav[s.x == 0].min() >= sav[s.x == 1].max()
    assert s.optimality_gap == 0.0
    for s2 in _all_methods(p).values():
        check_invariants(p, s2)
    pz = Problem(channel_gain=gains, gs_loss=np.zeros(5000), loss_threshold=0.0)
    for m, s3 in _all_methods(pz).items():
        check_invariants(pz, s3)
        if m in ("exact", "ranking", "rounding", "search"):
            assert s3.feasible and np.all(s3.x == 0) and s3.mean_loss == 0.0


def test_gains_over_eighteen_decades():
    rng = np.random.default_rng(3)
    T = 400
    gains = 10.0 ** rng.uniform(-16, 2, T)
    gains[0], gains[1] = 1e-16, 1e2
    p = Problem(channel_gain=gains, gs_loss=rng.uniform(0, 0.1, T), loss_threshold=0.03)
    ex = solve(p, "exact")
    assert ex.feasible and ex.optimality_gap == 0.0
    for m, s in _all_methods(p).items():
        check_invariants(p, s)
        if s.feasible and m not in ("maxrate", "fairness"):
            assert ex.energy_j <= s.energy_j * (1 + 1e-12), m
    # The 1e-16 slot saves by far the most: it must be a key when any budget is available.
    assert ex.x[0] == 0


def test_overflowing_image_exponent_is_handled_in_log_domain():
    # τB = 10 bit: 2^(I/τB) = 2^6720 overflows float64, 2^(S/τB) = 2^19.2 does not.
    gains = np.full(6, 1e-6)
    losses = np.array([0.01, 0.02, 0.03, 0.01, 0.02, 0.03])
    p = Problem(channel_gain=gains, gs_loss=losses, loss_threshold=0.01, bandwidth_hz=100.0)
    assert not p.image_ok.any() and p.key_ok.all()
    for m, s in _all_methods(p).items():
        check_invariants(p, s)
        if m in ("exact", "ranking", "rounding", "search", "robomr"):
            assert not s.feasible, m
    ex = solve(p, "exact")
    assert any("cannot carry an image" in n for n in ex.notes)
    p_ok = Problem(channel_gain=gains, gs_loss=losses, loss_threshold=0.02, bandwidth_hz=100.0)
    ex2 = solve(p_ok, "exact")
    assert ex2.feasible and np.all(ex2.x == 0) and ex2.optimality_gap == 0.0
    check_invariants(p_ok, ex2)
    # Mixed: only some slots overflow (gain so large/small that the energy is not representable).
    # I/(τB) = 100: slot 2's image energy ~1e300 J is not representable, its key (~1e269 J) is.
    g = np.array([1e-6, 1e-6, 1e-280, 1e-6])
    pm = Problem(channel_gain=g, gs_loss=[0.05, 0.01, 0.02, 0.04], loss_threshold=0.01, bandwidth_hz=6720.0)
    assert pm.image_ok.tolist() == [True, True, False, True]
    sm = solve(pm, "exact")
    assert sm.feasible and sm.x[2] == 0 and sm.x.tolist() == [1, 0, 0, 1]


def test_dead_channel_is_infeasible_with_reason():
    p = Problem(channel_gain=[1e-6, 0.0, 1e-6], gs_loss=[0.01, 0.01, 0.01], loss_threshold=0.05)
    for m, s in _all_methods(p).items():
        check_invariants(p, s)
        if m not in ("maxrate", "fairness", "robogs"):
            assert not s.feasible, m
    assert any("cannot carry even a pose key" in n for n in solve(p, "exact").notes)


def test_maxrate_and_fairness_spend_the_budget_and_classify_delivery():
    p = paper_problem(288, 4, 0.03)
    ex = solve(p, "exact")
    for m in ("maxrate", "fairness"):
        s = solve(p, m)
        check_invariants(p, s)
        assert s.energy_j == pytest.approx(ex.energy_j, rel=1e-9)
        bits = link.slot_bits(s.power_w, p.channel_gain, p.slot_s, p.bandwidth_hz, p.noise_w)
        for t in range(p.slots):
            want = "image" if bits[t] >= p.image_bits * (1 - 1e-9) else "key" if bits[t] >= p.pose_bits * (1 - 1e-9) \
                else "none"
            assert s.delivered[t] == want
        # A smaller budget can only deliver fewer images.
        s_small = solve(p, m, energy_budget_j=ex.energy_j / 10)
        assert s_small.energy_j == pytest.approx(ex.energy_j / 10, rel=1e-9)
        assert s_small.delivered.count("image") <= s.delivered.count("image")
        s_pen = solve(p, m, undelivered_loss=1.0)
        assert s_pen.mean_loss >= s.mean_loss
    fair = solve(p, "fairness")
    rates = link.rate_bps(fair.power_w, p.channel_gain, p.bandwidth_hz, p.noise_w)
    np.testing.assert_allclose(rates, rates[0], rtol=1e-9)
    mr = solve(p, "maxrate")
    live = mr.power_w > 0
    level = mr.power_w[live] + p.noise_w / p.channel_gain[live]
    np.testing.assert_allclose(level, level[0], rtol=1e-9)
    assert np.all(p.noise_w / p.channel_gain[~live] >= level[0] * (1 - 1e-12))


def test_rate_allocation_budget_comes_from_the_registry_not_an_import():
    """maxrate / fairness get the energy of ``budget_from`` through ``solve`` (the registry); called directly
    they need a budget, and a budget taken from another budget spender is refused instead of recursing."""
    p = paper_problem(60, 2, 0.03)
    ranking = solve(p, "ranking")
    s = solve(p, "maxrate", budget_from="ranking")
    assert s.energy_j == pytest.approx(ranking.energy_j, rel=1e-9)
    assert s.notes[0].startswith("energy budget = ranking energy")
    assert "budget_from" in method_options("fairness")
    assert "budget_from" not in method_options("exact")
    with pytest.raises(ValueError, match="spends an energy budget"):
        rate_allocation.solve_fairness(p)
    assert rate_allocation.solve_fairness(p, energy_budget_j=ranking.energy_j).energy_j == pytest.approx(
        ranking.energy_j, rel=1e-9)
    with pytest.raises(ValueError, match="budget_from must be a method that chooses its own energy"):
        solve(p, "fairness", budget_from="maxrate")
    with pytest.raises(ValueError, match="budget_from must be"):
        solve(p, "maxrate", budget_from="magic")


def test_solve_rejects_unknown_method_and_option():
    p = paper_problem(10, 1)
    with pytest.raises(ValueError, match="unknown method"):
        solve(p, "magic")
    with pytest.raises(ValueError, match="no option"):
        solve(p, "exact", iterations=3)


@pytest.mark.parametrize(("patch", "field"), [
    ({"slot_s": 0}, "slot_s"), ({"channel_gain": [1e-6, -1.0]}, "channel_gain"),
    ({"gs_loss": [0.1]}, "gs_loss"), ({"gs_loss": [0.1, float("nan")]}, "gs_loss"),
    ({"channel_gain": [1e-6, float("inf")]}, "channel_gain"), ({"gs_loss": [0.1, -0.2]}, "gs_loss"),
    ({"loss_threshold": -0.1}, "loss_threshold"), ({"noise_w": "a"}, "noise_w"),
    ({"image_bits": 100}, "image_bits"),
])
def test_problem_validation_names_field(patch, field):
    base = {"slot_s": 0.1, "image_bits": 67_200, "pose_bits": 192, "bandwidth_hz": 1e6, "noise_w": 1e-9,
            "channel_gain": [1e-6, 2e-6], "gs_loss": [0.01, 0.02], "loss_threshold": 0.01}
    base.update(patch)
    with pytest.raises(ProblemError) as err:
        Problem.from_dict(base)
    assert err.value.field == field


# ---- CLI ------------------------------------------------------------------------------------------------
def _problem_file(tmp_path, **patch):
    d = paper_problem(40, 9).to_dict()
    for k, v in patch.items():
        if v is None:
            d.pop(k)
        else:
            d[k] = v
    f = tmp_path / "p.json"
    f.write_text(json.dumps(d))
    return str(f)


def test_cli_solves_and_writes_output(tmp_path, capsys):
    f = _problem_file(tmp_path)
    out = tmp_path / "o.json"
    assert cli.main([f, "--method", "exact", "-o", str(out)]) == 0
    res = json.loads(out.read_text())
    for key in ("method", "x", "power_w", "energy_j", "mean_loss", "feasible", "solve_time_s", "iterations",
                "history", "optimality_gap"):
        assert key in res
    assert res["optimality_gap"] == 0.0 and res["history"] is None and len(res["x"]) == 40
    assert cli.main([f, "--method", "apo", "--option", "iterations=2", "--option", "beta=1e5"]) == 0
    res2 = json.loads(capsys.readouterr().out)
    assert res2["method"] == "apo" and len(res2["history"]) >= 1
    assert res2["energy_j"] >= res["energy_j"] * (1 - 1e-12)


@pytest.mark.parametrize(("patch", "args", "field"), [
    ({"gs_loss": None}, [], "gs_loss"), ({"gs_loss": [0.1] * 39}, [], "gs_loss"),
    ({"channel_gain": [float("nan")] * 40}, [], "channel_gain"), ({"gs_loss": [-0.1] * 40}, [], "gs_loss"),
    ({"channel_gain": [-1e-6] * 40}, [], "channel_gain"), ({"loss_threshold": -1}, [], "loss_threshold"),
    ({"channel_gain": [float("inf")] * 40}, [], "channel_gain"),
    ({}, ["--method", "nope"], "method"), ({}, ["--option", "bogus=1"], "bogus"),
])
def test_cli_bad_input_exits_2_with_one_line(tmp_path, capsys, patch, args, field):
    f = _problem_file(tmp_path, **patch)
    argv = [f, *(args if "--method" in args else ["--method", "exact", *args])]
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and field in err and "Traceback" not in err


def test_cli_console_script_and_make_problem(tmp_path):
    out = tmp_path / "p.json"
    r = subprocess.run([sys.executable, "-m", "gsrmr_scheduler.cli", "make-problem", "--slots", "30",
                        "--seed", "2", "-o", str(out)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    data = json.loads(out.read_text())
    assert len(data["channel_gain"]) == 30 and data["loss_threshold"] == 0.03
    r = subprocess.run([sys.executable, "-m", "gsrmr_scheduler.cli", str(out), "--method", "ranking"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and json.loads(r.stdout)["feasible"] is True
    r = subprocess.run([sys.executable, "-m", "gsrmr_scheduler.cli", str(tmp_path / "missing.json"),
                        "--method", "exact"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "problem" in r.stderr


# ---- property: no method ever returns NaN, negative power, or a false feasibility claim ----------------
@hyp.settings(max_examples=40, deadline=None, database=None)
@hyp.given(
    T=st.integers(1, 24),
    log_gain_lo=st.floats(-16, 2),
    log_gain_span=st.floats(0, 18),
    lth=st.floats(0, 0.2),
    log_bw=st.floats(1, 7),
    seed=st.integers(0, 2**16),
)
def test_property_every_method_is_sane(T, log_gain_lo, log_gain_span, lth, log_bw, seed):
    rng = np.random.default_rng(seed)
    gains = 10.0 ** rng.uniform(log_gain_lo, min(2.0, log_gain_lo + log_gain_span), T)
    losses = np.where(rng.random(T) < 0.2, 0.0, rng.uniform(0, 0.1, T))
    p = Problem(channel_gain=gains, gs_loss=losses, loss_threshold=lth, bandwidth_hz=10.0**log_bw)
    ex = solve(p, "exact")
    if T <= 12:
        best = brute_force_energy(p)
        assert ex.feasible == (best is not None)
        if best is not None:
            assert ex.energy_j == pytest.approx(best, rel=1e-9)
    for m in FAST_METHODS:
        s = solve(p, m)
        check_invariants(p, s)
        if s.feasible and m not in ("maxrate", "fairness"):
            assert ex.feasible and ex.energy_j <= s.energy_j * (1 + 1e-12), m
