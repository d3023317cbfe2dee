"""A certification's estimate before it runs and its counts sized to a time budget (issue 58,
item 2): the planning arithmetic against hand-computed values, the budget's scaling against its
floors, and analyse and the certify job using the counts the plan gives."""

import pytest

from wmrjax import certify as C
from wmrjax.certify import budget as B

ASKED = C.Counts(n_empirical=1024, n_directions=32, n_starts=8, n_samples=512, steps=30, later=1681)
COST = (1e-6, 2.0)  # 1 us per run-step, 2 s to compile the rollout program
N_STEPS = 1000


def test_the_estimate_is_counts_times_the_measured_step_cost():
    """Each stage's seconds by hand: runs x n_steps x cost (the falsifier's typical attempts of
    samples, gradient start-iterations and fine confirmations, each at its measured factor)."""
    est = C.plan(ASKED, cost=COST, n_steps=N_STEPS, n_state=8)
    run = N_STEPS * COST[0]
    stages = {n: s for n, (_, s) in est.stages.items()}
    assert stages["empirical check"] == pytest.approx(1024 * run, rel=1e-12)
    # 33 rays: a grid call of 33 x 48 runs (7 blocks of 256), 17 calls of 99 and 14 of 33 (1 block each)
    assert stages["empirical radius"] == pytest.approx(256 * (7 + 17 + 14) * run, rel=1e-12)
    assert stages["later runs"] == pytest.approx(1681 * run, rel=1e-12)
    assert stages["compiling and certificates"] == pytest.approx(B.COMPILE_RATIO * 2.0, rel=1e-12)
    starts = 8  # gradient_starts(8, 4): 4 sampled, 2 instantaneous, 2 warm
    per_attempt = 512 * run + 0.6 * starts * 31 * run * B.GRADIENT_COST + 28 * 10 * run * B.CONFIRM_COST
    assert stages["falsifier (full)"] == pytest.approx(12 * per_attempt, rel=1e-12)
    assert est.seconds() == pytest.approx(sum(stages.values()), rel=1e-12)
    assert est.scale == 1.0 and est.counts == ASKED
    # memory: the process, and one block of 256 runs saving every step (2 n + 11 floats a sample),
    # or twice the peak resident memory measured so far when that is more
    assert est.memory_bytes == pytest.approx(0.6e9 + 256 * 1001 * (2 * 8 + 11) * 8, rel=1e-12)
    measured = C.plan(ASKED, cost=COST, n_steps=N_STEPS, n_state=8, resident_bytes=1.2e9)
    assert measured.memory_bytes == 2.4e9 and measured.stages == est.stages
    assert "estimate: about" in est.line() and "GB of memory" in est.line()
    no_falsifier = C.plan(ASKED._replace(n_starts=0), cost=COST, n_steps=N_STEPS, n_state=8)
    assert no_falsifier.stages["falsifier (full)"] == (0, 0.0)


def test_a_budget_scales_the_counts_to_fit_it_and_stops_at_the_floors():
    full = C.plan(ASKED, cost=COST, n_steps=N_STEPS, n_state=8)
    least = C.plan(C.scaled(ASKED, 0.0), cost=COST, n_steps=N_STEPS, n_state=8)
    # the confirmations and the gradient stage's windows do not shrink with the scale
    assert 0.45 < least.seconds() / full.seconds() < 0.55  # 0.504 (10 s of it compiling)
    budget = 1.0 + 0.5 * (least.seconds() + full.seconds())
    est = C.plan(ASKED, cost=COST, n_steps=N_STEPS, n_state=8, budget_s=budget, spent_s=1.0)
    assert 0 < est.scale < 1 and est.budget_s == budget
    assert est.seconds() + 1.0 <= budget  # it fits, and only just (the largest scale that does)
    assert C.plan(C.scaled(ASKED, est.scale * 1.01), cost=COST, n_steps=N_STEPS, n_state=8).seconds() + 1.0 > budget
    assert est.counts.n_empirical == round(est.scale * 1024) and est.counts.later == round(est.scale * 1681)
    assert "scaled by" in est.line()
    # a budget the smallest counts cannot meet: every count at its floor, and the estimate says so
    tiny = C.plan(ASKED, cost=COST, n_steps=N_STEPS, n_state=8, budget_s=1e-3)
    assert tiny.counts == C.Counts(64, 8, 4, 64, 8, 169) and tiny.seconds() > 1e-3
    # a budget above the estimate changes nothing; counts below a floor or 0 are never raised
    assert C.plan(ASKED, cost=COST, n_steps=N_STEPS, n_state=8, budget_s=1e9).counts == ASKED
    assert C.scaled(C.Counts(10, 0, 2, 512, 30, 0), 0.01) == C.Counts(10, 0, 2, 64, 8, 0)


@pytest.fixture(scope="module")
def budgeted(paper61):
    """analyse on the section 6.1 loop over 2 s with a budget far below what its counts need."""
    ctrl, params, _ = paper61
    asked = dict(n_empirical=400, n_directions=20, n_starts=8, n_samples=300)
    kw = dict(t_final=2.0, dt=0.02) | asked
    return C.analyse(ctrl, params, budget_s=1e-3, **kw), asked


def test_analyse_runs_the_counts_its_budget_gives(budgeted):
    report, asked = budgeted
    est = report.estimate
    assert est.counts == C.Counts(64, 8, 4, 64, 8, 0)  # the floors: the budget cannot be met
    assert report.empirical_sampling["n_runs"] == 64
    assert len(report.empirical_position.per_direction) == 8 + 1  # the rays and the exact map's worst
    # the falsifier sampled 64 directions per radius it tried (each attempt one sampling stage)
    for f in (report.falsified_full, report.falsified_position):
        assert f.rollouts_by_stage["sampling"] % 64 == 0 and f.rollouts_by_stage["sampling"] > 0
    # every estimated stage was measured, in the same names
    assert set(report.stage_s) == set(est.stages) - {"later runs"}
    assert all(v >= 0 for v in report.stage_s.values())
    assert est.step_cost_s > 0 and est.n_steps == 100


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), "60", True])
def test_a_bad_budget_is_refused_before_any_work(paper61, bad):
    ctrl, params, _ = paper61
    with pytest.raises(ValueError, match="budget_s must be"):
        C.analyse(ctrl, params, t_final=2.0, budget_s=bad)
