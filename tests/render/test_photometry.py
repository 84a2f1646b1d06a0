"""Photometry: a Lambertian plane under uniform illuminance, through the whole render path to the frames folder.

Expected values are computed here, independently of the renderer:
* E channel [lux] = rho * E * T * cos^4(theta) / (4 N^2)    (camera equation on a Lambertian surface)
* Phi channel [e-/(s m^2)] = E channel * (e-/s/m^2 per lux of the emitter spectrum for the profile QE),
  the ratio integral(S QE l/(hc)) / (683 integral(S V)) evaluated with numpy on a 0.5 nm grid.
"""

import numpy as np
import pytest
from scipy import stats

from tests.render.conftest import needs_mitsuba

pytestmark = [pytest.mark.render, needs_mitsuba]

RHO, LUX, T, N, F_MM, PITCH = 0.5, 100.0, 0.9, 2.0, 8.0, 20e-6


def planck(wl_nm, temp_k):
    lam = wl_nm * 1e-9
    h, c, k = 6.62607015e-34, 299792458.0, 1.380649e-23
    return 1.0 / (lam ** 5 * np.expm1(h * c / (lam * k * temp_k)))


def expected_e_per_lux(qe, step_nm=None):
    """e-/(s m^2) per lux of a 5000 K black body for QE curve ``qe`` (independent numpy integral).

    ``step_nm``: sample the emitter spectrum and the QE-weighted response on this grid and interpolate
    linearly, as a tabulated renderer does; None integrates the exact functions on a 0.5 nm grid.
    """
    from sensor.spectral import photopic_v  # the CIE 1924 standard table (data, not renderer code)
    wl = np.arange(300.0, 1100.0, 0.5)
    s = planck(wl, 5000.0)
    hc = 6.62607015e-34 * 299792458.0
    v = photopic_v(wl)
    if step_nm:
        grid = np.arange(300.0, 1100.0 + step_nm, step_nm)
        s = np.interp(wl, grid, planck(grid, 5000.0))
        qe_w = np.interp(wl, grid, qe(grid) * grid)
        return np.sum(s * qe_w * 1e-9 / hc) / (683.002 * np.sum(s * v))
    num = np.sum(s * qe(wl) * wl * 1e-9 / hc)
    den = 683.002 * np.sum(s * v)
    return num / den


@pytest.mark.parametrize("launch", [pytest.param("film", marks=pytest.mark.slow), "frozen"])
def test_lambertian_plane_E_and_Phi(tmp_path, write_scene, z, launch):
    from render2spike.render.job import render_scene
    from render2spike.render.scene import load_scene
    from sensor.io.frames import read_frames

    # whole keyframes: the three frames of this still scene are three independent renders (with static-region
    # reuse they would be one static frame, three times)
    sc = load_scene(write_scene(), ["render.spp=64", "render.static_reuse=false"])
    res = render_scene(sc, tmp_path / "frames", progress=False, log=lambda *a: None, launch=launch)
    seq = read_frames(res.out)
    assert len(seq) == 3  # static scene: the 200 Hz base grid over 10 ms, no refinement
    frames = [seq.read(i) for i in range(len(seq))]
    for fr in frames:  # the frame contract's header
        for key in ("spp", "render_noise_ratio", "variant", "launch", "scene_hash", "target_lux", "made_by", "units"):
            assert key in fr.header, key
        assert fr.header["target_lux"] == LUX and fr.phi.dtype == np.float32 and fr.header["launch"] == launch
    H, W = frames[0].phi.shape
    x = (np.arange(W) + 0.5 - W / 2) * PITCH
    y = (np.arange(H) + 0.5 - H / 2) * PITCH
    f = F_MM * 1e-3
    cos4 = (f / np.sqrt(f ** 2 + x[None, :] ** 2 + y[:, None] ** 2)) ** 4
    e_expected = RHO * LUX * T * cos4 / (4 * N ** 2)
    phi_expected = e_expected * expected_e_per_lux(sc.profile.qe)

    # tabulation error of the renderer's 5 nm spectra (emitter and Phi response), computed, not assumed
    qe = sc.profile.qe
    tab_err = abs(expected_e_per_lux(qe, step_nm=5.0) / expected_e_per_lux(qe) - 1.0)
    z_px = float(stats.norm.isf(1e-3 / (2 * H * W)))  # Bonferroni over the pixels, family-wise 1e-3
    for chan, expect in (("illuminance_lux", e_expected), ("phi", phi_expected)):
        tab = tab_err if chan == "phi" else 0.0  # E: the lux normalisation uses the same V table as the film
        stack = np.stack([getattr(fr, chan).astype(np.float64) for fr in frames])  # 3 independent renders
        ratio = stack / expect
        # per-pixel MC variance from the spread of the K = 3 frames; pixels are independent, so the
        # standard error of the image mean of the K-frame average is sqrt(mean(var_px) / (K * n_px)).
        K, n_px = stack.shape[0], H * W
        se = np.sqrt(ratio.var(axis=0, ddof=1).mean() / (K * n_px))
        tol = z * se + tab
        assert abs(ratio.mean() - 1.0) < tol, (chan, ratio.mean(), tol)
        # per-pixel: the cos^4 falloff is reproduced (every pixel within a Bonferroni z of its MC noise)
        px_sd = np.sqrt(ratio.var(axis=0, ddof=1).mean() / K)
        assert np.abs(ratio.mean(axis=0) - 1.0).max() < z_px * px_sd + tab, chan


def test_light_level_scales_linearly(tmp_path, write_scene):
    """Halving illuminance_lux halves both channels exactly (the emitters are scaled, the noise is the same)."""
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    p = write_scene()
    a = SceneRenderer(load_scene(p)).render_frame(0.0, 0, 8)
    b = SceneRenderer(load_scene(p, lux=50.0)).render_frame(0.0, 0, 8)
    assert np.allclose(b["phi"], 0.5 * a["phi"], rtol=1e-5)
    assert np.allclose(b["lux"], 0.5 * a["lux"], rtol=1e-5)


def test_reference_measured_by_meter_for_environment_light(write_scene):
    """A constant environment of radiance L gives E = pi L on an unoccluded surface: the meter must find it."""
    from render2spike.render.photometry import v_integral
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene, spectrum_curve
    p = write_scene({"lights": [{"name": "sky", "type": "environment", "strength": 0.3,
                                 "spectrum": {"blackbody_k": 6500}}],
                     "reference": {"point": [0, 0, 0.5], "normal": [0, 0, 1]}})
    r = SceneRenderer(load_scene(p))
    cal = r.calibration
    expect = np.pi * v_integral(spectrum_curve({"blackbody_k": 6500}), 0.3)
    # meter MC error: the two halves' difference gives the standard error; 3.9 sigma + 0.2 % spectral tabulation
    assert abs(cal["raw_e_meter"] - expect) < 3.9 * max(cal["raw_e_meter_stderr"], 1e-6 * expect) + 2e-3 * expect
    assert cal["raw_e_direct_delta"] == 0.0


def test_occluded_reference_is_an_error(write_scene):
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    from sensor.errors import InputError
    p = write_scene({"reference": {"point": [0, 0, 0], "normal": [0, 0, -1]}})  # facing away from the sun
    with pytest.raises(InputError, match="no light reaches the reference"):
        SceneRenderer(load_scene(p))


XML = """<scene version="3.0.0">
  <shape type="rectangle" id="floor"><transform name="to_world"><scale value="5"/></transform>
    <bsdf type="diffuse"><float name="reflectance" value="0.5"/></bsdf></shape>
  <emitter type="constant"><spectrum name="radiance" value="400:1, 800:1"/></emitter>
  <sensor type="perspective"><film type="hdrfilm"/></sensor>
</scene>
"""


def test_xml_scene_light_level(tmp_path, write_scene):
    """A plane lit by a uniform sky from a Mitsuba XML file: E_img = rho E T / (4 N^2) with E from the meter."""
    from render2spike.render.renderer import SceneRenderer
    from render2spike.render.scene import load_scene
    (tmp_path / "room.xml").write_text(XML)
    p = write_scene({"xml": "room.xml", "lights": [], "objects": [],
                     "reference": {"point": [0, 0, 0], "normal": [0, 0, 1]}})
    r = SceneRenderer(load_scene(p))
    f = r.render_frame(0.0, 0, 32)
    # the 5 m plane seen from 1 m fills the view; each pixel sees rho E / pi with E = 100 lux from the whole sky
    # (the 10 m plane blocks the lower hemisphere for both the meter and the plane)
    ratio = f["lux"] / (RHO * LUX * T * r.cos4 / (4 * N ** 2))
    se = np.sqrt(f["phi_var"].mean() / f["phi"].mean() ** 2 / f["phi"].size)
    meter_rel = r.calibration["raw_e_meter_stderr"] / r.calibration["raw_e_meter"]
    assert abs(ratio.mean() - 1) < 3.9 * np.hypot(se, meter_rel) + 2e-3, ratio.mean()
