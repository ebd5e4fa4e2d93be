"""The filter step in one compiled call (tracker.estimators.ukf_step) is the stage-by-stage
step, to the last bit.

``step_3d`` runs the predict, the update and the report of the usual frame inside one
compiled function; when a frame needs more (a trial whose slot-0 hypothesis does not update,
several hypotheses), it stops after the predict and the bank goes on with the stages one by
one. Forcing it to stop after the predict on every frame gives the stage-by-stage filter:
on seeded trials that go through every rule (starts, restarts, added hypotheses, outliers,
missing points, model mismatch), both must give the same estimates, flags, NIS, counts and
innovations, bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest

from models.catheter import default_catheter
from tests.tracker.test_ukf_batch import SETTINGS, observations, random_trials
from tracker.estimators import ukf_core, ukf_step
from tracker.estimators.ukf import BendingPlaneUKF


def run(catheter, settings, data, trials, monkeypatch, fused: bool):
    """Every trial's estimates as arrays, and how often step_3d finished the update."""
    real = ukf_step.step_3d
    finished = []

    def counted(*args):
        if not fused:  # first_only False: stop after the predict
            args = args[:33] + (False,) + args[34:]  # first_only
        result = real(*args)
        finished.append(result[0] == ukf_step.FINISHED_UPDATE)
        return result

    monkeypatch.setattr(ukf_core.ukf_step, "step_3d", counted)
    ukf = BendingPlaneUKF(catheter, settings)
    rows = []
    for i in range(trials):
        ukf.reset()
        for observation in observations(i, *data):
            e = ukf.step(observation)
            innovation = () if e.innovation is None else tuple(e.innovation)
            rows.append((e.delta_L_rad, e.std_rad, e.flags.value, e.nis, e.nis_dof,
                         e.rejected_outliers, e.informative_radius_mm, innovation))  # fmt: skip
    monkeypatch.undo()
    return rows, sum(finished), len(finished)


@pytest.mark.parametrize("name", sorted(SETTINGS))
def test_the_step_in_one_call_is_the_stage_by_stage_step(name, monkeypatch):
    catheter = default_catheter(np.pi / 2)
    data = random_trials(catheter, np.random.default_rng(sum(map(ord, name))), n_trials=30)
    fused, finished, calls = run(catheter, SETTINGS[name], data, 30, monkeypatch, True)
    staged, finished_staged, _ = run(catheter, SETTINGS[name], data, 30, monkeypatch, False)
    # The usual frame finishes in one call, the others go the general way (with a large
    # process noise every frame restarts from its closed form: all of them).
    assert finished_staged == 0 and finished < calls, (finished, calls)
    if name != "large process noise":
        assert finished > 0.5 * calls, (finished, calls)
    assert len(fused) == len(staged)
    for a, b in zip(fused, staged, strict=True):
        # NaN == NaN here: compare the bit patterns of the floats.
        assert np.array_equal(np.array(a[:7], float), np.array(b[:7], float), equal_nan=True)
        assert a[7] == b[7]
