"""Focus-measure validation on the simulator: fitted vertex against the true offset (issue 11.2).

``python -m hil.bench_focus [--models reference,aberrated] [--depths 2.5,4,5.5] [--repeats 5]
[--calibration DIR]``

For a static target at depth z, three-setting brackets (half-width h: 3 px of outer blur, as the
burst planner) are centred at v + δ for δ across [−h, h]; every frame is rendered, tracked by the
contour and scored by each focus measure; the three costs give the vertex (fit_burst). Reported per
optics model and measure: the slope of (v̂ − v_c) against (v − v_c) (least squares over δ and
repeats) and the vertex noise (std of v̂ over noise repeats at each δ, pooled), in units of h.

``fixed_point_h`` is where the closed loop settles: the true offset δ* at which the mean fitted
offset crosses zero (linear interpolation between the two δ around the crossing). A burst whose
vertex lands on its own bracket centre is re-planned there, so a static target's estimate sits
−δ* h from the true sharp setting in v (docs/estimation.md §13): a lean that only a calibration
using this same three-point fit can absorb.

With ``--calibration DIR`` each optics model's lens is calibrated as the bench does
(:func:`hil.calibration.calibrated_lens`, paper-circle's camera, seed 1, cached in DIR) and the
measure it was calibrated with is also reported *corrected* by the table's vertex response
(``<measure>+response``: :func:`dffd.core.focus.fit_burst` with ``response``, docs/estimation.md
§21). Its offsets are from the calibration's fixed point, which the table maps to the true
depth: its intercept is the lean the table absorbs, its slope should be 1 across the bracket.
``local_slope`` is the slope over the offsets within ± 0.3 h (where the closed loop's bursts
are), ``slope`` over all of them; ``noise_centre_h`` the vertex noise within ± CENTRE_H.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

import dffd.core.contour as contour_mod
from dffd.core.acquisition import find_target
from dffd.core.contour import ContourTracker, TrackerConfig
from dffd.core.focus import fit_burst, frame_cost
from dffd.core.lens import Lens, VertexResponse
from drivers.sim.config import load_sim_camera_config, with_overrides
from drivers.sim.resources import reference_camera_file
from drivers.sim.source import SimFrameSource, camera_state_for

# debiased_peak: its frame cost is the edge moment on the wider window it debiases the peak
# gradient against (focus.DEBIAS_WINDOW_SIGMAS); the debiased peak settles where that moment does
MEASURES = ("peak_gradient", "edge_variance", "debiased_peak")
EXTRA: dict[str, object] = {}
# Offsets (h) where a closed loop's bursts are: the vertex noise there is reported apart
# (noise_centre_h), since a response's inverse slope is < 1 there and > 1 near the ends.
CENTRE_H = 0.15


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def sim_renderer(
    model: str, z: float, shape: str, seed: int
) -> tuple[Callable[[float, int], np.ndarray], float, float, Lens]:
    """(render(v0_mm, repeat) -> gray, v_true, h, lens) for a static target on a sim model."""
    cfg = load_sim_camera_config(reference_camera_file())
    cfg = with_overrides(
        cfg,
        {
            "optics.model": model,
            "world.target.shape": shape,
            "world.trajectory.position_m": (0.03, -0.02, z),
            "lens.focus_jitter_counts": 0.0,
            "seed": seed,
            **EXTRA,
        },
    )
    clock = _Clock()
    state = camera_state_for(cfg, clock=clock)
    src = SimFrameSource.from_config(cfg, state)
    optics = src.optics
    zoom = cfg.zoom_counts
    v_true = optics.sharp_v_mm(z, zoom)
    f = optics.focal_length_mm(zoom)
    n_f = optics.f_number(zoom)
    h = 3.0 * optics.pixel_pitch_mm * n_f * 2.0 * v_true / f
    lens = Lens(
        name="bench",
        focal_length_mm=f,
        pixel_pitch_mm=optics.pixel_pitch_mm,
        focus_counts=(0, 1),
        focus_v_mm=(f, f + 5.0),
        f_number=n_f,
    )
    counter = [0]

    def render(v0: float, repeat: int) -> np.ndarray:
        power = (1.0 / f - 1.0 / v0) * 1000.0
        state.focus.jump(optics.focus_counts_for_depth(1.0 / power), clock.t)
        counter[0] += 1
        frame = src.render_frame(counter[0] + 100000 * repeat)
        return frame.image

    return render, v_true, h, lens


def measure(
    render: Callable[[float, int], np.ndarray],
    v_true: float,
    h: float,
    lens: Lens,
    *,
    deltas: Sequence[float],
    repeats: int,
    response: VertexResponse | None = None,
) -> dict[str, dict[str, float]]:
    """Slope and noise of the vertex for each measure (and ``<measure>+response`` corrected by
    ``response`` for its measure)."""
    tracker = ContourTracker(TrackerConfig())
    names = [*MEASURES, *([f"{response.measure}+response"] if response is not None else [])]
    offsets: dict[str, list[tuple[float, float, int]]] = {m: [] for m in names}
    for rep in range(repeats):
        for delta in deltas:
            v_c = v_true - delta * h  # true offset of the vertex from the bracket centre: +δ h
            costs: dict[str, list[tuple[float, float]]] = {m: [] for m in MEASURES}
            for x in (-1.0, 0.0, 1.0):
                gray = render(v_c + x * h, rep)
                pts = find_target(gray)
                assert pts is not None
                assert tracker.start(gray, pts, 0.0)
                obs = tracker.update(gray, 0.0, "similarity")
                for m in MEASURES:
                    # None: the blur overflows the moment's window on the normal lines
                    c = frame_cost(obs, m)  # type: ignore[arg-type]
                    costs[m].append((math.nan, math.nan) if c is None else c)
            for m in MEASURES:
                if any(math.isnan(c[0]) for c in costs[m]):
                    offsets[m].append((delta, math.nan, rep))  # counted as rejected
                    continue
                corrected = [None] if response is None or m != response.measure else [
                    None, response]  # fmt: skip
                for r in corrected:
                    fit = fit_burst(
                        [v_c - h, v_c, v_c + h],
                        [c[0] for c in costs[m]],
                        [c[1] for c in costs[m]],
                        lens,
                        response=r,
                    )
                    name = m if r is None else f"{m}+response"
                    offsets[name].append(
                        (delta, (fit.v_hat_mm - v_c) / h if fit.accepted else math.nan, rep)
                    )
    out = {}
    for m in names:
        arr = np.array(offsets[m])
        bad = int(np.sum(~np.isfinite(arr[:, 1])))
        arr = arr[np.isfinite(arr[:, 1])]
        slope, icpt = np.polyfit(arr[:, 0], arr[:, 1], 1)
        near = np.abs(arr[:, 0]) <= 0.3 + 1e-9
        local = (
            float(np.polyfit(arr[near, 0], arr[near, 1], 1)[0])
            if len(np.unique(arr[near, 0])) > 1
            else math.nan
        )
        noise, centre = [], []
        for delta in deltas:
            sel = arr[arr[:, 0] == delta, 1]
            if len(sel) > 1:
                noise.append(np.var(sel, ddof=1))
                if abs(delta) <= CENTRE_H:
                    centre.append(noise[-1])
        out[m] = {
            "fixed_point_h": fixed_point(arr[:, 0], arr[:, 1]),
            "slope": float(slope),
            "local_slope": local,
            "intercept_h": float(icpt),
            "noise_h": float(math.sqrt(np.mean(noise))) if noise else math.nan,
            "noise_centre_h": float(math.sqrt(np.mean(centre))) if centre else math.nan,
            "max_dev_h": float(np.max(np.abs(arr[:, 1] - arr[:, 0]))),
            "rejected": bad,
        }
    return out


def calibrated_response(model: str, cache_dir: Path) -> VertexResponse | None:
    """The vertex response of the table the bench calibrates for this optics model (the
    paper-circle scenario's camera, seed 1; cached in ``cache_dir``)."""
    from hil.calibration import calibrated_lens
    from hil.scenario import OPTICS_MODELS, load_scenario

    if model not in OPTICS_MODELS:
        raise SystemExit(f"unknown optics model {model!r}: one of {', '.join(OPTICS_MODELS)}")
    scenario = load_scenario("paper-circle").with_optics(model)  # type: ignore[arg-type]
    calibration = calibrated_lens(scenario, 1, cache_dir)
    return Lens.from_toml(calibration.lens_path).vertex_response


def fixed_point(delta: np.ndarray, x_hat: np.ndarray) -> float:
    """True offset δ* (h) where the mean fitted offset crosses zero; NaN without a crossing."""
    ds = np.unique(delta)
    means = np.array([float(np.mean(x_hat[delta == d])) for d in ds])
    for i in range(len(ds) - 1):
        a, b = means[i], means[i + 1]
        if a == 0.0:
            return float(ds[i])
        if a * b < 0.0:
            return float(ds[i] + (ds[i + 1] - ds[i]) * a / (a - b))
    return float(ds[-1]) if means[-1] == 0.0 else math.nan


def main() -> None:
    """Print slope, intercept, vertex noise and worst deviation per model, depth and measure."""
    parser = argparse.ArgumentParser(prog="python -m hil.bench_focus", description=__doc__)
    parser.add_argument("--models", default="reference,aberrated")
    parser.add_argument("--depths", default="3,6,9")
    parser.add_argument("--shape", default="disc")
    parser.add_argument("--k", type=float, default=None, help="window in edge spreads (tuning)")
    parser.add_argument(
        "--override",
        action="append",
        default=[],
        help="simulator KEY=VALUE, e.g. lens.psf=gaussian",
    )
    parser.add_argument("--repeats", type=int, default=4)
    parser.add_argument("--deltas", default="-0.9,-0.6,-0.3,0,0.3,0.6,0.9")
    parser.add_argument(
        "--calibration",
        default=None,
        help="directory of the bench's calibrated tables (made if missing): report the "
        "calibrated measure corrected by its vertex response too",
    )
    parser.add_argument(
        "--lens",
        action="append",
        default=[],
        help="MODEL=FILE: take that optics model's vertex response from a lens file instead",
    )
    args = parser.parse_args()
    deltas = [float(d) for d in args.deltas.split(",")]
    if args.k is not None:
        contour_mod.EDGE_WINDOW_SIGMAS = args.k
    extra = {}
    for item in args.override:
        key, value = item.split("=", 1)
        extra[key] = json.loads(value) if value[:1] in "[{0123456789-." else value
    EXTRA.clear()
    EXTRA.update(extra)
    results = {}
    for model in args.models.split(","):
        files = dict(item.split("=", 1) for item in args.lens)
        response = (
            Lens.from_toml(files[model]).vertex_response
            if model in files
            else None
            if args.calibration is None
            else calibrated_response(model, Path(args.calibration))
        )
        for z in (float(x) for x in args.depths.split(",")):
            t0 = time.perf_counter()
            render, v_true, h, lens = sim_renderer(model, z, args.shape, 0)
            r = measure(
                render, v_true, h, lens, deltas=deltas, repeats=args.repeats, response=response
            )
            results[f"{model} z={z}"] = r
            for m, v in r.items():
                print(
                    f"{model:9s} z={z:4.1f} {m:24s} slope {v['slope']:.3f} "
                    f"local {v['local_slope']:.3f} centre noise {v['noise_centre_h']:.4f} h "
                    f"icpt {v['intercept_h']:+.3f} h  noise {v['noise_h']:.4f} h  "
                    f"maxdev {v['max_dev_h']:.3f} h  fixed point {v['fixed_point_h']:+.3f} h  "
                    f"rejected {v['rejected']}",
                    flush=True,
                )
            print(f"  ({time.perf_counter() - t0:.1f} s)", flush=True)
    print(json.dumps(results))


if __name__ == "__main__":
    main()
