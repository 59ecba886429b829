"""The monitor's batched screen: a burst of states checked at once gives
the Health of the same states checked one by one, and both give the Health of the per-state
tests alone (the reference: the screen switched off), on correct runs, on runs with the
paper's planted faults, and on streams with gaps, a restart, a duplicate, a landmark added
or removed and single-state faults of every kind."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from slamlens.common.inprocess_bus import InProcessBus
from slamlens.common.keys import Keys
from slamlens.common.messages import Health, SlamState, Truth
from slamlens.services.monitor import checks
from slamlens.services.monitor.monitor import Monitor
from slamlens.services.monitor.service import BURST_HEALTHS, MonitorService
from slamlens.services.monitor.settings import MonitorSettings
from tests.unit.monitor_runs import run, with_cov

SETTINGS = MonitorSettings()
TOLS = dict(rtol_symmetry=SETTINGS.rtol_symmetry, rtol_correlation=SETTINGS.rtol_correlation,
            rtol_psd=SETTINGS.rtol_psd, atol=SETTINGS.atol_growth)


def _stream(states: list[SlamState], truths: list[Truth]) -> list[SlamState | Truth]:
    """States and truths in arrival order: a state's truth just before it, every third one
    just after it (a late truth: the state waits for it)."""
    by_stamp = {t.stamp: t for t in truths}
    out: list[SlamState | Truth] = []
    late: Truth | None = None
    for k, s in enumerate(states):
        truth = by_stamp.pop(s.stamp, None)
        if truth is not None and k % 3 == 0:
            late = truth
        elif truth is not None:
            out.append(truth)
        out.append(s)
        if late is not None:
            out.append(late)
            late = None
    return out


def _feed(mon: Monitor, items: list[SlamState | Truth]) -> list[bytes]:
    """Truths to the monitor, states checked: the Health of each state, in order."""
    out = []
    for x in items:
        if isinstance(x, Truth):
            mon.add_truth(x)
        else:
            out.append(mon.check(x).to_bytes())
    return out


def _one_by_one(items: list[SlamState | Truth]) -> list[bytes]:
    return _feed(Monitor(SETTINGS), items)


def _in_bursts(items: list[SlamState | Truth], rng: np.random.Generator) -> list[bytes]:
    mon = Monitor(SETTINGS)
    out = []
    k = 0
    while k < len(items):
        burst = items[k:k + int(rng.integers(1, 60))]
        k += len(burst)
        mon.prepare([x for x in burst if isinstance(x, SlamState)])
        out += _feed(mon, burst)
    return out


def _reference(items: list[SlamState | Truth]) -> list[bytes]:
    """The reference: screens that prove nothing, so every state runs every per-state test
    (the monitor as it was before the screen)."""

    def alone(P: np.ndarray, **_: float) -> checks.Screen:
        return checks.Screen(np.zeros(len(P), bool), np.zeros(len(P), bool))

    def pairs(P_prev: np.ndarray, *_: np.ndarray, **__: float) -> checks.PairScreen:
        no = np.zeros(len(P_prev), bool)
        return checks.PairScreen(no, no, no)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(checks, "screen_alone", alone)
        mp.setattr(checks, "screen_pairs", pairs)
        return _one_by_one(items)


def _hostile(states: list[SlamState]) -> list[SlamState]:
    """A stream with a gap, a duplicate, a restart, a landmark removed and then back, and
    single states that break symmetry, PSD, correlation, growth and the predict step."""
    s = list(states[:120])
    base = s[-1]
    P = base.covariance.copy()
    P[7, 8] += 1e-4
    P[8, 7] -= 1e-4
    s.append(with_cov(base, P))  # asymmetric
    P = base.covariance.copy()
    P[0, 9] = P[9, 0] = 1.5 * math.sqrt(P[0, 0] * P[9, 9])
    s.append(with_cov(base, P, seq=base.seq + 2))  # |ρ| > 1 and not PSD
    P = base.covariance.copy()
    P[5:7, 5:7] += 1e-3 * np.eye(2)
    s.append(with_cov(base, P, seq=base.seq + 3))  # a feature grew
    s += states[125:160:3]  # gaps
    s.append(states[159])
    s.append(states[159])  # a duplicate
    k = next(i for i in range(170, 200) if states[i].step == "predict")
    P = states[k].covariance.copy()
    P[3:5, 3:5] *= 0.999  # a predict that touched the map
    s += states[160:k] + [with_cov(states[k], P, seq=states[k].seq)] + states[k + 1:200]
    last = s[-1]
    keep = [0, 1, 3, 4, 5][:max(1, last.n - 1)]
    rows = np.r_[0:3, [3 + 2 * i + a for i in keep for a in (0, 1)]]
    s.append(SlamState(robot="r", seq=last.seq + 1, stamp=last.stamp, step="update",
                       pose=last.pose, landmark_ids=last.landmark_ids[keep],
                       landmarks=last.landmarks[keep],
                       covariance=last.covariance[np.ix_(rows, rows)]))  # one removed
    s += states[200:230]  # ... and back
    s += states[:40]  # seq going back: a restart
    return s


RUNS = {
    "correct": dict(seed=1, steps=130),
    "map fault": dict(seed=2, map_fault=(1, 6), onset=8.0, steps=130),
    "cross-covariance fault": dict(seed=3, cross_fault=(3,), onset=8.0, steps=130),
}


@pytest.mark.parametrize("name", list(RUNS))
def test_bursts_one_by_one_and_the_per_state_tests_give_the_same_health(name: str) -> None:
    states, truths = run(**RUNS[name])
    for hostile in (False, True):
        stream = _stream(_hostile(states) if hostile else states, truths)
        bursts = _in_bursts(stream, np.random.default_rng(7))
        single = _one_by_one(stream)
        reference = _reference(stream)
        assert len(reference) == sum(isinstance(x, SlamState) for x in stream)
        assert bursts == single == reference
        healths = [Health.from_bytes(b) for b in reference]
        kinds = {v.kind for h in healths for v in h.violations}
        if name == "correct" and not hostile:
            assert kinds <= {"nees", "nis"} and all(not h.suspects.size for h in healths)
        if name != "correct":  # the planted faults are named in every variant
            assert kinds & {"pair", "feature", "prediction"}
        if hostile:  # every planted kind seen
            assert {"symmetry", "correlation", "psd", "feature", "prediction"} <= kinds


def test_screens_agree_with_the_per_state_tests_entry_for_entry() -> None:
    """On random covariances, clean and broken: a state is screened clean exactly when the
    per-state test finds nothing (structure, growth, predict step; PSD when the smallest
    eigenvalue is not within rounding of the tolerance)."""
    rng = np.random.default_rng(5)
    n = 6
    N = 3 + 2 * n
    stack, prev_stack, poses_prev, poses_cur = [], [], [], []
    for k in range(120):
        A = rng.normal(size=(N, N))
        P_prev = A @ A.T / N + 1e-3 * np.eye(N)
        P = P_prev.copy()
        kind = k % 6
        if kind == 1:  # shrink the map by an update-like PSD downdate: clean
            H = rng.normal(size=(2, N))
            S = H @ P_prev @ H.T + np.eye(2)
            K_ = P_prev @ H.T @ np.linalg.inv(S)
            P = P_prev - K_ @ S @ K_.T
            P = 0.5 * (P + P.T)
        elif kind == 2:  # a feature grows
            i = 3 + 2 * int(rng.integers(n))
            P[i:i + 2, i:i + 2] += 1e-2 * np.eye(2)
        elif kind == 3:  # asymmetric
            P[4, 9] += 1e-3
        elif kind == 4:  # indefinite
            w, V = np.linalg.eigh(P)
            w[0] = -1e-2
            P = (V * w) @ V.T
        elif kind == 5:  # |ρ| > 1
            P[1, 11] = P[11, 1] = 1.2 * math.sqrt(P[1, 1] * P[11, 11])
        stack.append(P)
        prev_stack.append(P_prev)
        poses_prev.append(rng.normal(size=3))
        poses_cur.append(rng.normal(size=3))
    Ps, Pp = np.stack(stack), np.stack(prev_stack)
    alone = checks.screen_alone(Ps, **TOLS)
    predict = np.ones(len(Ps), bool)
    pairs = checks.screen_pairs(Pp, Ps, np.stack(poses_prev), np.stack(poses_cur), predict,
                                rtol_growth=SETTINGS.rtol_growth, atol_growth=SETTINGS.atol_growth,
                                rtol_prediction=SETTINGS.rtol_prediction)
    pos = np.arange(n)
    for k in range(len(Ps)):
        asym, corr = checks.structure(Ps[k], rtol_symmetry=TOLS["rtol_symmetry"],
                                      rtol_correlation=TOLS["rtol_correlation"],
                                      atol=TOLS["atol"])
        assert alone.structure[k] == (asym.count == 0 and corr.count == 0), k
        Mp, Mc = Pp[k][3:, 3:], Ps[k][3:, 3:]
        grew = (checks.feature_growth(Mp, Mc, rtol=SETTINGS.rtol_growth,
                                      atol=SETTINGS.atol_growth).count
                + checks.pair_growth(Mp, Mc, rtol=SETTINGS.rtol_growth,
                                     atol=SETTINGS.atol_growth).count)
        assert pairs.growth[k] == (grew == 0), k
        assert pairs.unchanged[k] == np.array_equal(Mp, Mc)
        map_changed, cross, noise = checks.prediction_residuals(
            Pp[k], Ps[k], poses_prev[k], poses_cur[k], pos, pos,
            rtol=SETTINGS.rtol_prediction, atol=SETTINGS.atol_growth)
        if pairs.prediction[k]:
            assert map_changed.count == cross.count == 0 and noise is None
    # per matrix (a stack of one each), the PSD screen is the per-state test
    for k in range(len(Ps)):
        one = checks.screen_alone(Ps[k:k + 1], **TOLS)
        neg = checks.min_eigenvalue_if_indefinite(Ps[k], rtol=TOLS["rtol_psd"], atol=TOLS["atol"])
        assert bool(one.psd[0]) == (neg is None), k
    # every kind was present, so the screens said both clean and not clean
    assert alone.structure.any() and not alone.structure.all()
    assert not alone.psd.any()  # an indefinite matrix sends the stack to the per-state test
    assert pairs.growth.any() and not pairs.growth.all()


def test_predict_steps_of_a_correct_filter_are_screened_clean() -> None:
    """The screen is not just "not clean": on a correct run it proves the predicts clean."""
    states, _ = run(seed=1, steps=120)
    for a, b in zip(states[60:-1], states[61:], strict=True):
        if b.step != "predict" or a.n != b.n:
            continue
        pairs = checks.screen_pairs(a.covariance[None], b.covariance[None], a.pose[None],
                                    b.pose[None], np.ones(1, bool),
                                    rtol_growth=SETTINGS.rtol_growth,
                                    atol_growth=SETTINGS.atol_growth,
                                    rtol_prediction=SETTINGS.rtol_prediction)
        assert pairs.unchanged[0] and pairs.growth[0] and pairs.prediction[0]
        alone = checks.screen_alone(b.covariance[None], **TOLS)
        assert alone.structure[0] and alone.psd[0]


def test_the_service_checks_a_burst_as_one_by_one() -> None:
    """Through the service (decode, robot check, duplicates, rejections counted in their
    turn): a burst taken at once publishes the Health of samples handled one by one."""
    keys = Keys("t")
    states, truths = run(seed=2, map_fault=(1, 6), onset=8.0, steps=130)
    stream = _stream(_hostile(states), truths)
    samples = [(keys.truth("r") if isinstance(x, Truth) else keys.state("r"), x.to_bytes())
               for x in stream]
    samples.insert(50, (keys.state("r"), b"\x93not a state"))
    samples.insert(90, (keys.truth("r"), b"\xc1"))

    def published(burst: bool) -> list[bytes]:
        bus = InProcessBus()
        out: list[bytes] = []
        bus.subscribe(keys.health("r"), lambda k, p: out.append(p))
        service = MonitorService(bus, keys=keys, robot="r",
                                 settings=MonitorSettings(robot="r"))
        for key, payload in samples:
            if burst:
                bus.put(key, payload)
            else:
                service.handle(key, payload)
        while burst and service.step(timeout=0):
            pass
        assert service.drops.total == 2
        return out

    def without_backlog(payloads: list[bytes]) -> list[Health]:
        healths = [Health.from_bytes(p) for p in payloads]
        for h in healths:
            h.statistics.pop("behind")
        return healths

    one, many = published(False), published(True)
    assert len(one) == len(many) > 200
    assert without_backlog(one) == without_backlog(many)
    # in a burst, "behind" counts what of the burst is still to come
    assert Health.from_bytes(many[0]).statistics["behind"] == len(samples) - 1


def test_a_burst_s_healths_are_put_back_to_back_and_get_answers_the_health_seen() -> None:
    """The Healths of a burst are put in groups of at most BURST_HEALTHS (one Zenoh batch
    for many), each once, in order; a ``get`` made as a Health is received answers that
    Health: never an older one, never one still waiting in the burst."""
    keys = Keys("t")
    states, _truths = run(seed=2, steps=60)
    bus = InProcessBus()
    service = MonitorService(bus, keys=keys, robot="r", settings=MonitorSettings(robot="r"))
    put: list[int] = []
    answered: list[int] = []  # the seq a get answers with while each Health is put
    checked_by_then: list[int] = []  # states checked when each Health was put

    def on_health(_key: str, payload: bytes) -> None:
        put.append(Health.from_bytes(payload).seq)
        checked_by_then.append(service.checked)
        replies = bus.get(keys.health("r"))
        answered.append(Health.from_bytes(replies[0].payload).seq if replies else -1)

    bus.subscribe(keys.health("r"), on_health)
    for s in states:
        bus.put(keys.state("r"), s.to_bytes())
    while service.step(timeout=0):
        pass
    seqs = [s.seq for s in states]
    assert put == seqs  # every state's Health, once, in order
    assert answered == put
    # held for the burst: each Health went out once its group of BURST_HEALTHS was checked
    assert len(set(checked_by_then)) == -(-len(seqs) // BURST_HEALTHS)
    assert checked_by_then[0] == min(BURST_HEALTHS, len(seqs))
    assert Health.from_bytes(bus.get(keys.health("r"))[0].payload).seq == seqs[-1]


def test_a_burst_without_a_state_to_check_is_taken_and_the_next_states_checked() -> None:
    """A burst of truths, a rejected sample and another robot's state (no state of its own
    robot to screen) is taken without a check; the states after it are checked as usual."""
    keys = Keys("t")
    states, truths = run(seed=1, steps=20)
    bus = InProcessBus()
    out: list[Health] = []
    bus.subscribe(keys.health("r"), lambda _k, p: out.append(Health.from_bytes(p)))
    service = MonitorService(bus, keys=keys, robot="r", settings=MonitorSettings(robot="r"))
    other = SlamState(robot="q", seq=1, stamp=0.0, step="init", pose=states[0].pose,
                      landmark_ids=states[0].landmark_ids, landmarks=states[0].landmarks,
                      covariance=states[0].covariance)
    for t in truths:
        bus.put(keys.truth("r"), t.to_bytes())
    bus.put(keys.state("r"), b"\x93not a state")
    bus.put(keys.state("r"), other.to_bytes())
    assert service.step(timeout=0) == len(truths) + 2
    assert out == [] and service.drops.total == 2
    for s in states:
        bus.put(keys.state("r"), s.to_bytes())
    while service.step(timeout=0):
        pass
    alone = Monitor(MonitorSettings(robot="r"))  # the same truths, then the states
    for t in truths:
        alone.add_truth(t)
    expected = [alone.check(s) for s in states]
    for h in out:
        h.statistics.pop("behind")
        for k in ("lost", "restarts", "dropped", "sampled_out"):
            h.statistics.pop(k)
    assert out == expected
    assert any("nees_pose" in h.statistics for h in out)  # the truths were kept


def test_the_service_counts_the_states_ok_with_a_timid_nis_and_says_so() -> None:
    """The correct run with every S × 4 and its truth, through the service: the states "ok"
    with a NIS window below its band standing are counted apart, and the last lines say
    how many; without the truth there are none (those states are "tuning")."""
    from slamlens.services.monitor.cli import verdict_sentence

    keys = Keys("t")
    states, truths = run(seed=1)
    timid = [s if s.innovation_covariances is None else dataclasses.replace(
        s, innovation_covariances=s.innovation_covariances * 4.0) for s in states]

    def summary(with_truth: bool) -> dict:
        service = MonitorService(InProcessBus(), keys=keys, robot="r",
                                 settings=MonitorSettings(robot="r", nis_window=20))
        for x in _stream(timid, truths if with_truth else []):
            key = keys.truth("r") if isinstance(x, Truth) else keys.state("r")
            service.handle(key, x.to_bytes())
        return service.summary()

    seen, blind = summary(True), summary(False)
    assert seen["states_ok_with_timid_nis"] > 100
    assert seen["states_by_verdict"]["tuning"] > 0  # before the first NEES window passed
    assert blind["states_ok_with_timid_nis"] == 0 and blind["states_by_verdict"]["tuning"] > 0
    assert (f"{seen['states_ok_with_timid_nis']} ok with a NIS window below its band "
            "standing") in verdict_sentence(seen)
    assert "below its band" not in verdict_sentence(blind)
