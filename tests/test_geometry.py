"""Imaging-geometry distributions for training and test data (d2turb.sim.geometry)."""

import math

import numpy as np
import pytest

from d2turb.errors import D2TurbError
from d2turb.sim.geometry import GEOMETRIES, GeometryDistribution, footprint_px, geometry_bank


def test_bank_is_a_latin_hypercube_inside_the_ranges():
    dist = GeometryDistribution(size=12)
    bank = dist.bank()
    assert len(bank) == 12
    lo, hi = dist.range_m
    u_range = [(math.log(p.path_length_m) - math.log(lo)) / (math.log(hi) - math.log(lo)) for p in bank]
    flo, fhi = dist.footprint_px
    u_foot = [(math.log(footprint_px(p)) - math.log(flo)) / (math.log(fhi) - math.log(flo)) for p in bank]
    u_s = [(p.offset_s - dist.offset_s[0]) / (dist.offset_s[1] - dist.offset_s[0]) for p in bank]
    for u in (u_range, u_foot, u_s):  # one geometry in each of the 12 strata of every parameter
        assert sorted(int(v * 12) for v in u) == list(range(12))
    for p in bank:  # q = λ/(D·ifov) pixels per λ/D stays at the distribution's value (Nyquist)
        assert p.wavelength_m / (p.aperture_m * p.ifov_rad) == pytest.approx(2.0, rel=1e-12)
    assert [p.path_length_m for p in dist.bank()] == [p.path_length_m for p in bank]  # fixed seed


def test_footprint_is_the_inverse_of_the_tilt_separation_scale():
    # Tilt correlation depends on s = r·ifov·L·t / (D(1 − t)) (docs/physics.md): at mid-path (t = 1/2) s = 1
    # exactly when the pixel separation r equals the footprint D / (ifov·L).
    from d2turb.sim import Simulator

    for p in geometry_bank("field")[:3]:
        layers = Simulator(p).tilt_layers()
        t, _ = np.polynomial.legendre.leggauss(48)
        t = 0.5 * (t + 1)
        alpha = np.array([a for a, _ in layers])
        expected = t / (1 - t) / footprint_px(p)
        np.testing.assert_allclose(alpha, expected, rtol=1e-10)


def test_fixed_geometry_takes_overrides_and_field_refuses_geometry_overrides():
    (p,) = geometry_bank("fixed", {"path_length_m": 2000.0})
    assert p.path_length_m == 2000.0
    assert len(geometry_bank("field", {"n_zernike": 15})) == GEOMETRIES["field"].size
    with pytest.raises(D2TurbError, match="path_length_m"):
        geometry_bank("field", {"path_length_m": 2000.0})
    with pytest.raises(D2TurbError, match="unknown geometry"):
        geometry_bank("nope")
    with pytest.raises(D2TurbError, match="increasing pair"):
        GeometryDistribution(range_m=(5.0, 1.0))


def test_make_dataset_draws_one_geometry_per_chunk(tmp_path):
    import json

    from PIL import Image
    from skimage import data

    from d2turb.data.generate import DatasetConfig, generate_dataset

    Image.fromarray(data.astronaut()[::8, ::8]).save(tmp_path / "a.png")  # 64x64
    out = tmp_path / "ds"
    cfg = DatasetConfig(clean=[str(tmp_path / "a.png")], out=str(out), pairs=6, patch=32, batch=2, device="cpu")
    cfg.geometry = "field"
    generate_dataset(cfg, progress=False)
    record = json.loads((out / "dataset.json").read_text())
    assert record["geometry"] == "field" and len(record["params"]) == GEOMETRIES["field"].size
    metas = [json.loads(line) for line in (out / "meta.jsonl").read_text().splitlines()]
    lo, hi = GEOMETRIES["field"].footprint_px
    for m in metas:
        assert m["params"] == record["params"][m["geometry"]]
        assert lo <= m["params"]["footprint_px"] <= hi
    by_chunk = {}
    for m in metas:
        by_chunk.setdefault(m["chunk"], set()).add(m["geometry"])
    assert all(len(g) == 1 for g in by_chunk.values())
