"""Lens model: focus counts <-> lens-to-sensor distance v (PCHIP) and the thin-lens depth relation.

One model is built either from a lens table (``dffd/defaults/lenses/*.toml``) or from the ``lens``
block of a recording's ``meta.json`` (design.md §3, §8). Units: millimetres for the lens, metres for
depths handed to the rest of the core.
"""

from __future__ import annotations

import bisect
import math
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

MM_PER_M = 1000.0
# A bracket whose half-width (relative to v) is within this factor of the one a vertex response
# was measured with gets its correction: the burst planner's brackets are all 3 px of outer blur
# (± a few % from the motion compensation and the rolling bracket's drift); the wider ones
# (full-range start-up brackets, a large depth σ) are 1.5-100x wider and have another response.
RESPONSE_WIDTH_TOLERANCE = 1.25


class LensError(ValueError):
    """A lens calibration is missing a field or is not physically valid; the message names it."""


@dataclass(frozen=True, slots=True, eq=False)
class Lens:
    """A calibrated lens at a fixed zoom: focal length, pixel pitch and the focus table."""

    name: str
    focal_length_mm: float
    pixel_pitch_mm: float
    focus_counts: tuple[int, ...]
    focus_v_mm: tuple[float, ...]
    f_number: float | None = None
    zoom_counts: int | None = None
    # Standard error of the table's v (mm) where it was calibrated (`dffd calibrate`'s fit:
    # √((leave-one-out rms² − residual rms²)/2)); 0: not known. A table error is a bias every
    # measurement shares, so it enters the published σ, not the filters (docs/estimation.md §14).
    table_sigma_v_mm: float = 0.0
    # The three-point vertex's response to the true offset, measured by `dffd calibrate` on its
    # sweeps (None: not measured, no correction; docs/estimation.md §21).
    vertex_response: VertexResponse | None = None
    # The same per calibrated depth: (counts, σ of v in mm) rows, the calibration's check at
    # each depth (`dffd calibrate`, `TableCheck`); interpolated between them, held beyond.
    # Empty: ``table_sigma_v_mm`` everywhere (lens files written before it).
    table_sigma_v_at: tuple[tuple[int, float], ...] = ()
    # The PCHIP interpolants (SciPy's ``PchipInterpolator(..., extrapolate=False)``, built and
    # evaluated here with its arithmetic: importing scipy.interpolate cost a start ~0.4 s of
    # CPU, docs/design.md §5.3), evaluated one scalar at a time (the core converts a few values
    # on every frame).
    _v_at: _ScalarPchip = field(init=False, repr=False)
    _counts_at: _ScalarPchip = field(init=False, repr=False)
    # (min, max) of focus_v_mm, computed once: v_range_mm runs several times a frame.
    _v_range: tuple[float, float] = field(init=False, repr=False)
    # table_sigma_v_at as (v_mm, σ) sorted by v, for table_sigma_v_mm_at
    _sigma_v: tuple[tuple[float, ...], tuple[float, ...]] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        _validate(self)
        counts = np.asarray(self.focus_counts, dtype=np.float64)
        v = np.asarray(self.focus_v_mm, dtype=np.float64)
        order = np.argsort(v)
        object.__setattr__(self, "_v_at", _ScalarPchip(counts, v))
        object.__setattr__(self, "_counts_at", _ScalarPchip(v[order], counts[order]))
        object.__setattr__(self, "_v_range", (min(self.focus_v_mm), max(self.focus_v_mm)))
        rows = sorted((self._v_at(c), s) for c, s in self.table_sigma_v_at)
        object.__setattr__(self, "_sigma_v", (tuple(r[0] for r in rows), tuple(r[1] for r in rows)))

    # -- construction -----------------------------------------------------------------------
    @classmethod
    def from_toml(cls, path: str | Path) -> Lens:
        """Load ``[lens]`` from a calibration TOML file."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except OSError as exc:
            raise LensError(f"cannot read lens file {path}: {exc}; check the path") from exc
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise LensError(f"lens file {path} is not valid TOML: {exc}") from exc
        block = data.get("lens")
        if not isinstance(block, dict):
            raise LensError(f"lens file {path} has no [lens] table")
        return cls.from_meta(block, source=str(path))

    @classmethod
    def from_meta(cls, meta: Mapping[str, Any], source: str = "lens block") -> Lens:
        """Build from a mapping with ``focal_length_mm``, ``pixel_pitch_mm``, ``focus_table``."""
        if not isinstance(meta, Mapping):
            raise LensError(
                f"{source}: expected a table with focal_length_mm, pixel_pitch_mm and "
                f"focus_table (got {type(meta).__name__})"
            )
        table = meta.get("focus_table")
        if not isinstance(table, Sequence) or isinstance(table, str) or len(table) < 2:
            raise LensError(
                f"{source}: focus_table must be a list of at least two [counts, v_mm] pairs"
            )
        counts: list[int] = []
        vs: list[float] = []
        for i, row in enumerate(table):
            if not isinstance(row, Sequence) or isinstance(row, str) or len(row) != 2:
                raise LensError(f"{source}: focus_table[{i}] must be a [counts, v_mm] pair")
            c, v = row
            counts.append(_integer(c, f"focus_table[{i}] counts", source))
            vs.append(_number(v, f"focus_table[{i}] v_mm", source))
        f_number = meta.get("f_number")
        zoom = meta.get("zoom_counts")
        table_sigma = meta.get("table_sigma_v_mm")
        response = meta.get("vertex_response")
        sigma_rows = meta.get("table_sigma_v_at", ())
        if not isinstance(sigma_rows, Sequence) or isinstance(sigma_rows, str):
            raise LensError(f"{source}: table_sigma_v_at must be a list of [counts, sigma_v_mm]")
        at: list[tuple[int, float]] = []
        for i, row in enumerate(sigma_rows):
            if not isinstance(row, Sequence) or isinstance(row, str) or len(row) != 2:
                raise LensError(f"{source}: table_sigma_v_at[{i}] must be a [counts, sigma_v_mm]")
            at.append(
                (
                    _integer(row[0], f"table_sigma_v_at[{i}] counts", source),
                    _number(row[1], f"table_sigma_v_at[{i}] sigma_v_mm", source),
                )
            )
        return cls(
            name=str(meta.get("name", "unnamed")),
            focal_length_mm=_number(meta.get("focal_length_mm"), "focal_length_mm", source),
            pixel_pitch_mm=_number(meta.get("pixel_pitch_mm"), "pixel_pitch_mm", source),
            focus_counts=tuple(counts),
            focus_v_mm=tuple(vs),
            f_number=None if f_number is None else _number(f_number, "f_number", source),
            zoom_counts=None if zoom is None else _integer(zoom, "zoom_counts", source),
            table_sigma_v_mm=(
                0.0 if table_sigma is None else _number(table_sigma, "table_sigma_v_mm", source)
            ),
            vertex_response=(
                None if response is None else VertexResponse.from_meta(response, source)
            ),
            table_sigma_v_at=tuple(at),
        )

    def to_meta(self) -> dict[str, Any]:
        """The ``lens`` block of a recording's ``meta.json`` (round-trips through from_meta)."""
        meta: dict[str, Any] = {
            "name": self.name,
            "focal_length_mm": self.focal_length_mm,
            "pixel_pitch_mm": self.pixel_pitch_mm,
            "focus_table": [
                [c, v] for c, v in zip(self.focus_counts, self.focus_v_mm, strict=True)
            ],
        }
        if self.f_number is not None:
            meta["f_number"] = self.f_number
        if self.zoom_counts is not None:
            meta["zoom_counts"] = self.zoom_counts
        if self.table_sigma_v_mm > 0:
            meta["table_sigma_v_mm"] = self.table_sigma_v_mm
        if self.vertex_response is not None:
            meta["vertex_response"] = self.vertex_response.to_meta()
        if self.table_sigma_v_at:
            meta["table_sigma_v_at"] = [[c, s] for c, s in self.table_sigma_v_at]
        return meta

    def table_sigma_v_mm_at(self, v_mm: float) -> float:
        """The table's own standard error of v (mm) at ``v_mm``: the per-depth rows
        interpolated (held beyond the calibrated depths), else the one ``table_sigma_v_mm``."""
        vs, sigmas = self._sigma_v
        if not vs:
            return self.table_sigma_v_mm
        # bisect, not np.interp: this runs for every estimator on every frame
        i = bisect.bisect_left(vs, v_mm)
        if i == 0:
            return sigmas[0]
        if i == len(vs):
            return sigmas[-1]
        w = (v_mm - vs[i - 1]) / (vs[i] - vs[i - 1])
        return sigmas[i - 1] + w * (sigmas[i] - sigmas[i - 1])

    # -- derived quantities -----------------------------------------------------------------
    @property
    def focal_length_px(self) -> float:
        """Focal length in pixels."""
        return self.focal_length_mm / self.pixel_pitch_mm

    @property
    def counts_range(self) -> tuple[int, int]:
        """(min, max) focus counts covered by the table."""
        return self.focus_counts[0], self.focus_counts[-1]

    @property
    def v_range_mm(self) -> tuple[float, float]:
        """(min, max) lens-to-sensor distance covered by the table."""
        return self._v_range

    @property
    def depth_range_m(self) -> tuple[float, float]:
        """(nearest, farthest) depth in focus somewhere in the table (farthest may be inf)."""
        vmin, vmax = self.v_range_mm
        return self.depth_from_v(vmax), self.depth_from_v(vmin)

    # -- conversions ------------------------------------------------------------------------
    def v_from_counts(self, counts: float) -> float:
        """Lens-to-sensor distance (mm) at ``counts``; clamps to the table range."""
        lo, hi = self.counts_range
        return self._v_at(min(max(float(counts), lo), hi))

    def v_from_counts_array(self, counts: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Vectorised :meth:`v_from_counts`."""
        lo, hi = self.counts_range
        c = np.clip(np.asarray(counts, dtype=np.float64), lo, hi)
        return self._v_at.array(c)

    def counts_from_v(self, v_mm: float) -> int:
        """Nearest focus counts (rounded) for ``v_mm``; clamps to the table range."""
        vmin, vmax = self.v_range_mm
        return round(self._counts_at(min(max(v_mm, vmin), vmax)))

    def depth_from_v(self, v_mm: float) -> float:
        """Thin lens (1): depth z (m) in focus at lens-to-sensor distance ``v_mm``."""
        f = self.focal_length_mm
        if v_mm <= f:
            return math.inf
        return f * v_mm / (v_mm - f) / MM_PER_M

    def v_from_depth(self, z_m: float) -> float:
        """Thin lens (1) inverted: v (mm) that focuses depth ``z_m``."""
        f = self.focal_length_mm
        z = z_m * MM_PER_M
        if not z > f:
            raise ValueError(f"depth {z_m} m is inside the focal length; cannot be in focus")
        return f * z / (z - f)

    def counts_for_depth(self, z_m: float) -> int:
        """Focus counts that focus depth ``z_m`` (clamped to the table)."""
        return self.counts_from_v(self.v_from_depth(z_m))

    def dz_dv(self, v_mm: float) -> float:
        """dz/dv in metres per millimetre at ``v_mm`` (negative: larger v, nearer target)."""
        f = self.focal_length_mm
        return -(f * f) / (v_mm - f) ** 2 / MM_PER_M

    def blur_radius_px(self, v0_mm: float, v_mm: float, f_number: float) -> float:
        """Blur-circle radius (px) for setting ``v0`` when ``v`` is sharp (design.md §3)."""
        aperture = self.focal_length_mm / f_number
        return 0.5 * aperture * abs(v0_mm - v_mm) / v_mm / self.pixel_pitch_mm


@dataclass(frozen=True, slots=True, eq=False)
class VertexResponse:
    """The burst fit's vertex against the true offset, measured by the calibration (§21).

    For bracket centres ``c`` around the closed loop's fixed point ``v*`` of each calibration
    sweep, the three-point vertex ``v̂(c)`` the estimator fits on the smoothed sweep:
    ``fitted_h = (v̂ − c)/h`` against ``true_h = (v* − c)/h`` (both in half-brackets h, pooled
    over the depths), for the focus ``measure`` and the bracket half-width ``half_width_rel``
    (h / v) it was measured with. Inverted at run time (:meth:`correct`), it maps a burst's
    fitted offset to the true one: slope 1 across the bracket whatever the PSF, and the fixed
    point (the table's) unchanged, since ``fitted_h`` is 0 at ``true_h`` 0.
    """

    measure: str
    half_width_rel: float
    true_h: tuple[float, ...]  # increasing, 0 among them
    fitted_h: tuple[float, ...]  # strictly increasing
    depth_spread_h: float = 0.0  # rms spread of the depths' responses about the pooled one
    n_depths: int = 0
    _inverse: _ScalarPchip = field(init=False, repr=False)

    def __post_init__(self) -> None:
        src = "vertex_response"
        t, f = np.asarray(self.true_h, dtype=np.float64), np.asarray(self.fitted_h, np.float64)
        if len(t) != len(f) or len(t) < 3:
            raise LensError(f"{src}: true_h and fitted_h need the same length, at least 3")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(f))):
            raise LensError(f"{src}: true_h and fitted_h must be finite")
        if np.any(np.diff(t) <= 0) or np.any(np.diff(f) <= 0):
            raise LensError(f"{src}: true_h and fitted_h must be strictly increasing")
        if not self.half_width_rel > 0:
            raise LensError(f"{src}: half_width_rel must be > 0 (got {self.half_width_rel})")
        object.__setattr__(self, "_inverse", _ScalarPchip(f, t))

    @classmethod
    def from_meta(cls, meta: object, source: str = "lens block") -> VertexResponse:
        """From the ``vertex_response`` table of a lens file or a recording's lens block."""
        src = f"{source}: vertex_response"
        if not isinstance(meta, Mapping):
            raise LensError(f"{src} must be a table (measure, half_width_rel, true_h, fitted_h)")

        def floats(key: str) -> tuple[float, ...]:
            values = meta.get(key)
            if not isinstance(values, Sequence) or isinstance(values, str):
                raise LensError(f"{src}.{key} must be a list of numbers")
            return tuple(_number(x, f"vertex_response.{key}[{i}]", source) for i, x in
                         enumerate(values))  # fmt: skip

        n_depths = meta.get("n_depths", 0)
        return cls(
            measure=str(meta.get("measure", "")),
            half_width_rel=_number(
                meta.get("half_width_rel"), "vertex_response.half_width_rel", source
            ),
            true_h=floats("true_h"),
            fitted_h=floats("fitted_h"),
            depth_spread_h=_number(meta.get("depth_spread_h", 0.0), "depth_spread_h", source),
            n_depths=_integer(n_depths, "vertex_response.n_depths", source),
        )

    def to_meta(self) -> dict[str, Any]:
        """The ``vertex_response`` table (round-trips through :meth:`from_meta`)."""
        return {
            "measure": self.measure,
            "half_width_rel": self.half_width_rel,
            "true_h": list(self.true_h),
            "fitted_h": list(self.fitted_h),
            "depth_spread_h": self.depth_spread_h,
            "n_depths": self.n_depths,
        }

    def applies(self, half_width_mm: float, mid_mm: float) -> bool:
        """Whether a bracket of half-width ``half_width_mm`` at ``mid_mm`` is the kind measured
        (within RESPONSE_WIDTH_TOLERANCE of ``half_width_rel``): a wider bracket (the first,
        full-range ones; a large σ) has another response."""
        if not (half_width_mm > 0 and mid_mm > 0):
            return False
        ratio = half_width_mm / mid_mm / self.half_width_rel
        return 1.0 / RESPONSE_WIDTH_TOLERANCE <= ratio <= RESPONSE_WIDTH_TOLERANCE

    def correct(self, fitted_h: float) -> tuple[float, float]:
        """(true offset, d true / d fitted) for a fitted offset, both in half-brackets. Beyond
        the measured range the end segment's chord continues (a straight line)."""
        f, t = self.fitted_h, self.true_h
        if fitted_h < f[0]:
            slope = (t[1] - t[0]) / (f[1] - f[0])
            return t[0] + slope * (fitted_h - f[0]), slope
        if fitted_h > f[-1]:
            slope = (t[-1] - t[-2]) / (f[-1] - f[-2])
            return t[-1] + slope * (fitted_h - f[-1]), slope
        return self._inverse(fitted_h), self._inverse.derivative(fitted_h)


class _ScalarPchip:
    """SciPy's ``PchipInterpolator(x, y, extrapolate=False)``, built and evaluated in Python.

    The coefficients are SciPy's (:func:`_pchip_coefficients`); a value has the arithmetic of
    ``scipy.interpolate.PPoly.__call__`` (interval ``x_i <= x < x_{i+1}``, the last one closed;
    ``Σ_k c[K−1−k] s^k`` accumulated from the constant term with ``s = x − x_i``; NaN outside),
    so the values are bit-identical (tests/test_core_lens.py) at a few percent of its per-call
    cost.
    """

    __slots__ = ("_c", "_coeffs", "_x", "_xa")

    def __init__(self, x: npt.NDArray[np.float64], y: npt.NDArray[np.float64]) -> None:
        c = _pchip_coefficients(x, y)
        self._xa = np.asarray(x, dtype=np.float64)
        self._c = c
        self._x: list[float] = [float(b) for b in x]
        # Per interval, the coefficients from the constant term up.
        self._coeffs = [[float(k) for k in c[::-1, i]] for i in range(c.shape[1])]

    def array(self, xv: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """Vectorised ``__call__`` (the same operations element by element)."""
        x, c = self._xa, self._c
        xv = np.asarray(xv, dtype=np.float64)
        i = np.clip(np.searchsorted(x, xv, side="right") - 1, 0, len(x) - 2)
        s = xv - x[i]
        z = 1.0 * s
        res = (0.0 + c[3, i] * 1.0) + c[2, i] * z
        z = z * s
        res = res + c[1, i] * z
        res = res + c[0, i] * (z * s)
        return np.where((xv >= x[0]) & (xv <= x[-1]), res, np.nan)

    def __call__(self, xval: float) -> float:
        x = self._x
        if not x[0] <= xval <= x[-1]:
            return math.nan
        i = min(bisect.bisect_right(x, xval) - 1, len(x) - 2)
        s = xval - x[i]
        coeffs = self._coeffs[i]
        if len(coeffs) == 4:  # PCHIP's cubics: the loop below unrolled, the same operations
            c0, c1, c2, c3 = coeffs
            z = 1.0 * s
            res = (0.0 + c0 * 1.0) + c1 * z
            z = z * s
            res = res + c2 * z
            return res + c3 * (z * s)
        res = 0.0
        z = 1.0
        last = len(coeffs) - 1
        for k, c in enumerate(coeffs):
            res = res + c * z
            if k < last:
                z *= s
        return res

    def derivative(self, xval: float) -> float:
        """The first derivative at ``xval`` (the same intervals; NaN outside)."""
        x = self._x
        if not x[0] <= xval <= x[-1]:
            return math.nan
        i = min(bisect.bisect_right(x, xval) - 1, len(x) - 2)
        s = xval - x[i]
        coeffs = self._coeffs[i]
        res = 0.0
        z = 1.0
        for k in range(1, len(coeffs)):
            res = res + k * coeffs[k] * z
            z *= s
        return res


def _pchip_coefficients(
    x: npt.NDArray[np.float64], y: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """The cubic coefficients (4, n−1), highest power first, of SciPy's PCHIP through (x, y):
    ``PchipInterpolator._find_derivatives`` then ``CubicHermiteSpline``, the same operations.
    ``x`` strictly increasing, n >= 2."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    hk = x[1:] - x[:-1]
    mk = (y[1:] - y[:-1]) / hk
    if len(y) == 2:  # two points: linear
        dk = np.array([mk[0], mk[0]])
    else:
        smk = np.sign(mk)
        condition = (smk[1:] != smk[:-1]) | (mk[1:] == 0) | (mk[:-1] == 0)
        w1 = 2 * hk[1:] + hk[:-1]
        w2 = hk[1:] + 2 * hk[:-1]
        with np.errstate(divide="ignore", invalid="ignore"):
            whmean = (w1 / mk[:-1] + w2 / mk[1:]) / (w1 + w2)
        dk = np.zeros_like(y)
        dk[1:-1][~condition] = 1.0 / whmean[~condition]
        dk[0] = _pchip_edge(hk[0], hk[1], mk[0], mk[1])
        dk[-1] = _pchip_edge(hk[-1], hk[-2], mk[-1], mk[-2])
    dx = np.diff(x)
    slope = np.diff(y) / dx
    t = (dk[:-1] + dk[1:] - 2 * slope) / dx
    return np.stack((t / dx, (slope - dk[:-1]) / dx - t, dk[:-1], y[:-1]))


def _pchip_edge(h0: float, h1: float, m0: float, m1: float) -> float:
    """SciPy's one-sided three-point end derivative, shape-preserving (``_edge_case``)."""
    d = ((2 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
    if np.sign(d) != np.sign(m0):
        return 0.0
    if np.sign(m0) != np.sign(m1) and abs(d) > 3.0 * abs(m0):
        return 3.0 * m0
    return float(d)


def _number(value: object, name: str, source: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise LensError(f"{source}: {name} is missing or not a number (got {value!r})")
    out = float(value)
    if not math.isfinite(out):
        raise LensError(f"{source}: {name} must be finite (got {value!r})")
    return out


def _integer(value: object, name: str, source: str) -> int:
    number = _number(value, name, source)
    if number != int(number):
        raise LensError(f"{source}: {name} must be an integer (got {value!r})")
    return int(number)


def _validate(lens: Lens) -> None:
    src = f"lens {lens.name!r}"
    if lens.focal_length_mm <= 0:
        raise LensError(f"{src}: focal_length_mm must be > 0 (got {lens.focal_length_mm})")
    if lens.pixel_pitch_mm <= 0:
        raise LensError(f"{src}: pixel_pitch_mm must be > 0 (got {lens.pixel_pitch_mm})")
    if not lens.table_sigma_v_mm >= 0:
        raise LensError(f"{src}: table_sigma_v_mm must be >= 0 (got {lens.table_sigma_v_mm})")
    for c, s in lens.table_sigma_v_at:
        if not s >= 0:
            raise LensError(f"{src}: table_sigma_v_at's sigma_v_mm must be >= 0 (got {s})")
        if not min(lens.focus_counts) <= c <= max(lens.focus_counts):
            raise LensError(f"{src}: table_sigma_v_at's counts {c} are outside the focus_table")
    if lens.f_number is not None and lens.f_number <= 0:
        raise LensError(f"{src}: f_number must be > 0 (got {lens.f_number})")
    if len(lens.focus_counts) != len(lens.focus_v_mm) or len(lens.focus_counts) < 2:
        raise LensError(f"{src}: focus_table needs at least two [counts, v_mm] rows")
    counts = np.asarray(lens.focus_counts)
    v = np.asarray(lens.focus_v_mm)
    if np.any(np.diff(counts) <= 0):
        raise LensError(f"{src}: focus_table counts must be strictly increasing")
    dv = np.diff(v)
    if not (np.all(dv > 0) or np.all(dv < 0)):
        raise LensError(f"{src}: focus_table v_mm must be strictly monotone in counts")
    # v == f is the infinity setting (the far end of real tables); v < f is not physical.
    if np.any(v < lens.focal_length_mm):
        raise LensError(
            f"{src}: focus_table v_mm must be >= focal_length_mm "
            f"({lens.focal_length_mm}); a setting with v < f focuses beyond infinity"
        )
