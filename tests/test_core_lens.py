"""Lens model: loading, validation, PCHIP round trips, thin lens."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.interpolate import PchipInterpolator

from dffd.core.lens import Lens, LensError
from dffd.core.synthetic import synthetic_lens
from dffd.resources import lens_table

SIM_LENS = lens_table("sim-evi-d100")
RESPONSE = {
    "measure": "peak_gradient",
    "half_width_rel": 2.9e-3,
    "true_h": [-1.0, 0.0, 1.0],
    "fitted_h": [-0.9, 0.0, 0.9],
}


def test_loads_the_simulator_lens_file() -> None:
    lens = Lens.from_toml(SIM_LENS)
    assert lens.focal_length_mm == pytest.approx(31.0)
    assert lens.counts_range[0] == 4096
    z = 5.0
    c = lens.counts_for_depth(z)
    assert lens.depth_from_v(lens.v_from_counts(c)) == pytest.approx(z, rel=0.01)


def test_round_trips_and_thin_lens() -> None:
    lens = synthetic_lens()
    for counts in (4096, 5000, 12345, 30000, 33792):
        assert lens.counts_from_v(lens.v_from_counts(counts)) == counts
    for z in (1.5, 2.0, 5.0, 10.0):
        v = lens.v_from_depth(z)
        assert lens.depth_from_v(v) == pytest.approx(z, rel=1e-12)
        # dz/dv against a finite difference
        h = 1e-6
        fd = (lens.depth_from_v(v + h) - lens.depth_from_v(v - h)) / (2 * h)
        assert lens.dz_dv(v) == pytest.approx(fd, rel=1e-5)
    assert Lens.from_meta(lens.to_meta()).focus_v_mm == lens.focus_v_mm
    assert lens.table_sigma_v_mm == 0.0  # a table of unknown error
    stated = Lens.from_meta(lens.to_meta() | {"table_sigma_v_mm": 3e-4})
    assert Lens.from_meta(stated.to_meta()).table_sigma_v_mm == 3e-4
    # a lens file with the one number only (written before the per-depth rows): that number
    # at every v
    assert stated.table_sigma_v_mm_at(lens.v_from_depth(3.0)) == 3e-4


def test_the_table_sigma_per_depth_is_interpolated_and_held_beyond() -> None:
    """Rows of (counts, σ of v) at calibrated depths: interpolated in v between them, the end
    rows' σ beyond them, the one number not used; they round-trip through meta and TOML."""
    lens = Lens.from_toml(lens_table("sim-evi-d100"))
    c2, c5 = round(lens.counts_for_depth(2.0)), round(lens.counts_for_depth(5.0))
    rows = ((min(c2, c5), 1e-4), (max(c2, c5), 3e-4))
    stated = Lens.from_meta(lens.to_meta() | {"table_sigma_v_mm": 9e-4, "table_sigma_v_at": rows})
    v2, v5 = stated.v_from_counts(c2), stated.v_from_counts(c5)
    s2, s5 = stated.table_sigma_v_mm_at(v2), stated.table_sigma_v_mm_at(v5)
    assert {round(s2, 10), round(s5, 10)} == {1e-4, 3e-4}
    mid = stated.table_sigma_v_mm_at(0.5 * (v2 + v5))
    assert mid == pytest.approx(2e-4)
    assert stated.table_sigma_v_mm_at(stated.v_from_depth(1.2)) == pytest.approx(s2)
    assert stated.table_sigma_v_mm_at(stated.v_from_depth(20.0)) == pytest.approx(s5)
    again = Lens.from_meta(stated.to_meta())
    assert again.table_sigma_v_at == stated.table_sigma_v_at


def test_the_vertex_response_round_trips_and_old_files_have_none(tmp_path: Path) -> None:
    """A lens file without ``vertex_response`` (every one before docs/estimation.md §21) loads
    without one: no correction, as before; one written by ``dffd calibrate`` reads back."""
    from dffd.calibrate_lensfile import lens_toml

    assert Lens.from_toml(SIM_LENS).vertex_response is None
    lens = Lens.from_meta(synthetic_lens().to_meta() | {"vertex_response": RESPONSE})
    response = lens.vertex_response
    assert response is not None
    again = Lens.from_meta(lens.to_meta()).vertex_response
    assert again is not None
    assert again.to_meta() == response.to_meta()
    path = tmp_path / "lens.toml"
    path.write_text(lens_toml(lens, None, 2, ["a note"]), "utf-8")
    again = Lens.from_toml(path).vertex_response
    assert again is not None
    assert again.to_meta() == response.to_meta()
    assert again.correct(0.45) == response.correct(0.45)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"focal_length_mm": None}, "focal_length_mm"),
        ({"pixel_pitch_mm": -1.0}, "pixel_pitch_mm"),
        ({"focus_table": [[4096, 31.1]]}, "focus_table"),
        ({"focus_table": [[4096, 31.1], [4000, 31.2]]}, "counts"),
        ({"focus_table": [[4096, 31.1], [5000, 31.3], [6000, 31.2]]}, "monotone"),
        ({"focus_table": [[4096, 30.0], [5000, 31.3]]}, "focal_length_mm"),
        ({"focus_table": "nope"}, "focus_table"),
        ({"focus_table": [[4096, 31.1], [float("nan"), 31.3]]}, r"focus_table\[1\] counts"),
        ({"focus_table": [[4096, 31.1], [4500.5, 31.3]]}, r"focus_table\[1\] counts"),
        ({"zoom_counts": "tele"}, "zoom_counts"),
        ({"table_sigma_v_mm": -1e-4}, "table_sigma_v_mm"),
        ({"vertex_response": [0.1]}, "vertex_response must be a table"),
        ({"vertex_response": RESPONSE | {"fitted_h": [-0.9, 0.1, 0.0]}}, "strictly increasing"),
        ({"vertex_response": RESPONSE | {"true_h": [-1.0, 0.0]}}, "same length"),
        ({"vertex_response": RESPONSE | {"half_width_rel": 0.0}}, "half_width_rel"),
        ({"table_sigma_v_at": [[5000, -1e-4]]}, "table_sigma_v_at"),
        ({"table_sigma_v_at": [[5000]]}, r"table_sigma_v_at\[0\]"),
        ({"table_sigma_v_at": [[99999, 1e-4]]}, "table_sigma_v_at"),
    ],
)
def test_validation_names_the_field(change: dict[str, object], field: str) -> None:
    meta = synthetic_lens().to_meta()
    meta.update(change)
    with pytest.raises(LensError, match=field):
        Lens.from_meta(meta)


def test_lens_block_that_is_not_a_table_is_an_error() -> None:
    with pytest.raises(LensError, match="expected a table"):
        Lens.from_meta([1, 2])  # type: ignore[arg-type]


def test_missing_file_and_bad_toml(tmp_path: Path) -> None:
    with pytest.raises(LensError, match="cannot read"):
        Lens.from_toml(tmp_path / "absent.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[lens\n")
    with pytest.raises(LensError, match="not valid TOML"):
        Lens.from_toml(bad)
    bad.write_bytes(b"\xff\xfe[lens]\n")
    with pytest.raises(LensError, match="not valid TOML"):
        Lens.from_toml(bad)
    empty = tmp_path / "empty.toml"
    empty.write_text("x = 1\n")
    with pytest.raises(LensError, match=r"\[lens\]"):
        Lens.from_toml(empty)


@pytest.mark.parametrize("lens", [Lens.from_toml(SIM_LENS), synthetic_lens()], ids=["sim", "synth"])
def test_scalar_conversions_are_bit_identical_to_scipy_pchip(lens: Lens) -> None:
    # The scalar evaluator replaces SciPy's per-call cost; it must not move a value by one bit.
    counts = np.asarray(lens.focus_counts, dtype=np.float64)
    v = np.asarray(lens.focus_v_mm, dtype=np.float64)
    order = np.argsort(v)
    to_v = PchipInterpolator(counts, v, extrapolate=False)
    to_counts = PchipInterpolator(v[order], counts[order], extrapolate=False)
    rng = np.random.default_rng(7)
    lo, hi = lens.counts_range
    cs = np.concatenate([counts, rng.uniform(lo, hi, 3000), [lo - 10.0, hi + 10.0]])
    for c in cs:
        assert lens.v_from_counts(float(c)) == float(to_v(min(max(c, lo), hi)))
    vmin, vmax = lens.v_range_mm
    for vv in np.concatenate([v, rng.uniform(vmin, vmax, 3000), [vmin - 0.1, vmax + 0.1]]):
        exact = float(to_counts(min(max(vv, vmin), vmax)))
        assert lens.counts_from_v(float(vv)) == round(exact)
        assert lens._counts_at(min(max(float(vv), vmin), vmax)) == exact  # before rounding
    clipped = np.clip(cs, lo, hi)
    assert np.array_equal(lens.v_from_counts_array(cs), to_v(clipped))


def test_pchip_built_here_equals_scipys_on_random_monotone_tables() -> None:
    # The interpolant is built without SciPy (its import cost a start ~0.4 s of CPU); on tables
    # of 2-12 rows with uneven spacing and either direction (the end-derivative's shape cases
    # included) the values are SciPy's to the bit.
    from dffd.core.lens import _ScalarPchip

    rng = np.random.default_rng(11)
    for _ in range(300):
        n = int(rng.integers(2, 13))
        x = np.cumsum(rng.uniform(0.01, 5.0, n) ** 3)
        y = np.cumsum(rng.uniform(0.001, 1.0, n) ** rng.uniform(0.2, 4.0))
        if rng.random() < 0.5:
            y = -y
        ours = _ScalarPchip(x, y)
        theirs = PchipInterpolator(x, y, extrapolate=False)
        xs = np.concatenate([x, rng.uniform(x[0], x[-1], 50)])
        assert np.array_equal(ours.array(xs), theirs(xs))
        assert all(ours(float(a)) == float(theirs(a)) for a in xs)
        # the derivative (the vertex response's slope, which scales a corrected vertex's σ)
        slope = theirs.derivative()
        assert all(
            ours.derivative(float(a)) == pytest.approx(float(slope(a)), rel=1e-12, abs=1e-15)
            for a in xs
        )
