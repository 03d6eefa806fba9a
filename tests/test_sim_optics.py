"""One optics type (issue 50 item 3): TurbulenceParams holds a d2turb.sim.Optics, the PSFs, the geometry banks and the
page build from it, the flat keywords and the recorded metadata stay as they were."""

import dataclasses
import math

import pytest
import torch

from d2turb.errors import D2TurbError
from d2turb.sim import Optics, Simulator, TurbulenceParams, as_optics
from d2turb.sim.geometry import GEOMETRIES, footprint_px
from d2turb.sim.psf import PupilPSF

RGB = (620e-9, 530e-9, 460e-9)
# the keys and order of TurbulenceParams.to_dict before the optics were one type (dataset.json, meta lines)
RECORD_KEYS = [
    "aperture_m",
    "wavelength_m",
    "path_length_m",
    "dr0",
    "cn2",
    "ifov_rad",
    "n_zernike",
    "offset_s",
    "modulation",
    "tilt_geometry",
    "layer_z_frac",
    "psf_grid_px",
    "r0_m",
    "reference_wavelength_m",
]


def test_the_params_hold_one_optics_given_flat_or_whole():
    flat = TurbulenceParams(aperture_m=0.2, wavelength_m=RGB, path_length_m=2000.0, ifov_rad=2e-6, dr0=2.0)
    whole = TurbulenceParams(optics=Optics(0.2, RGB, 2e-6, 2000.0), dr0=2.0)
    assert flat == whole and flat.to_dict() == whole.to_dict()
    o = flat.optics
    assert (o.aperture_m, o.wavelength_m, o.channels_m, o.ifov_rad, o.path_length_m) == (0.2, 530e-9, RGB, 2e-6, 2000.0)
    assert (flat.aperture_m, flat.wavelength_m, flat.path_length_m, flat.ifov_rad) == (0.2, RGB, 2000.0, 2e-6)
    assert flat.wavelengths == RGB and flat.reference_wavelength == 530e-9
    with pytest.raises(D2TurbError, match="not both"):
        TurbulenceParams(aperture_m=0.2, optics=Optics())


def test_optics_without_ifov_or_path_take_the_simulators_defaults():
    p = TurbulenceParams(optics=Optics(aperture_m=0.2))
    assert p == TurbulenceParams(aperture_m=0.2)
    assert p.path_length_m == 1000.0 and p.ifov_rad == 525e-9 / (2 * 0.2) and p.optics.ifov_known


def test_the_record_is_as_before():
    p = TurbulenceParams(wavelength_m=list(RGB), cn2=1e-15)
    d = p.to_dict()
    assert list(d) == RECORD_KEYS
    assert d["wavelength_m"] == list(RGB) and d["reference_wavelength_m"] == 530e-9
    assert d["r0_m"] == pytest.approx(0.1 / d["dr0"], rel=1e-15)
    # an old record (eval/clips.py and make-dataset read the flat keys back) gives the same parameters
    keys = ("aperture_m", "wavelength_m", "path_length_m", "cn2", "ifov_rad", "n_zernike", "offset_s", "modulation")
    again = TurbulenceParams(**{k: d[k] for k in keys})
    assert again == p and again.to_dict() == d
    assert TurbulenceParams().to_dict()["wavelength_m"] == 525e-9  # one wavelength stays a number


def test_setting_a_flat_value_replaces_the_optics():
    p = TurbulenceParams()
    p.ifov_rad *= 4
    assert p.optics.ifov_rad == 4 * 525e-9 / 0.2 and p.lambda_over_d_px == pytest.approx(0.5, rel=1e-12)
    p.wavelength_m = RGB
    assert p.optics.channels_m == RGB and p.optics.wavelength_m == 530e-9
    with pytest.raises(D2TurbError, match="aperture_m"):
        p.aperture_m = -1.0


def test_three_wavelengths_have_the_middle_as_reference():
    o = Optics(wavelength_m=RGB)
    assert o.wavelength_m == o.reference_wavelength == 530e-9 and o.wavelengths == RGB
    assert o.ifov_rad == 530e-9 / (2 * 0.1)  # Nyquist at the reference
    assert dataclasses.replace(o, aperture_m=0.2).channels_m == RGB  # replace keeps the channels
    assert Optics(wavelength_m=[500e-9]).channels_m is None
    with pytest.raises(D2TurbError, match="middle"):
        Optics(wavelength_m=600e-9, channels_m=RGB)
    with pytest.raises(D2TurbError, match="one value or three"):
        Optics(wavelength_m=(500e-9, 600e-9))
    with pytest.raises(D2TurbError, match="not smaller than the aperture"):
        Optics(aperture_m=6e-7, wavelength_m=(620e-9, 500e-9, 460e-9))  # the longest wavelength counts


def test_derived_quantities_have_one_definition():
    o = Optics(aperture_m=0.05, wavelength_m=500e-9, ifov_rad=5e-6, path_length_m=1000.0)
    assert o.lambda_over_d_px == pytest.approx(2.0, rel=1e-12)  # λ/(D·ifov)
    assert o.footprint_px == pytest.approx(10.0, rel=1e-12)  # D/(ifov·L)
    # footprint = qD²/(λL): footprint 10 px at q = 2, L = 1 km, λ = 500 nm is D = 5 cm, ifov = 5 µrad
    back = Optics.from_footprint(10.0, 2.0, 1000.0, 500e-9)
    assert back.aperture_m == pytest.approx(0.05, rel=1e-12) and back.ifov_rad == pytest.approx(5e-6, rel=1e-12)
    with pytest.raises(D2TurbError, match="path length"):
        _ = Optics().footprint_px
    p = TurbulenceParams(optics=o)
    assert footprint_px(p) == o.footprint_px and p.lambda_over_d_px == o.lambda_over_d_px
    for q in GEOMETRIES["blind"].bank()[:4]:
        assert q.optics.footprint_px == pytest.approx(footprint_px(q)) and 1.0 <= q.lambda_over_d_px <= 4.0


def test_the_psfs_are_those_of_the_params_optics():
    p = TurbulenceParams(wavelength_m=RGB, n_zernike=10)
    sim = Simulator(p)
    coeffs = torch.randn(3, 7, generator=torch.Generator().manual_seed(0))
    direct = PupilPSF(p.optics, range(4, 11)).psfs(coeffs, 6)
    assert direct.shape == (3, 3, 13, 13) and torch.equal(sim.pupil.psfs(coeffs, 6), direct)
    assert torch.allclose(direct.sum(dim=(-2, -1)), torch.ones(3, 3), atol=1e-5)


def test_measure_reads_the_params_optics():
    p = TurbulenceParams(wavelength_m=RGB, path_length_m=500.0)
    o = as_optics(p)
    assert o is p.optics and o.wavelength_m == 530e-9 and o.ifov_known and o.path_length_m == 500.0
    assert math.isclose(as_optics({"wavelength_m": list(RGB)}).wavelength_m, 530e-9)


def test_the_page_values_hold_the_optics():
    from d2turb.app import core
    from d2turb.app.jobs import simulate_argv

    v = core.sim_values(core.SimSettings(wavelength_nm="620 530 460", ifov_urad=3.1), None)
    assert v.optics == Optics(0.1, RGB, 3.1e-6, 1000.0) and v.params().optics == v.optics
    nyquist = core.sim_values(core.SimSettings(), None)
    assert not nyquist.optics.ifov_known and "--ifov" not in simulate_argv(nyquist, "x.png")
    assert nyquist.params() == TurbulenceParams(dr0=3.0)
