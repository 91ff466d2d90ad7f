"""gsrmr-experiments --quick: the report is complete and internally consistent (pure, no ROS)."""

from __future__ import annotations

import csv
import itertools
import json
import math
from pathlib import Path

import pytest

from gsrmr_sim.experiments import cli
from gsrmr_sim.experiments.report import PAPER_CLAIMS

SCENES = ("sandbox", "garden")
LTH = ("0.02", "0.025", "0.03", "0.035", "0.04")
METHODS = {"robomr", "ranking", "rounding", "search", "exchange", "maxrate", "fairness", "robogs", "apo", "exact"}


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    base = tmp_path_factory.mktemp("experiments")
    out = base / "report"
    demo = base / "demo-fake"
    demo.mkdir()
    (demo / "summary.json").write_text(json.dumps({"slots": 10, "images_sent": 3, "energy_j": 0.5,
                                                   "energy_upload_all_j": 2.0, "energy_ratio_vs_upload_all": 4.0,
                                                   "mean_loss": 0.01, "psnr_db": 30.0}))
    assert cli.main(["--out", str(out), "--quick", "--cache", str(base / "cache"),
                     "--demo-reports", str(base / "demo-*")]) == 0
    return out


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def test_every_expected_file_exists(report: Path) -> None:
    expected = ["fig4a_apo_convergence.png", "fig4a_apo_convergence.csv", "fig5a_strip.png", "fig5b_profile.png",
                "fig5b_profile.csv", "tradeoff_scheduler.png", "tradeoff_scheduler_apo_n.csv",
                "tradeoff_scheduler_methods.csv", "tradeoff_scheduler_horizon.csv", "tradeoff_renderer.png",
                "tradeoff_renderer.csv", "tradeoff_jpeg.png", "tradeoff_jpeg.csv", "tradeoff_training.png",
                "tradeoff_training.csv", "summary.md", "summary.json"]
    for sc in SCENES:
        expected += [f"fig4b_energy_{sc}.png", f"fig4b_energy_{sc}.csv", f"table1_{sc}.csv",
                     f"sensitivity_loss_scale_{sc}.png", f"sensitivity_loss_scale_{sc}.csv"]
    for name in expected:
        p = report / name
        assert p.is_file() and p.stat().st_size > 0, name
        if name.endswith(".png"):
            assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    listed = set(json.loads((report / "summary.json").read_text())["files"])
    assert set(expected) <= listed
    assert listed == {p.name for p in report.iterdir() if p.is_file()}


def test_summary_json_has_stable_keys(report: Path) -> None:
    s = json.loads((report / "summary.json").read_text())
    for key in ("command", "argv", "quick", "started_utc", "git", "cache", "channel_seed", "seed", "main_scene",
                "settings", "scenes", "fig5", "tradeoffs", "checks", "elapsed_s", "files", "load_average",
                "node_suite", "resolution"):
        assert key in s, key
    # the live pipeline even in --quick: the live camera size and the simulated radio's seed (config/link.yaml)
    assert s["resolution"] == {sc: "320x240" for sc in SCENES}
    assert s["channel_seed"] == 7
    assert s["quick"] is True and s["command"].startswith("gsrmr-experiments ") and "--quick" in s["command"]
    assert set(s["scenes"]) == set(SCENES)
    for sc in SCENES:
        r = s["scenes"][sc]
        assert set(r["claims"]) == set(PAPER_CLAIMS)
        for c in r["claims"].values():
            assert {"paper", "ours", "holds"} <= set(c)
        assert set(r["fig4b"]["per_threshold"]) == set(LTH)
        for v in r["fig4b"]["per_threshold"].values():
            assert set(v["energy_j"]) == METHODS
            assert v["saving_factor_apo"] >= 1.0  # APO never spends more than uploading every image
        assert r["data"]["slots"] == s["settings"][sc]["slots"]
    assert "fig4a" in s["scenes"][s["main_scene"]]
    assert set(s["tradeoffs"]) == {"scheduler", "renderer", "jpeg", "training"}
    assert all(s["checks"].values()), s["checks"]
    assert s["node_suite"]["demo-fake"]["energy_ratio_vs_upload_all"] == 4.0
    md = (report / "summary.md").read_text()
    assert s["command"] in md and "Claims: paper vs ours" in md and "Table 1" in md


def test_energies_and_losses_consistent(report: Path) -> None:
    for sc in SCENES:
        rows = _rows(report / f"fig4b_energy_{sc}.csv")
        assert {r["loss_threshold"] for r in rows} == set(LTH)
        for lth in LTH:
            by = {r["method"]: r for r in rows if r["loss_threshold"] == lth}
            assert set(by) == METHODS
            e = {m: float(r["energy_j"]) for m, r in by.items()}
            assert all(math.isfinite(v) and v > 0 for v in e.values()), e
            for m, r in by.items():
                if r["feasible"] == "True" and m != "exact":
                    assert e["exact"] <= e[m] * (1 + 1e-9), (sc, lth, m)
            assert float(by["robomr"]["mean_loss_predicted"]) == 0.0
            assert by["apo"]["feasible"] == "True" and float(by["apo"]["mean_loss_predicted"]) <= float(lth) + 1e-12
            assert e["robogs"] <= e["apo"] <= e["robomr"]
            total = sum(int(by["apo"][k]) for k in ("images", "keys", "undelivered"))
            assert total == json.loads((report / "summary.json").read_text())["scenes"][sc]["data"]["slots"]
        t1 = _rows(report / f"table1_{sc}.csv")
        for r in t1:
            assert float(r["loss"]) >= 0.0 and 0.0 <= float(r["ssim"]) <= 1.0 + 1e-9
            parts = sum(float(r[k]) for k in ("plan_loss", "jpeg_loss", "pose_loss", "fallback_loss"))
            assert float(r["loss"]) == pytest.approx(parts, abs=1e-9)
            if r["method"] == "apo":
                # measured on composed images: the plan plus what the paper's model leaves out. Image slots carry
                # their JPEG's loss (> 0), so APO's composed loss exceeds its plan whenever it sends an image.
                assert float(r["plan_loss"]) == pytest.approx(float(r["predicted_loss"]), abs=1e-9)
                assert int(r["images"]) > 0 and float(r["jpeg_loss"]) > 0
                assert float(r["loss"]) > float(r["predicted_loss"])
            if r["method"] == "apo_jpeg":  # planned with J_t: its plan + JPEG stays within L_th
                assert float(r["plan_loss"]) + float(r["jpeg_loss"]) <= float(r["loss_threshold"]) + 1e-9


def test_apo_convergence_and_profile(report: Path) -> None:
    conv = _rows(report / "fig4a_apo_convergence.csv")
    assert conv and all(0.0 <= float(r["phi"]) <= 0.25 and float(r["dx_norm"]) >= 0 for r in conv)
    prof = _rows(report / "fig5b_profile.csv")
    s = json.loads((report / "summary.json").read_text())
    assert len(prof) == s["scenes"][s["main_scene"]]["data"]["slots"]
    assert sum(int(r["x"]) for r in prof) == s["fig5"]["apo_images"]
    assert all(float(r["power_w"]) > 0 for r in prof)


def test_better_gs_never_costs_more(report: Path) -> None:
    # Scaling every L_t down only enlarges the feasible set, so the optimum energy cannot rise.
    for sc in SCENES:
        rows = _rows(report / f"sensitivity_loss_scale_{sc}.csv")
        for lth in LTH:
            rr = sorted((r for r in rows if r["loss_threshold"] == lth), key=lambda r: -float(r["loss_scale"]))
            assert len(rr) >= 2
            f = [float(r["saving_factor_exact"]) for r in rr]
            assert all(b >= a * (1 - 1e-9) for a, b in itertools.pairwise(f)), (sc, lth, f)


def test_unknown_scene_is_a_one_line_error(tmp_path: Path, capsys) -> None:
    assert cli.main(["--out", str(tmp_path / "r"), "--scenes", "no_such_scene", "--cache", str(tmp_path / "c")]) == 2
    assert "no_such_scene" in capsys.readouterr().err


def test_training_history_is_read_correctly(report: Path) -> None:
    # Guards the Trainer history format: PSNRs are plausible dB values, the last count is the model's.
    s = json.loads((report / "summary.json").read_text())
    rows = _rows(report / "tradeoff_training.csv")
    for sc in SCENES:
        rr = [r for r in rows if r["scene"] == sc]
        assert rr, sc
        assert all(3.0 < float(r["heldout_psnr_db"]) < 100.0 for r in rr), rr
        assert int(rr[-1]["gaussians"]) == s["scenes"][sc]["data"]["trained_gaussians"]
        assert int(rr[-1]["iteration"]) == s["scenes"][sc]["data"]["train_iterations"]
