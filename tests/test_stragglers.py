"""Stragglers near theta = 0: the certificate that a start cannot settle before the horizon (status NOT_SETTLING),
checked against SciPy's Radau, and the run's one pool of stragglers (bits independent of the chunk size)."""
import numpy as np
import pytest

import jaxsleigh as js
from jaxsleigh.controllers.paper import PaperLaw
from jaxsleigh.integrate.stragglers import MARGIN, cannot_settle, certify, damping_floor
from jaxsleigh.model.closed_loop import ClosedLoop
from jaxsleigh.status import DESCRIPTIONS, Status, converged, counts_in_words, integrated

#: a start certified on the default basin of seed 5 (|q(100 s)| = 132 m in float64 Radau)
FAR = [-2.58646016, -2.99752719, -0.13364724]


def _w_state(q_norm, n=1):
    """A w-chart state at |q| = q_norm: w1 = 1 (theta = 1), w3 = 0, z2 = w2 = sqrt(q_norm^2 - 1), at rest."""
    w2 = np.sqrt(q_norm ** 2 - 1.0)
    return np.tile(np.array([[1.0], [w2], [0.0], [0.0], [0.0]]), (1, n))


def test_the_bound_is_the_dissipation_inequality():
    """|q| - eps > MARGIN sqrt((T - t) H_d / d): exactly there, and only for OK lanes short of the horizon."""
    d = 4.0
    y = _w_state(1000.0, 4)
    t = np.array([10.0, 10.0, 10.0, 100.0])
    # H_d at which the reach MARGIN sqrt(90 H / 4) equals 1000 - 0.05
    h_edge = (1000.0 - 0.05) ** 2 * d / (MARGIN ** 2 * 90.0)
    Hd = np.array([0.99 * h_edge, 1.01 * h_edge, 0.5 * h_edge, 0.5 * h_edge])
    st = np.zeros(4, np.int32)
    got = cannot_settle(t, y, Hd, st, t_final=100.0, eps=0.05, d=d)
    assert got.tolist() == [True, False, True, False]          # the last is at the horizon
    st[2] = Status.BUDGET_EXHAUSTED
    assert cannot_settle(t, y, Hd, st, t_final=100.0, eps=0.05, d=d).tolist() == [True, False, False, False]
    assert not cannot_settle(t, _w_state(1.0 + 1e-9, 4), Hd * 0, st * 0, t_final=100.0, eps=2.0, d=d).any()


def test_the_damping_floor_is_the_smallest_eigenvalue_of_the_injection():
    args = ClosedLoop(js.paper_plant(), js.paper_gains())
    assert float(damping_floor(args)) == pytest.approx(4.0)
    g = js.gains(L=[2.0, 0.5, 0.8], k=0.1, D_hat=[[4.0, 1.0], [1.0, 4.0]])
    assert float(damping_floor(ClosedLoop(js.paper_plant(), g))) == pytest.approx(3.0)
    # no certificate for a law other than the paper's, nor for negative gains
    assert damping_floor(ClosedLoop(js.paper_plant(), PaperLaw())) is None
    neg = js.paper_gains()._replace(k=-0.1)
    assert damping_floor(ClosedLoop(js.paper_plant(), neg)) is None
    assert certify(np.zeros(1, np.int32), np.zeros(1), _w_state(1e4), np.ones(1), args=ClosedLoop(
        js.paper_plant(), neg), t_final=100.0, eps=0.05) is None


def test_the_new_status_is_described_and_counted_as_not_settled():
    assert Status.NOT_SETTLING == 9 and "horizon" in DESCRIPTIONS[Status.NOT_SETTLING]
    st = np.array([0, 9, 4, 1])
    T = np.array([3.0, np.inf, np.nan, np.nan])
    assert converged(st, T).tolist() == [True, False, False, False]
    assert integrated(st).tolist() == [True, True, True, False]
    assert "1 not_settling" in counts_in_words(st)


@pytest.fixture(scope="module")
def far_run():
    return js.run_basin(np.array([FAR, [1.0, 1.0, 1.0]]), t_final=100.0,
                        run=js.RunOptions(progress=False, audit=False))


@pytest.mark.slow
def test_a_far_start_is_stopped_early_and_reported_unsettled(far_run):
    r = far_run
    assert r.status.tolist() == [Status.NOT_SETTLING, Status.OK]
    assert np.isinf(r.T_eps[0]) and np.isfinite(r.T_eps[1])
    assert r.not_converged.tolist() == [True, False] and not r.failed.any()
    assert np.isnan(r.q_final[0]).all()
    assert r.fraction == 0.5


@pytest.mark.slow
def test_the_certified_start_does_not_settle_in_float64_radau(far_run):
    """The reference (Radau, float64, rtol = atol = 1e-8, physical chart) ends the certified start far outside the
    ball at the horizon, and the engine stopped it long before (fewer steps than a tenth of the OK run's)."""
    import jax
    from scipy.integrate import solve_ivp
    from numpy_field import numpy_field

    f, jac = numpy_field(ClosedLoop(js.paper_plant(), js.paper_gains()))
    with jax.enable_x64(True):
        sol = solve_ivp(f, (0.0, 100.0), np.r_[FAR, 0.0, 0.0], method="Radau", rtol=1e-8, atol=1e-8, jac=jac)
    assert sol.status == 0 and np.linalg.norm(sol.y[:3, -1]) > 100.0
    assert far_run.n_steps[0] < 2000


def test_a_flying_start_out_of_budget_stays_budget_exhausted():
    """A start near theta = 0 whose budget runs out in its flight (H_d still huge) is not certified: status 4."""
    r = js.run_ensemble([[1.9, -0.04, 2e-4]], t_final=100.0, stepsize=js.StepSizeController(max_steps=3000),
                        run=js.RunOptions(progress=False))
    assert r.status.tolist() == [Status.BUDGET_EXHAUSTED]


@pytest.mark.slow
def test_the_pool_of_stragglers_gives_the_same_bits_whatever_the_chunk_size(monkeypatch):
    """Stragglers in every part go to the one pool; its batches (64-256 lanes) step each lane with the same bits
    whatever else is in them, so chunks of 2048 and of 4096 starts give the same bytes, certified lanes included,
    and lanes switched to the implicit step too (the switch brought down to 2,000 attempts, so that some do)."""
    import jaxsleigh.studies.ensemble as ens

    monkeypatch.setattr(ens, "STIFF_AFTER", 2000)
    rng = np.random.default_rng(11)
    ics = np.column_stack([rng.uniform(-3, 3, (4096, 2)), rng.uniform(0.3, 3, 4096) * rng.choice([-1, 1], 4096)])
    ics[::128, 2] = rng.uniform(0.003, 0.02, 32)            # stragglers in every part
    runs = [js.run_basin(ics, t_final=6.0, run=js.RunOptions(chunk_size=c, progress=False, audit=False))
            for c in (2048, 4096)]
    for f in ("q_final", "p_final", "T_eps", "n_steps", "n_rejected", "status", "u_energy"):
        np.testing.assert_array_equal(getattr(runs[0], f), getattr(runs[1], f), err_msg=f)
    assert np.any(runs[0].n_steps > 20 * np.median(runs[0].n_steps))      # the stragglers were there
    assert np.sum(runs[0].n_steps + runs[0].n_rejected > 3000) >= 4        # and some took implicit steps


@pytest.mark.slow
def test_a_run_killed_while_its_stragglers_run_resumes_from_its_parts_to_the_same_bytes(tmp_path, monkeypatch):
    """The parts' states of a chunk are written (pending_*.npz) before its stragglers go to the pool; a run that dies
    while they run has no chunk file, and resuming continues the stragglers from those states to the same bytes."""
    import jaxsleigh.studies.ensemble as ens

    rng = np.random.default_rng(3)
    ics = np.column_stack([rng.uniform(-3, 3, (2048, 2)), rng.uniform(0.3, 3, 2048)])
    ics[::64, 2] = 0.01                                      # stragglers in both parts
    run = js.RunOptions(chunk_size=2048, progress=False, audit=False)
    whole = js.run_basin(ics, t_final=4.0, run=run)

    def dead(self, lanes, rows):
        raise KeyboardInterrupt

    monkeypatch.setattr(ens._Chunks, "run_stragglers", dead)
    with pytest.raises((KeyboardInterrupt, RuntimeError)):
        js.run_basin(ics, t_final=4.0, run=run._replace(checkpoint_dir=tmp_path / "ck"))
    assert [p.name for p in (tmp_path / "ck").glob("*_*.npz")] == ["pending_000000.npz"]
    monkeypatch.undo()
    resumed = js.run_basin(ics, t_final=4.0, run=run._replace(checkpoint_dir=tmp_path / "ck", resume=True))
    for f in ("q_final", "T_eps", "n_steps", "status", "u_energy"):
        np.testing.assert_array_equal(getattr(resumed, f), getattr(whole, f), err_msg=f)
    assert sorted(p.name for p in (tmp_path / "ck").glob("*_*.npz")) == ["chunk_000000.npz"]
    assert np.any(whole.n_steps > 10 * np.median(whole.n_steps))
