"""The sensitivity studies: the paper's findings, the bound, determinism, settings, CLI."""

import dataclasses
import json
import math

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from replay.cli import main
from replay.parallel import single_blas_thread
from replay.studies import (
    CSV_COLUMNS,
    SensitivitySettings,
    Task,
    baseline_agreement,
    closed_form_errors,
    findings,
    make_tasks,
    read_table,
    run_sensitivity,
    simulate_task,
    stepped_errors,
    study_points,
    ukf_errors,
)
from tracker.estimators import make_estimator
from tracker.reconstruction import Reconstructor

# Small but statistically meaningful: every finding is checked on these seeded tables.
SMALL = SensitivitySettings(
    seed=1,
    trials=160,
    chunk_trials=80,
    noise_levels_mm=(0.0, 0.5, 1.0, 2.0, 4.0),
    theta_L1_deg=(10.0, 50.0, 90.0, 130.0, 170.0),
    theta_L2_deg=(10.0, 50.0, 90.0, 130.0, 170.0),
    deflection_levels_mm=(0.0, 4.0, 8.0),
)
# Tiny: for determinism and plumbing.
TINY = SensitivitySettings(
    seed=11,
    trials=30,
    chunk_trials=20,
    noise_levels_mm=(0.0, 1.0),
    theta_L1_deg=(45.0, 90.0),
    theta_L2_deg=(45.0,),
    deflection_levels_mm=(0.0, 5.0),
)
CLI_TINY = [
    "--trials", "20", "--ukf-trials", "2", "--chunk-trials", "10", "--noise-levels-mm", "0", "1",
    "--theta-l1-deg", "45", "90", "--theta-l2-deg", "60", "--deflection-levels-mm", "0", "4",
    "--workers", "1", "--no-progress",
]  # fmt: skip


@pytest.fixture(scope="module")
def small_run():
    return run_sensitivity(SMALL, workers=1, progress=False)


def by_claim(result):
    return {f.claim: f for f in findings(result.rows)}


def rows_equal(a, b):
    def same(x, y):
        return x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y))

    return (
        all(
            r.keys() == s.keys() and all(same(r[k], s[k]) for k in r)
            for study in a
            for r, s in zip(a[study], b[study], strict=True)
        )
        and a.keys() == b.keys()
    )


# ------------------------------------------------------------------------------ the findings
@pytest.mark.parametrize(
    "claim",
    [
        "Body Positions is at least as good as Tip Position",
        "Tip Velocity is the most sensitive to noise",
        "Position-based errors grow toward the straight configuration",
        "Position-based errors grow with deflection",
        "The UKF is at or below the per-frame estimators (model exact)",
        "The per-frame position estimators sit on the bound where the model is exact",
    ],
)
def test_the_papers_findings_hold(small_run, claim):
    finding = by_claim(small_run)[claim]
    assert finding.holds, finding.detail


def test_tables_hold_every_method_and_the_bound_at_every_point(small_run):
    points = study_points(SMALL)
    methods = ["tip-position", "body-positions", "tip-velocity", "ukf"]
    bounds = ["crb-tip", "crb-body", "crb-velocity", "crb-all-frames"]
    for study in "abc":
        rows = small_run.rows[study]
        n_points = sum(p.study == study for p in points)
        assert len(rows) == n_points * (len(methods) + len(bounds))
        for r in rows:
            expected = SMALL.effective_ukf_trials if r["method"] == "ukf" else SMALL.trials
            assert r["n"] <= expected
            if r["kind"] == "bound":
                assert r["median_deg"] == pytest.approx(0.6745 * r["rms_deg"], rel=1e-3)


def test_errors_grow_with_noise_and_vanish_without_it(small_run):
    for delta_2 in SMALL.delta_2_deg:
        for method in ("tip-position", "body-positions"):
            medians = [
                r["median_deg"]
                for r in small_run.rows["a"]
                if r["method"] == method and r["delta_2_deg"] == delta_2
            ]
            assert medians[0] < 1e-9  # zero noise: exact
            assert all(b > a for a, b in zip(medians, medians[1:], strict=False))


def test_straight_configuration_has_an_infinite_bound(small_run):
    straight = [
        r
        for r in small_run.rows["b"]
        if r["theta_L1_deg"] == 90 and r["theta_L2_deg"] == 90 and r["method"] == "crb-body"
    ]
    assert straight and all(r["rms_deg"] == math.inf for r in straight)


@pytest.mark.parametrize("view", ["orthographic", "pinhole"])
@pytest.mark.parametrize("delta_2", [0.0, 90.0])
def test_per_frame_estimators_attain_the_bound_where_the_model_is_exact(delta_2, view):
    """Small noise, no deflection: RMS error = Cramer-Rao bound within Monte Carlo error.

    Tip Velocity too, once the noise dominates its finite-difference bias (the chord over one
    frame interval is not the tangent at the last frame: about 2 deg at zero noise).
    """
    settings = SensitivitySettings(
        seed=5,
        trials=600,
        chunk_trials=600,
        ukf_trials=0,
        studies=("a",),
        delta_2_deg=(delta_2,),
        view=view,
        noise_levels_mm=(0.05, 0.5),
        methods=("tip-position", "body-positions", "tip-velocity", "crb"),
    )
    rows = run_sensitivity(settings, workers=1, progress=False).rows["a"]
    rms = {(r["noise_mm"], r["method"]): r["rms_deg"] for r in rows}
    tolerance = 4 / math.sqrt(2 * settings.trials)
    for noise in settings.noise_levels_mm:
        for method, bound in (("tip-position", "crb-tip"), ("body-positions", "crb-body")):
            assert rms[noise, method] / rms[noise, bound] == pytest.approx(1, abs=tolerance)
    assert rms[0.05, "tip-velocity"] / rms[0.05, "crb-velocity"] == pytest.approx(1, abs=0.2)


# ------------------------------------------------------------------------------ fast path
@pytest.mark.parametrize("view", ["orthographic", "pinhole"])
def test_batched_trials_are_what_the_live_pipeline_makes_of_their_frames(view):
    settings = dataclasses.replace(TINY, view=view, delta_2_deg=(90.0,))
    point = [p for p in study_points(settings) if p.study == "c" and p.deflection_mm > 0][0]
    data = simulate_task(settings, Task(point, 0, 0, 4))
    reconstructor = Reconstructor(
        data.catheter, data.scene.rig, data.scene.R_w_b, data.scene.o_b_w_mm
    )
    closed = {
        name: closed_form_errors(data, kind)
        for name, kind in (("tip-position", "tip"), ("body-positions", "body"),
                           ("tip-velocity", "velocity"))
    }  # fmt: skip
    for i in range(4):
        frames = data.batch.frames(i)
        reconstructor.reset()
        live = [reconstructor.observe(f) for f in frames]
        fast = data.observations(i)
        for a, b in zip(live, fast, strict=True):
            for name in ("tip_b_mm", "tip_cov_b", "markers_b_mm", "markers_cov_b",
                         "velocity_b_mm_s", "velocity_cov_b", "velocity_tip_cov_b"):  # fmt: skip
                if getattr(a, name) is None:  # no velocity on the first frame
                    assert getattr(b, name) is None
                    continue
                assert getattr(a, name) == pytest.approx(getattr(b, name), rel=1e-9, abs=1e-9)
        # The batched closed forms are the per-frame estimators on the last frame.
        for name, errors in closed.items():
            estimate = make_estimator(name, data.catheter).step(live[-1])
            error = (estimate.delta_L_rad - frames[-1].delta_L_true_rad + np.pi) % (2 * np.pi)
            assert error - np.pi == pytest.approx(errors[i], abs=1e-7)


def test_the_ukf_runs_on_every_trial_by_default():
    assert SensitivitySettings().effective_ukf_trials == SensitivitySettings().trials == 500
    assert SMALL.effective_ukf_trials == SMALL.trials


@pytest.mark.parametrize("view", ["orthographic", "pinhole"])
def test_batched_ukf_is_the_ukf_stepped_trial_by_trial(view):
    """Every point of TINY (bent and straight, noise 0 and 1 mm, both deflections, both
    delta_2): the batched filter's final errors are BendingPlaneUKF's, for both UKF variants."""
    settings = dataclasses.replace(TINY, view=view)
    for point in study_points(settings):
        data = simulate_task(settings, Task(point, 0, 0, 12))
        for method in ("ukf", "ukf-position"):
            batched = ukf_errors(data, method, 12)
            stepped = stepped_errors(data, method, 12)
            np.testing.assert_array_equal(np.isnan(batched), np.isnan(stepped))
            np.testing.assert_allclose(batched, stepped, rtol=0, atol=1e-9)


def test_least_squares_baseline_agrees_with_the_closed_form_away_from_straight():
    rates = baseline_agreement(TINY, trials_per_point=2, workers=1, progress=False)
    assert rates["trials"] == 3 * 2 * len(study_points(TINY))
    assert rates["bent"] == 1.0


# ------------------------------------------------------------------------------ determinism
def test_same_seed_same_tables_with_one_or_two_workers_and_on_dask():
    from dask.distributed import LocalCluster

    one = run_sensitivity(TINY, workers=1, progress=False)
    two = run_sensitivity(TINY, workers=2, progress=False)
    with LocalCluster(
        processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None
    ) as cluster:
        dask = run_sensitivity(TINY, scheduler=cluster.scheduler_address, progress=False)
    assert rows_equal(one.rows, two.rows)
    assert rows_equal(one.rows, dask.rows)
    other_seed = run_sensitivity(dataclasses.replace(TINY, seed=12), workers=1, progress=False)
    assert not rows_equal(one.rows, other_seed.rows)


def test_tasks_have_independent_streams_and_cover_every_trial():
    tasks = make_tasks(TINY, study_points(TINY))
    keys = [t.seed_key for t in tasks]
    assert len(set(keys)) == len(keys)
    for point in study_points(TINY):
        mine = [t for t in tasks if t.point == point]
        assert [(t.start, t.stop) for t in mine] == [(0, 20), (20, 30)]


def _blas_threads() -> list[int]:
    return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]


def test_tasks_run_on_one_blas_thread_and_the_last_one_out_restores_the_count():
    """Tasks in threads of one process (a Dask worker) leave in any order."""
    before = _blas_threads()
    first, second = single_blas_thread(), single_blas_thread()
    first.__enter__()
    second.__enter__()
    assert all(n == 1 for n in _blas_threads())
    first.__exit__(None, None, None)
    assert all(n == 1 for n in _blas_threads())
    second.__exit__(None, None, None)
    assert _blas_threads() == before


# ------------------------------------------------------------------------------ bad settings
@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(noise_levels_mm=(0.0, -1.0)), r"noise levels must be non-negative \(mm\), got -1"),
        (dict(noise_mm=-0.5), r"noise must be non-negative \(mm\), got -0.5"),
        (dict(theta_L1_deg=()), r"the theta_L1 grid \(study b\) is empty"),
        (dict(deflection_levels_mm=()), r"the deflection levels \(study c\) is empty"),
        (dict(delta_2_deg=(0.0, 90.0, 0.0)), r"the delta_2 list has 0 twice"),
        (dict(methods=("tip-position", "kalman")), r"unknown method 'kalman'; choose from"),
        (dict(studies=("d",)), r"unknown study 'd'"),
        (dict(view="fisheye"), r"unknown view 'fisheye'"),
        (dict(trials=0), r"trials must be at least 1"),
        (dict(frames_per_trial=1), r"frames_per_trial must be at least 2"),
        (dict(joint_rates=(1.0, 2.0)), r"joint_rates needs three values"),
        (dict(frame_interval_s=0.0), r"frame_interval_s must be positive"),
    ],
)
def test_bad_settings_are_one_clear_error(changes, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(TINY, **changes)


def test_unreachable_configuration_fails_before_any_work():
    settings = dataclasses.replace(TINY, theta_L1_deg=(300.0,))
    with pytest.raises(ValueError, match="theta_L1 = 300 deg is not reachable"):
        run_sensitivity(settings, workers=1, progress=False)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--noise-levels-mm", "-1", "0"], "noise levels must be non-negative (mm), got -1"),
        (["--theta-l1-deg"], "the theta_L1 grid (study b) is empty"),
        (["--methods", "tip-position", "magic"], "unknown method 'magic'"),
        (["--configuration-deg", "45"], "configuration_theta_L_deg needs two tip angles"),
    ],
)
def test_cli_bad_settings_end_in_one_line(tmp_path, capsys, argv, message):
    code = main(["sensitivity", *CLI_TINY, "--out", str(tmp_path), *argv])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("cathtrack sensitivity: error: ") and message in err
    assert err.count("\n") == 1
    assert not any(tmp_path.iterdir())


# ------------------------------------------------------------------------------ CLI outputs
def test_cli_writes_tables_figures_summary_and_settings(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["sensitivity", *CLI_TINY, "--seed", "4", "--out", str(out)]) == 0
    names = {p.name for p in out.iterdir()}
    expected = {f"study_{s}.{ext}" for s in "abc" for ext in ("csv", "png")}
    assert expected | {"summary.md", "settings.json"} == names
    for s in "abc":
        rows = read_table(out / f"study_{s}.csv")
        assert rows and list(rows[0]) == list(CSV_COLUMNS)
        assert (out / f"study_{s}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    record = json.loads((out / "settings.json").read_text())
    assert record["seed"] == 4 and record["settings"]["trials"] == 20
    assert record["settings"]["joint_rates"] == [0.5, 0.25, 0.25]
    assert record["settings"]["frame_interval_s"] == 0.05
    summary = (out / "summary.md").read_text()
    assert "## Study a" in summary and "findings" in summary
    assert "wrote 8 files" in capsys.readouterr().out
    # The saved settings reproduce the tables exactly.
    again = tmp_path / "again"
    argv = ["sensitivity", "--settings", str(out / "settings.json"), "--workers", "1"]
    assert main([*argv, "--no-progress", "--out", str(again)]) == 0
    for s in "abc":
        assert (again / f"study_{s}.csv").read_text() == (out / f"study_{s}.csv").read_text()
