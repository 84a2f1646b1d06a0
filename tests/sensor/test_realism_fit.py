"""Fitting the profile's dark rate and threshold to a recording: recovery on a synthetic camera, and the CLI."""

import numpy as np
import pytest

import sensor
from sensor.analysis.realism import fit_profile, scaled_profile

TRUE_THETA, TRUE_DARK = 200.0, 0.01  # [e-], [dark events per interval]


def _recording(seed, T=400, n=40):
    """A 40 x 40 camera with known theta and dark rate; 8 light levels (columns of 5) from 8 to 120 e-/interval."""
    prof = sensor.SensorProfile.synthetic(n, n, threshold_e=TRUE_THETA, dark_rate=TRUE_DARK, seed=seed)
    lam = np.repeat(np.geomspace(8.0, 120.0, 8), n // 8).astype(np.float32)
    rec = sensor.simulate(np.broadcast_to(lam[None, None, :], (T, n, n)), prof, "elssim", seed=100 + seed)
    return rec, prof


@pytest.mark.slow
def test_fit_recovers_dark_rate_and_threshold(z):
    # start from a profile that is wrong by x1/1.6 in dark rate and x1/0.8 in threshold: the truth is at scales
    # (1.6, 0.8), between grid points (a coarser grid than the default, for speed). The n = 8 pixel draws are
    # disjoint with their own simulation seeds, so the fit's mean has standard error sd / sqrt(n); with sd
    # itself estimated from n draws the bound is Student's t (n - 1 dof) at the two-sided level of z
    from scipy.stats import norm
    from scipy.stats import t as student_t
    rec, prof = _recording(1)
    start = scaled_profile(prof, 1 / 1.6, 1 / 0.8)
    n = 8
    f = fit_profile(rec, start, seed=0, n_seeds=n, n_pixels=190, dark_scales=(0, 0.5, 1, 1.5, 2, 3, 4),
                    threshold_scales=(0.25, 0.35, 0.5, 0.7, 1, 1.4, 2, 2.8, 4))
    assert f.notes["disjoint_draws"] and len(f.per_seed) == n
    assert f.dark_scale_sd > 0 and f.threshold_scale_sd > 0, f.per_seed
    q = student_t.isf(norm.sf(z), n - 1)
    tol_dark = q * f.dark_scale_sd / np.sqrt(n)
    assert abs(f.dark_scale - 1.6) <= tol_dark, (f.dark_scale, tol_dark)
    assert abs(1.0 - 1.6) > tol_dark  # the data do pin the dark rate: the starting value is rejected
    # the threshold is weakly identified (its spread is large); the same bound, on the log scale
    assert abs(np.log(f.threshold_scale / 0.8)) <= q * (f.threshold_scale_sd / f.threshold_scale) / np.sqrt(n), \
        (f.threshold_scale, f.threshold_scale_sd)
    # the fitted profile carries the scales; the fit lowers the distance on its statistics
    assert f.profile.threshold_e == np.float64(start.threshold_e) * f.threshold_scale
    np.testing.assert_allclose(f.profile.dark_rate, start.dark_rate * f.dark_scale, rtol=1e-6)
    for p in f.per_seed:
        assert p["D_fit_statistics_at_grid_min"] < p["D_fit_statistics_at_start"]


def test_realism_cli_fit_writes_a_fitted_profile(tmp_path, capsys):
    import csv
    import json

    from render2spike.cli import main
    rec, prof = _recording(2, T=200, n=24)
    prof.save(tmp_path / "prof.npz")
    np.savez(tmp_path / "rec.npz", spk=rec.astype(np.uint8))  # Spike-Zoo layout
    out = tmp_path / "rep"
    args = ["realism", str(tmp_path / "rec.npz"), "--out", str(out), "--profile", str(tmp_path / "prof.npz"),
            "--models", "elssim:interval,isi", "--fit", "--fit-seeds", "2", "--fit-pixels", "150", "--quiet"]
    assert main(args) == 0
    assert {p.name for p in out.iterdir()} == {"realism.csv", "realism.png", "realism.json", "realism.md",
                                               "fitted_profile.npz"}
    fitted = sensor.SensorProfile.load(out / "fitted_profile.npz")
    summary = json.loads((out / "realism.json").read_text())
    fit = summary["fit"]
    assert fitted.threshold_e == np.float64(prof.threshold_e) * fit["threshold_scale"]
    assert fitted.provenance["fitted"]["dark_scale"] == fit["dark_scale"]
    assert set(summary["distances"]) == {"elssim:interval", "isi", "elssim:interval (fitted)"}
    assert fit["before_D"]["elssim:interval"] == summary["distances"]["elssim:interval"]["D"]
    assert "elssim:interval (fitted)" in {r["source"] for r in csv.DictReader(open(out / "realism.csv"))}
    assert "**Fit.**" in (out / "realism.md").read_text()
    capsys.readouterr()
    assert main(args[:-5] + ["--fit-seeds", "1", "--overwrite"]) == 2
    assert "--fit-seeds" in capsys.readouterr().err


def test_fit_grid_grows_until_its_minimum_is_interior():
    """A minimum beyond the threshold grid's top (x20) or the dark grid's top (x6) is found, not clipped."""
    import numpy as np

    from sensor.analysis.fit import DARK_SCALES, THRESHOLD_SCALES, grow_grid

    def bowl(d, t):  # smallest at dark x6, threshold x20
        return (np.log(t / 20.0)) ** 2 + (d - 6.0) ** 2
    grid = np.array([[bowl(d, t) for t in THRESHOLD_SCALES] for d in DARK_SCALES])
    g, dsc, tsc = grow_grid(grid, DARK_SCALES, THRESHOLD_SCALES, bowl)
    i, j = np.unravel_index(int(np.argmin(g)), g.shape)
    assert 0 < j < len(tsc) - 1 and 0 < i < len(dsc) - 1
    assert abs(np.log(tsc[j] / 20.0)) <= np.log(2) / 4 + 1e-12 and abs(dsc[i] - 6.0) < 6.0 * 0.25
    assert g.shape == (len(dsc), len(tsc)) and g[i, j] == bowl(dsc[i], tsc[j])
    # a minimum beyond the limits stops there (the edge is reported by the fit's notes)
    g, dsc, tsc = grow_grid(grid, DARK_SCALES, THRESHOLD_SCALES, lambda d, t: -t)
    assert abs(tsc[-1] / 64.0 - 1) < 1e-9 and np.argmin(g) % g.shape[1] == len(tsc) - 1
    # the lower threshold edge grows too
    g, dsc, tsc = grow_grid(grid * 0 + np.log(np.array(THRESHOLD_SCALES))[None, :], DARK_SCALES, THRESHOLD_SCALES,
                            lambda d, t: np.log(t))
    assert abs(tsc[0] * 64.0 - 1) < 1e-9
