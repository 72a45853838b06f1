"""Coefficient search and the acceptance rule."""

import numpy as np
import pytest
from scipy import stats

from torchsoil.diagnosis.catalogue import CATALOGUE
from torchsoil.diagnosis.fit import CandidateFit, accept, folds, refine


def test_refine_finds_the_vertex_of_a_parabola():
    ks = [-1.0, 0.0, 0.5, 2.0]
    cost = [(k - 0.7) ** 2 + 3 for k in ks]
    assert abs(refine(ks, cost, (-5, 5)) - 0.7) < 0.35
    ks3 = [0.0, 0.5, 1.0]
    assert abs(refine(ks3, [(k - 0.7) ** 2 for k in ks3], (-5, 5)) - 0.7) < 1e-9


def test_refine_steps_beyond_an_edge_minimum_within_bounds():
    assert refine([0.0, 1.0, 2.0], [3.0, 2.0, 1.0], (-5, 5)) == 3.0
    assert refine([0.0, 1.0, 2.0], [3.0, 2.0, 1.0], (-5, 2.5)) is None


def test_folds_alternate_blocks():
    assert folds(10, 3).tolist() == [0, 0, 0, 1, 1, 1, 0, 0, 0, 1]


def fit_with(z, k_fold):
    n = np.zeros(3)
    return CandidateFit(CATALOGUE["slip_sinkage"], 1.0, k_fold, n, n, 0.0, 1.0, z, {})


def test_accept_needs_significance_and_agreeing_folds():
    assert accept(fit_with(3.0, (2.0, 4.0)), 2.1)
    assert not accept(fit_with(1.5, (2.0, 4.0)), 2.1)        # within the noise
    assert not accept(fit_with(3.0, (0.0, 4.0)), 2.1)        # one fold preferred the base model
    assert not accept(fit_with(3.0, (-2.0, 4.0)), 2.1)       # folds disagree on the sign


def test_fallback_levels_spend_alpha_once_and_carry_after_acceptance():
    from types import SimpleNamespace

    from torchsoil.diagnosis.run import accept_in_order, thresholds

    levels = thresholds([1e-5, 1e-3, 0.01, 0.2], 0.05, 0.6)
    assert sum(levels) == pytest.approx(0.05) and levels[0] == pytest.approx(0.03)
    assert thresholds([0.3], 0.05, 0.6) == [0.05]
    tied = thresholds([1e-30, 1e-30, 0.01], 0.05, 0.6)       # two shape terms, same profile evidence
    assert tied == pytest.approx([0.015, 0.015, 0.02])

    def fit(z):
        return SimpleNamespace(z=z, k_fold=(-0.3, -0.3), accepted=None)

    # the leading candidate needs less than a Bonferroni split would ask (z 1.88 vs 2.24) ...
    fits = [fit(2.0), fit(2.4), fit(0.0)]
    p = [1e-4, 1e-3, 1e-2]
    used = accept_in_order(fits, p, 0.05, 0.6)
    assert [f.accepted for f in fits] == [True, True, False]
    assert used[0] == pytest.approx(stats.norm.isf(0.03))
    # ... a later one more, unless the ones before it were accepted and passed their level on
    assert used[1] == pytest.approx(stats.norm.isf(0.03 + 0.01))
    fits = [fit(1.0), fit(2.3), fit(0.0)]
    used = accept_in_order(fits, p, 0.05, 0.6)
    assert [f.accepted for f in fits] == [False, False, False]
    assert used[1] == pytest.approx(stats.norm.isf(0.01))
