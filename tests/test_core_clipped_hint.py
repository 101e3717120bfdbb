"""The cut-off-target hint on a textured wall: texture is not a target, and a hint tests itself.

A textured background breaks under Otsu's threshold into blobs, and some that reach the frame's
edge are convex. These tests show that such blobs are not reported (they do not stand out of
the texture around them); that a high-contrast blob that is no target (a speck on the wall)
is chased once, rejected when its direction comes into full view without an acquisition, and
never chased again; that the hint gives up after ``MAX_TRIES`` blobs (handing over to the
search sweep); and that the real target is then acquired.
"""

from __future__ import annotations

import itertools
import math

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from dffd.config import DffdConfig
from dffd.core.clipped import MAX_TRIES, TRY_TIMEOUT_S, VERIFY_FRAMES, ClippedHint
from dffd.core.pipeline import Pipeline
from dffd.core.synthetic import render_disc, synthetic_lens
from dffd.core.types import FrameTag
from dffd.scheduler import search_views
from dffd.wiring import pipeline_config
from drivers.frames import Frame

SERVICE = pipeline_config(DffdConfig())
LENS = synthetic_lens()
FOCAL_PX = LENS.focal_length_mm / LENS.pixel_pitch_mm
W, H = 640, 480
FPS = 30.0
TRACK_COUNTS = LENS.counts_for_depth(4.0)

# The wall: band-limited noise of the aberrated optics' kind (mean 40 DN, σ ≈ 4.5 DN, a grain
# of a few pixels), over pan ±PAN_SPAN_DEG and tilt ±TILT_SPAN_DEG; px per degree on it.
PAN_SPAN_DEG = 12.0
TILT_SPAN_DEG = 4.0
PX_PER_DEG = FOCAL_PX * math.pi / 180.0
WALL_SEED = 7
# The target, a high-contrast disc out of the first view (its half-width is 3.3°).
TARGET_DEG = (6.5, 0.5)
TARGET_RADIUS_PX = 40.0
# The head in the closed loop: it turns to the reported point at most this fast (deg/frame).
HEAD_STEP_DEG = 0.4
# Specks on the wall: high-contrast dots too small to be a target when whole (π 5.5² < π 6²,
# the tracker's smallest), on a grid this far apart (deg), jittered by the seed.
SPECK_RADIUS_PX = 5.5
SPECK_STEP_DEG = 0.7


class _Wall:
    """A static scene in pan/tilt directions: the view is the window at the head's direction."""

    def __init__(
        self, seed: int, target: tuple[float, float] | None = TARGET_DEG, *, specks: bool = True
    ) -> None:
        rng = np.random.default_rng(seed)
        pw = int(2 * PAN_SPAN_DEG * PX_PER_DEG) + W
        ph = int(2 * TILT_SPAN_DEG * PX_PER_DEG) + H
        noise = cv2.GaussianBlur(rng.normal(0.0, 1.0, (ph, pw)).astype(np.float32), (0, 0), 3.0)
        wall = 40.0 + 4.5 * noise / float(noise.std())
        self.ox = PAN_SPAN_DEG * PX_PER_DEG + (W - 1) / 2.0  # pano pixel of direction (0, 0)
        self.oy = TILT_SPAN_DEG * PX_PER_DEG + (H - 1) / 2.0
        ys, xs = np.mgrid[0:ph, 0:pw].astype(np.float32)
        dots: list[tuple[float, float, float, float]] = []  # x, y, radius, level
        if specks:
            step = SPECK_STEP_DEG * PX_PER_DEG
            for gy in np.arange(step / 2, ph, step):
                for gx in np.arange(step / 2, pw, step):
                    jx, jy = rng.uniform(-0.4 * step, 0.4 * step, 2)
                    dots.append((gx + jx, gy + jy, SPECK_RADIUS_PX, 110.0))
        if target is not None:
            tx, ty = self.ox + target[0] * PX_PER_DEG, self.oy - target[1] * PX_PER_DEG
            dots.append((tx, ty, TARGET_RADIUS_PX, 150.0))
        for x, y, radius, level in dots:
            x0, x1 = max(int(x - radius - 2), 0), min(int(x + radius + 3), pw)
            y0, y1 = max(int(y - radius - 2), 0), min(int(y + radius + 3), ph)
            d = np.hypot(xs[y0:y1, x0:x1] - x, ys[y0:y1, x0:x1] - y)
            cover = np.clip(radius - d + 0.5, 0.0, 1.0)
            wall[y0:y1, x0:x1] = wall[y0:y1, x0:x1] * (1.0 - cover) + level * cover
        self.pano = wall.astype(np.float32)
        self._noise = np.random.default_rng(seed + 1)

    def view(self, pan: float, tilt: float) -> npt.NDArray[np.uint8]:
        x0 = self.ox + pan * PX_PER_DEG - (W - 1) / 2.0
        y0 = self.oy - tilt * PX_PER_DEG - (H - 1) / 2.0
        shift = np.float32([[1.0, 0.0, -x0], [0.0, 1.0, -y0]])
        img = cv2.warpAffine(self.pano, shift, (W, H), flags=cv2.INTER_LINEAR)
        img = img + self._noise.normal(0.0, 1.0, img.shape).astype(np.float32)
        return np.clip(img + 0.5, 0, 255).astype(np.uint8)

    def image_of(
        self, direction: tuple[float, float], pan: float, tilt: float
    ) -> tuple[float, float]:
        """The image point of ``direction`` in the view at (``pan``, ``tilt``)."""
        return (
            (W - 1) / 2.0 + (direction[0] - pan) * PX_PER_DEG,
            (H - 1) / 2.0 - (direction[1] - tilt) * PX_PER_DEG,
        )


def _direction(point: tuple[float, float], pan: float, tilt: float) -> tuple[float, float]:
    return (
        pan + math.degrees(math.atan2(point[0] - (W - 1) / 2.0, FOCAL_PX)),
        tilt + math.degrees(math.atan2((H - 1) / 2.0 - point[1], FOCAL_PX)),
    )


def _toward(here: float, goal: float) -> float:
    return here + max(-HEAD_STEP_DEG, min(HEAD_STEP_DEG, goal - here))


def test_the_texture_of_a_wall_is_not_taken_for_a_cut_off_target() -> None:
    """Otsu's threshold of a textured wall (seed 7, the aberrated optics' kind: σ 4.5 DN, a
    grain of a few pixels) leaves convex caps at the frame's edge; none is reported, for they do
    not stand out of the texture around them. Before, the core reported them and the head spun
    after them (``stop-and-go`` on the aberrated optics: never acquired in 60 s)."""
    wall = _Wall(WALL_SEED, target=None, specks=False)
    pipe = Pipeline(SERVICE, LENS)
    for k, pan in enumerate(np.linspace(-6.0, 6.0, 40)):
        frame = Frame(k, k / FPS, wall.view(float(pan), 0.0))
        out = pipe.process(frame, FrameTag("track", TRACK_COUNTS, float(pan), 0.0, None))
        assert out.candidate_px is None, f"a wall blob reported at pan {pan:+.2f}°"


def test_specks_are_rejected_then_the_sweep_finds_the_target() -> None:
    """Closed loop on the wall with high-contrast specks (seed 7): the head turns to each cut-off
    speck the core reports; none is a target when whole, so each is rejected and never chased
    again, the hint gives up after MAX_TRIES, and the search sweep's views
    (scheduler.search_views) bring the real disc into view, which is acquired. Before: the
    hint chased blobs at the edge for as long as there were any."""
    wall = _Wall(WALL_SEED)
    pipe = Pipeline(SERVICE, LENS)
    pan = tilt = 0.0
    goal = (0.0, 0.0)
    chased: list[tuple[int, tuple[float, float]]] = []  # frame, direction of each reported point
    quiet = 0  # frames since the last reported point
    views: list[tuple[float, float]] = []
    k = 0
    for k in range(600):
        frame = Frame(k, k / FPS, wall.view(pan, tilt))
        out = pipe.process(frame, FrameTag("track", TRACK_COUNTS, pan, tilt, None))
        if out.state == "tracking":
            break
        if out.candidate_px is not None:
            goal = _direction(out.candidate_px, pan, tilt)
            chased.append((k, goal))
            quiet = 0
        else:
            quiet += 1
        if quiet == round(FPS):  # a second without a hint: the sweep (search_after_s, shorter)
            views = search_views((pan, tilt), (-PAN_SPAN_DEG, PAN_SPAN_DEG), (-2.0, 2.0),
                                 (5.3, 4.0))  # fmt: skip
        if views and quiet > round(FPS) and quiet % 15 == 0:
            goal = views.pop(0)  # a dwell of 15 frames per view
        pan, tilt = _toward(pan, goal[0]), _toward(tilt, goal[1])
    assert pipe.state == "tracking", "the disc was never acquired"
    specks = [(i, d) for i, d in chased if _off(d, TARGET_DEG) > 1.0]
    tries = _distinct(specks)
    # The hint gave up after MAX_TRIES specks (each chased once, for at most its timeout)...
    assert len(tries) == MAX_TRIES
    assert len(specks) <= MAX_TRIES * (TRY_TIMEOUT_S * FPS + 1)
    assert all(_off(a, b) > 0.2 for a, b in itertools.combinations(tries, 2))
    # ... long before the sweep brought the disc into view.
    assert specks[-1][0] < k - round(FPS)
    # The tracked contour is the disc (its centroid where the disc is in this view).
    obs = out.observation
    assert obs is not None
    assert obs.ok
    x, y = wall.image_of(TARGET_DEG, pan, tilt)
    assert math.hypot(obs.centroid[0] - x, obs.centroid[1] - y) < 3.0


def test_a_rejected_blob_is_not_chased_again() -> None:
    """A blob turned to that came into view whole and was not taken is rejected; when the head
    turns back and it is cut by the edge again, the hint stays silent about it."""
    wall = _Wall(WALL_SEED, target=None)
    hint = ClippedHint(FOCAL_PX, max_tries=1)
    pan = tilt = 0.0
    point = hint.update(wall.view(pan, tilt), 0.0, pan, tilt)
    assert point is not None
    first = _direction(point, pan, tilt)
    # The head turns so that the blob's direction is at the centre: in full view.
    pan, tilt = first
    for k in range(1, VERIFY_FRAMES + 1):
        hint.update(wall.view(pan, tilt), k / FPS, pan, tilt)
    assert hint.rejected, "in full view and never acquired: rejected"
    assert hint.gave_up
    # Back where it started: the same blob is cut by the edge again, and is not reported.
    assert hint.update(wall.view(0.0, 0.0), 1.0, 0.0, 0.0) is None


def test_a_blob_the_head_never_reaches_is_rejected_after_the_timeout() -> None:
    """A head that does not turn (pan/tilt off, a blob beyond the range): the blob is given
    TRY_TIMEOUT_S, then rejected, and its direction is not chased again."""
    image = render_disc(W, H, (330.0, 462.0), 50.0, 0.5, rng=np.random.default_rng(0))
    hint = ClippedHint(FOCAL_PX)
    reported = [hint.update(image, k / FPS, 0.0, 0.0) for k in range(int(3 * TRY_TIMEOUT_S * FPS))]
    first_gap = next(k for k, p in enumerate(reported) if p is None)
    assert first_gap == pytest.approx(TRY_TIMEOUT_S * FPS, abs=2)
    # One blob, one direction: rejected once, never chased again, and the hint is done.
    assert len(hint.rejected) == 1
    assert all(p is None for p in reported[first_gap:])
    assert hint.tries == 1


def test_release_and_acquire_give_the_hint_a_fresh_start() -> None:
    image = render_disc(W, H, (330.0, 462.0), 50.0, 0.5, rng=np.random.default_rng(0))
    pipe = Pipeline(SERVICE, LENS)
    tag = FrameTag("track", TRACK_COUNTS, 0.0, 0.0, None)
    n = int(TRY_TIMEOUT_S * FPS) + 2
    outs = [pipe.process(Frame(k, k / FPS, image), tag).candidate_px for k in range(n)]
    assert outs[0] is not None
    assert outs[-1] is None  # rejected: the head never turned
    pipe.acquire_auto()
    assert pipe.process(Frame(n, n / FPS, image), tag).candidate_px is not None


def _off(a: tuple[float, float], b: tuple[float, float]) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def _distinct(chased: list[tuple[int, tuple[float, float]]]) -> list[tuple[float, float]]:
    """The directions chased: a report far from the one before starts a new one."""
    runs: list[tuple[float, float]] = []
    last: tuple[float, float] | None = None
    for _, d in chased:
        if last is None or _off(d, last) > 0.5:
            runs.append(d)
        last = d
    return runs
