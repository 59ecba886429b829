"""The batched screen of the monitor (docs/monitor.md, "Bursts").

A burst of states is screened at once, as stacks (``checks.screen_alone`` /
``screen_pairs``): which states are symmetric with |ρ| ≤ 1, PSD, and — against the state
before them, with the same landmarks in the same order — have an unchanged map block, no
growth and a clean predict step. The per-state checks then skip what the screen proved
clean. A state checked without being screened, or after another previous state than the
screen assumed, is screened on its own, so the Health of a burst is the Health of the same
states checked one by one. The screen also gives each state its features' own blocks (for
their NEES), the PSD screen's Cholesky factor (for the unobservable directions) and where
its prediction linearised.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from slamlens.common.messages import SlamState
from slamlens.services.monitor import checks
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.monitor.stats import BlockTerms, block_terms
from slamlens.services.monitor.unobservable import UnobservableCheck, predict_points


@dataclass(frozen=True)
class Screened:
    """What the batched screen (``checks.screen_*``) proved clean for one state."""

    state: SlamState  #: the state screened (held: its id keys the screen)
    prev: SlamState | None  #: the previous state the pair tests assumed
    structure: bool  #: no asymmetry, no |ρ| > 1
    psd: bool  #: PSD within tolerance
    #: against ``prev`` (same landmarks, same order): (map block unchanged, nothing grew,
    #: predict-step tests pass); None: the per-state tests decide
    pair: tuple[bool, bool, bool] | None
    terms: BlockTerms  #: the features' own blocks, for their NEES
    factor: np.ndarray | None  #: lower Cholesky factor of sym(P) + tol·I (PSD screen)
    #: where this state's prediction Fx is measured from (None: not checkable)
    before: np.ndarray | None


class Screen:
    """The screens of the states of the burst being checked, by state."""

    def __init__(self, settings: MonitorSettings, unobservable: UnobservableCheck) -> None:
        self.settings = settings
        #: whose robot point (where the predictions linearised) the screen follows
        self._unobservable = unobservable
        self._screens: dict[int, Screened] = {}

    def reset(self) -> None:
        self._screens = {}

    def prepare(self, prev: SlamState | None, states: Sequence[SlamState]) -> None:
        """Screen ``states``, to be checked in this order after ``prev``."""
        self._screens = {}
        if not states:  # a burst of truths, rejections or other robots' states only
            return
        start = 0
        # where each state's prediction linearised, followed through the whole burst
        before = predict_points(self._unobservable.robot, [prev, *states[:-1]], list(states))
        for k in range(1, len(states) + 1):  # runs of one covariance size
            if k == len(states) or states[k].covariance.shape != states[start].covariance.shape:
                self._screen_run(prev, states[start:k], before[start:k])
                prev = states[k - 1]
                start = k

    def take(self, state: SlamState, prev: SlamState | None) -> Screened:
        """The screen of ``state`` after ``prev`` (from :meth:`prepare`, else made now)."""
        got = self._screens.pop(id(state), None)
        if got is None or got.state is not state:
            self._screen_run(prev, [state])
            got = self._screens.pop(id(state))
        if got.prev is not prev:  # checked after another state than the screen assumed
            self._screen_run(prev, [state])
            fresh = self._screens.pop(id(state))
            got = dataclasses.replace(got, prev=prev, pair=fresh.pair, before=fresh.before)
        return got

    def _screen_run(self, prev: SlamState | None, run: Sequence[SlamState],
                    before: list[np.ndarray | None] | None = None) -> None:
        """Screen ``run`` (states of one covariance size, in order after ``prev``)."""
        s = self.settings
        P = np.stack([x.covariance for x in run])
        K, N = len(run), P.shape[1]
        n = (N - 3) // 2
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            at = np.arange(n)
            blocks = P[:, 3:, 3:].reshape(K, n, 2, n, 2)[:, at, :, at, :]  # [n, K, 2, 2]
            terms = block_terms(blocks.transpose(1, 0, 2, 3),
                                condition_max=s.nees_condition_max)
            alone = checks.screen_alone(P, rtol_symmetry=s.rtol_symmetry,
                                        rtol_correlation=s.rtol_correlation,
                                        rtol_psd=s.rtol_psd, atol=s.atol_growth)
            prevs = [prev, *run[:-1]]
            if before is None:  # one state, after the last one checked
                before = predict_points(self._unobservable.robot, prevs, list(run))
            pairs = self._screen_pairs(prev, prevs, run, P, before)
        structure, psd = alone.structure.tolist(), alone.psd.tolist()
        for k, x in enumerate(run):
            self._screens[id(x)] = Screened(
                x, prevs[k], structure[k], psd[k], None if pairs is None else pairs[k],
                terms[k], alone.factors[k] if alone.factors else None, before[k])

    def _screen_pairs(self, prev: SlamState | None, prevs: list[SlamState | None],
                      run: Sequence[SlamState], P: np.ndarray,
                      before: list[np.ndarray | None]
                      ) -> list[tuple[bool, bool, bool] | None] | None:
        """The pair screen of each state of ``run`` against the one before it (None for a
        state whose landmarks differ from its previous one's; None: none screened)."""
        s = self.settings
        K = len(run)
        # the same landmarks in the same order (int64 ids: equal iff their bytes are)
        same = np.array([p is not None and p.landmark_ids.shape == x.landmark_ids.shape
                         and p.landmark_ids.tobytes() == x.landmark_ids.tobytes()
                         for p, x in zip(prevs, run, strict=True)], dtype=bool)
        if not same.any():
            return None
        lead = (prev.covariance[None] if same[0] and prev is not None
                else np.zeros_like(P[:1]))
        P_ext = np.concatenate([lead, P])
        poses = np.stack([np.zeros(3) if p is None else p.pose
                          for p in [prevs[0], *run]])
        for k, xy in enumerate(before):  # FEJ: from the propagated position
            if xy is not None:
                poses[k, :2] = xy
        predict = np.array([s.check_prediction and x.step == "predict"
                            and p is not None and x.seq == p.seq + 1
                            and xy is not None
                            for p, x, xy in zip(prevs, run, before, strict=True)],
                           dtype=bool)
        at = np.flatnonzero(same)
        whole = at.size == K
        pairs = checks.screen_pairs(
            P_ext[:-1] if whole else P_ext[at], P if whole else P[at],
            poses[:-1] if whole else poses[at], poses[1:] if whole else poses[at + 1],
            predict if whole else predict[at], rtol_growth=s.rtol_growth,
            atol_growth=s.atol_growth, rtol_prediction=s.rtol_prediction)
        unchanged, growth, prediction = (pairs.unchanged.tolist(), pairs.growth.tolist(),
                                         pairs.prediction.tolist())
        out: list[tuple[bool, bool, bool] | None] = [None] * K
        for j, k in enumerate(at.tolist()):
            out[k] = (unchanged[j], growth[j], prediction[j])
        return out
