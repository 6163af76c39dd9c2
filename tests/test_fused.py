"""Caillette et al.'s fused segmentation and reconstruction (CVIU 2007, §6.1): the
chi-square thresholds of Eq. 5 against scipy, the YUV background model's distances,
and the reconstruction of a simulated frame against the true body volume."""
import numpy as np
import pytest
from scipy.stats import chi2

from app.evaluation.reconstruction import score_frame
from app.reconstruction import Reconstructor
from app.reconstruction.fused import chi2_threshold, chi2_thresholds
from app.segmentation import YuvBackground, shrink
from app.simulation.occupancy import true_occupancy
from app.simulation.simulator import Simulator


@pytest.mark.parametrize("alpha", [0.9, 0.95, 0.99, 0.999])
def test_thresholds_are_the_chi_square_quantiles(alpha):
    """T_k(alpha): int_0^T chi2_{3k} = alpha (Eq. 5), for every k a voxel's samples take."""
    ks = np.array([1, 2, 3, 5, 8, 13, 21, 32, 33, 50, 100, 277, 1000])
    ours = np.array([chi2_threshold(alpha, int(k)) for k in ks])
    exact = chi2.ppf(alpha, 3 * ks)
    small = 3 * ks <= 96
    np.testing.assert_allclose(ours[small], exact[small], rtol=1e-9)
    np.testing.assert_allclose(ours[~small], exact[~small], rtol=5e-4)
    table = chi2_thresholds(alpha, 40)
    assert table[0] == 0 and np.all(np.diff(table) > 0)
    np.testing.assert_allclose(table[1:], chi2.ppf(alpha, 3 * np.arange(1, 41)), rtol=5e-4)
    assert chi2.cdf(chi2_threshold(alpha, 1), 3) == pytest.approx(alpha, abs=1e-9)


def test_background_distances_follow_chi_square_3():
    """Pixels of the background with Gaussian noise of some covariance: after
    fit_noise their squared Mahalanobis distances are chi-square(3) (1 % above T_1 at
    alpha = 0.99); a pixel darkened by 10 % (a shadow) stays background, a colour
    change does not."""
    rng = np.random.default_rng(0)
    bg = rng.integers(60, 200, size=(60, 80, 3)).astype(np.uint8)
    model = YuvBackground(bg, min_sigma=0.5)
    frames = [np.clip(bg + rng.normal(0, 3.0, bg.shape), 0, 255).astype(np.uint8) for _ in range(6)]
    model.fit_noise(frames)
    d = model.distance(np.clip(bg + rng.normal(0, 3.0, bg.shape), 0, 255).astype(np.uint8))
    t1 = chi2_threshold(0.99, 1)
    assert np.mean(d) == pytest.approx(3.0, rel=0.25)
    assert 0.002 < np.mean(d > t1) < 0.03
    shadow = (bg.astype(np.float32) * 0.9).astype(np.uint8)
    assert np.median(model.distance(shadow)) < t1
    red = bg.copy()
    red[..., 2] = np.clip(red[..., 2].astype(int) + 60, 0, 255)
    assert np.mean(model.distance(red) > t1) > 0.95


def test_fused_reconstruction_of_a_simulated_frame():
    """walk1 at 4 cm, k = 0: the fused method finds the body about as well as carving
    the simulator's true silhouettes does (what k = 0 loses behind the table is lost
    by both), with a hull under 3x the body's volume; its coarse-to-fine tests lose
    nothing against the per-voxel test on the same pixels."""
    sim = Simulator("walk1", seed=0, seconds=2, width=320, height=240, zenithal=True)
    models = {c: YuvBackground(sim.background(c)) for c in sim.cameras}
    first = [sim.render(i)[0] for i in (0, 5, 10)]
    for c in sim.cameras:
        models[c].fit_noise([f[c] for f in first])
    sizes = {c: (320, 240) for c in sim.cameras}
    rec = Reconstructor(sim.calibration, 0.04, mask_sizes=sizes, method="fused", tolerance=0, colouring="naive")
    flat = Reconstructor(sim.calibration, 0.04, mask_sizes=sizes, method="flat", tolerance=0, colouring="none")
    fused, true, per_voxel = [], [], []
    for i in (20, 35, 48):
        images, labels, _ = sim.render(i)
        dist = {c: models[c].distance(images[c]) for c in sim.cameras}
        idx, colours, _, _ = rec.reconstruct(dist, images)
        assert len(colours) == len(idx) and colours.any()
        truth = true_occupancy(sim.body_record(i), rec.grid.origin, 0.04, rec.grid.dims)
        s = score_frame(i, idx, truth, rec.grid.dims, 0.04)
        fused.append(s.recall)
        assert s.volume_ratio < 3.0, s
        per_voxel.append(score_frame(i, flat.carve({c: d > rec.thresholds[1] for c, d in dist.items()}), truth,
                                     rec.grid.dims, 0.04).recall)
        true.append(score_frame(i, flat.carve({c: labels[c] >= 0 for c in sim.cameras}), truth,
                                rec.grid.dims, 0.04).recall)
    assert np.mean(fused) > np.mean(true) - 0.1, (fused, true)
    assert np.mean(fused) > 0.75 and np.mean(fused) >= np.mean(per_voxel) - 0.01, (fused, per_voxel)
