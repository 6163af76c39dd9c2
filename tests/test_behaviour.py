"""Caillette, Galata and Howard's tracker (CVIU 2007): the Figueiredo-Jain clusters (§4.1),
the VLMM and its model entropy (§4.2, Eq. 2), the closed-form relative entropy of Gaussian
blobs (§6.4, Eqs. 8-10)."""
import numpy as np
import pytest

from app.behaviour.clusters import GaussianClusters, fit_clusters
from app.behaviour.kl import gaussian_kl, matched_kl, mixture_kl
from app.behaviour.vlmm import Vlmm, learn_vlmm


def test_the_em_recovers_the_clusters_of_a_gaussian_mixture_and_their_number():
    """Four 2-d Gaussians (weights 0.21, 0.36, 0.14, 0.29; one tilted): started from 12
    components, Figueiredo and Jain's EM keeps four, each within 0.15 of a true mean and
    0.03 of its weight, and labels 97% of the points by the component that drew them."""
    rng = np.random.default_rng(1)
    means = np.array([[0, 0], [5, 0], [0, 6], [6, 6]], float)
    covs = [np.diag([1, .3]), np.array([[1, .6], [.6, 1]]), np.eye(2) * .5, np.diag([.2, 2])]
    sizes = (300, 500, 200, 400)
    X = np.concatenate([rng.multivariate_normal(m, c, n) for m, c, n in zip(means, covs, sizes)])
    truth = np.repeat(np.arange(4), sizes)
    g = fit_clusters(X, k_max=12, rng=np.random.default_rng(0))
    assert g.k == 4
    order = [int(np.argmin(np.linalg.norm(g.means - m, axis=1))) for m in means]
    assert sorted(order) == [0, 1, 2, 3]
    assert np.allclose(g.means[order], means, atol=0.15)
    assert np.allclose(g.weights[order], np.array(sizes) / sum(sizes), atol=0.03)
    assert np.allclose(g.covs[order[1]], covs[1], atol=0.2)
    labels = np.array(order).argsort()[g.label(X)]
    assert np.mean(labels == truth) >= 0.97
    back = GaussianClusters.from_dict(g.to_dict())
    assert np.array_equal(back.label(X), g.label(X))


def test_the_vlmm_learns_a_variable_order_sequence_and_its_entropy_is_the_hand_computed_one():
    """``a b a c`` repeated: after ``b`` and ``c`` comes ``a`` (order 1), after ``a`` it takes
    the label before it to know (``b a`` -> ``c``, ``c a`` -> ``b``: order 2). The model has
    exactly those contexts, and over the training sequence (n labels) its entropy is, by
    hand: the first label from the root (P(a) = 1/2), the second from ``a`` (1/2 each way),
    every other one certain, each smoothed by g_min over K = 3 labels:
    H = -(2 log2((1 - 3 g)/2 + g) + (n - 2) log2(1 - 2 g)) / n."""
    a, b, c = 0, 1, 2
    seq = [a, b, a, c] * 50
    g = 1e-3
    model = learn_vlmm([seq], labels=3, memory=4, epsilon=1e-3, g_min=g)
    assert set(model.contexts) == {(), (a,), (b,), (c,), (b, a), (c, a)}
    assert model.state_of([a, c, a, b, a]) == (b, a) and model.gamma((b, a), c) == pytest.approx(1 - 2 * g)
    assert model.next_state((b, a), c) == (c,)
    n = len(seq)
    hand = -(2 * np.log2((1 - 3 * g) / 2 + g) + (n - 2) * np.log2(1 - 2 * g)) / n
    assert model.entropy([seq]) == pytest.approx(hand, rel=1e-9)
    first_order = learn_vlmm([seq], labels=3, memory=1, epsilon=1e-3, g_min=g)
    assert model.entropy([seq]) < first_order.entropy([seq]) - 0.4     # the memory is worth half a bit a label
    back = Vlmm.from_dict(model.to_dict())
    assert back.entropy([seq]) == pytest.approx(model.entropy([seq]), rel=1e-7)
    with pytest.raises(ValueError):
        Vlmm.from_dict({**model.to_dict(), "contexts": [e for e in model.to_dict()["contexts"] if e["context"] != [a]]})


def test_the_closed_form_relative_entropy_matches_a_monte_carlo_estimate():
    """6-d blobs (position and colour): Eq. 10 as it should read (D_KL(f||g) = E_f[ln f/g])
    against 400 000 samples of f, within 1%; the printed form (f and g swapped) is the
    other divergence. Eq. 8 of two well separated mixtures against Monte Carlo, within 3%;
    Eq. 9 with the right correspondence equals Eq. 8."""
    rng = np.random.default_rng(4)

    def spd(scale):
        A = rng.normal(0, 1, (6, 6))
        return A @ A.T * scale + np.eye(6) * 0.1

    mf, mg = rng.normal(0, 1, 6), rng.normal(0, 1, 6)
    Sf, Sg = spd(0.3), spd(0.5)

    def logpdf(x, m, S):
        L = np.linalg.cholesky(S)
        z = np.linalg.solve(L, (x - m).T)
        return -0.5 * np.sum(z * z, axis=0) - np.sum(np.log(np.diag(L))) - 3 * np.log(2 * np.pi)

    x = rng.multivariate_normal(mf, Sf, 400_000)
    mc = float(np.mean(logpdf(x, mf, Sf) - logpdf(x, mg, Sg)))
    assert gaussian_kl(mf, Sf, mg, Sg) == pytest.approx(mc, rel=0.01)
    assert abs(gaussian_kl(mg, Sg, mf, Sf) - mc) > 0.05 * mc           # not symmetric: the printed Eq. 10 is this one

    wf, wg = np.array([0.3, 0.7]), np.array([0.4, 0.6])
    mfs = np.stack([mf, mf + 30]); mgs = np.stack([mg, mg + 30])
    Sfs, Sgs = np.stack([Sf, Sf * 0.5]), np.stack([Sg, Sg * 0.8])
    comp = rng.random(200_000) < wf[0]
    xs = np.where(comp[:, None], rng.multivariate_normal(mfs[0], Sfs[0], len(comp)),
                  rng.multivariate_normal(mfs[1], Sfs[1], len(comp)))
    F = np.logaddexp(np.log(wf[0]) + logpdf(xs, mfs[0], Sfs[0]), np.log(wf[1]) + logpdf(xs, mfs[1], Sfs[1]))
    G = np.logaddexp(np.log(wg[0]) + logpdf(xs, mgs[0], Sgs[0]), np.log(wg[1]) + logpdf(xs, mgs[1], Sgs[1]))
    mc_mix = float(np.mean(F - G))
    eq8 = mixture_kl(wf, mfs, Sfs, wg, mgs, Sgs)
    assert eq8 == pytest.approx(mc_mix, rel=0.03)
    assert matched_kl(wf, mfs, Sfs, wg, mgs, Sgs) == pytest.approx(eq8, rel=1e-9)
