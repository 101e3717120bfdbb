"""The rigs ``dffd calibrate``'s procedure runs on: the simulated camera and the real camera.

:class:`SimRig` (``--sim``) renders the simulated camera in lock-step virtual time with a static
target at the depth placed (a depth placed again is rendered frames further on: new sensor
noise) and says at which depths its target fits the tracker. :class:`LabRig` (``--config``)
drives the VISCA camera on ``camera.port``, reads the frames of ``capture.device`` (or
``capture.url``) and asks the operator at the terminal to place the target
(:mod:`dffd.calibrate_operator`); its optics are ``lens.file``'s, or the packaged default lens's
while that file does not exist yet. Both are a :class:`dffd.calibrate_procedure.Rig`.

Split from :mod:`dffd.calibrate` (the command).
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from dffd.calibrate_operator import ask_operator
from dffd.calibrate_procedure import Image
from dffd.calibrate_types import CalibrationError
from dffd.config import DffdConfig
from dffd.core.contour import TrackerConfig
from dffd.core.lens import MM_PER_M, Lens, LensError
from dffd.resources import DEFAULT_LENS, lens_table

# The contour must fit the tracker's radius range with room to spare: at most this fraction of
# TrackerConfig.max_radius_px (its normals search ±search_px beyond the edge, and a target that
# nearly fills the frame leaves the background too little area for the threshold), at least
# MIN_RADIUS_MARGIN × min_radius_px (a few-pixel blob gives a noisy focus cost).
MAX_RADIUS_FRACTION = 0.9
MIN_RADIUS_MARGIN = 1.5
DEPTH_STEP_M = 0.1  # a default depth the target is too large at moves out to a multiple of this
# Camera initialisation (the D100 takes ~10 s from standby, docs/design.md §6) and one focus move.
CAMERA_INIT_TIMEOUT_S = 30.0
# A frame must arrive within this time from a V4L2 device (30 fps; a grabber may stall ~1 s).
FRAME_TIMEOUT_S = 2.0

# The simulated camera keeps running between placements: a depth placed again is rendered from
# this many frames further on (new sensor noise; a sweep is ~250 frames).
SIM_REPEAT_FRAMES = 100_000


class SimRig:
    """The simulated camera in lock-step virtual time, a static target at a chosen depth."""

    def __init__(self, sim_config: Path | Any) -> None:
        """``sim_config``: a simulated-camera config file, or a loaded ``SimCameraConfig`` (the
        bench calibrates its sessions' own camera)."""
        from drivers.sim.config import load_sim_camera_config
        from drivers.sim.optics import Optics

        self.config = (
            load_sim_camera_config(sim_config) if isinstance(sim_config, Path) else sim_config
        )
        optics = Optics.from_config(self.config)
        lens = Lens.from_meta(_lens_meta(optics, self.config.zoom_counts))
        self.focal_length_mm = lens.focal_length_mm
        self.pixel_pitch_mm = lens.pixel_pitch_mm
        self.f_number: float | None = optics.f_number(self.config.zoom_counts)
        self.zoom_counts: int | None = self.config.zoom_counts
        self.focus_range = (
            int(self.config.lens.focus_far_counts),
            int(self.config.lens.focus_near_counts),
        )
        self._frame = 0  # frame index of the next render
        self._rig: Any = None  # drivers.sim.rig.SimCamera of the current target placement
        self._z_m = 3.0
        self._placed: dict[float, int] = {}  # placements so far per depth

    def radius_px(self, z_m: float) -> float:
        """The simulated target's image size r = f R / z (pixels) at ``z_m``."""
        image_mm = self.focal_length_mm * self.config.world.target.size_m / z_m
        return image_mm / self.pixel_pitch_mm

    def why_unusable(self, z_m: float) -> str | None:
        """Why the simulated target cannot be calibrated on at ``z_m`` (None: it can)."""
        limits = TrackerConfig()
        near = self.config.lens.near_focus_m
        r = self.radius_px(z_m)
        if z_m < near:
            return f"{z_m:g} m is nearer than the lens focuses ({near:g} m)"
        if r > MAX_RADIUS_FRACTION * limits.max_radius_px:
            return (
                f"at {z_m:g} m the simulated {self.config.world.target.size_m * MM_PER_M:g} mm "
                f"target is {r:.0f} px in radius, more than the tracker takes with margin "
                f"({MAX_RADIUS_FRACTION * limits.max_radius_px:.0f} px)"
            )
        if r < MIN_RADIUS_MARGIN * limits.min_radius_px:
            return f"at {z_m:g} m the simulated target is only {r:.1f} px in radius"
        return None

    def usable_depths(self, wanted: tuple[float, ...]) -> list[float]:
        """``wanted``, each depth nearer than the target fits moved out to the first usable
        multiple of :data:`DEPTH_STEP_M`, and depths where it is too small dropped."""
        limits = TrackerConfig()
        size_mm = self.config.world.target.size_m * MM_PER_M
        largest_px = MAX_RADIUS_FRACTION * limits.max_radius_px
        # r = f R / (z p) <= largest_px, and the lens focuses no nearer than near_focus_m.
        nearest = max(
            self.config.lens.near_focus_m,
            self.focal_length_mm * size_mm / (largest_px * self.pixel_pitch_mm) / MM_PER_M,
        )
        nearest = math.ceil(nearest / DEPTH_STEP_M - 1e-9) * DEPTH_STEP_M
        moved = {round(max(z, nearest), 6) for z in wanted}
        return sorted(z for z in moved if self.why_unusable(z) is None)

    async def place_target(self, z_m: float) -> None:
        """A fresh simulated session with the target at ``z_m`` (placed again: frames further
        on, new sensor noise)."""
        self._z_m = z_m
        self._rig = None
        self._placed[z_m] = self._placed.get(z_m, 0) + 1

    async def frame_at(self, counts: int, settle_frames: int) -> Image:
        """The lens is at ``counts`` well before the next exposure (virtual time: no wait)."""
        # One turn of the event loop a setting: nothing here waits, and Ctrl-C (asyncio.run
        # cancels the main task) would otherwise reach the procedure only once it had ended.
        await asyncio.sleep(0)
        source, state = self._session()
        k = self._frame
        t = source.frame_time(k)
        state.focus.jump(float(counts), t - 1.0)
        return self._render(k)

    async def step_focus(self, counts: int) -> float:
        """Move the lens at once, between the two exposures around the last delivery time."""
        source, state = self._session()
        now = source.delivery_time(self._frame - 1)
        period = 1.0 / source.fps
        exposed = (now - source.frame_time(0)) // period  # last exposure mid before now
        t_cmd = source.frame_time(int(exposed)) + 0.5 * period
        state.focus.jump(float(counts), t_cmd)
        return float(t_cmd)

    async def next_frame(self) -> tuple[Image, float]:
        """The next frame in sequence and its delivery time."""
        source, _ = self._session()
        k = self._frame
        return self._render(k), float(source.delivery_time(k))

    def _render(self, k: int) -> Image:
        source, _ = self._session()
        self._frame = k + 1
        # Render once the exposure is well over (the frames come in order: time never goes back).
        self._rig.virtual_clock.set(source.frame_time(k) + 1.0)
        image = source.render_frame(k).image
        gray: Image = image if image.ndim == 2 else image[..., 1]
        return gray

    def _session(self) -> tuple[Any, Any]:
        if self._rig is None:
            from drivers.sim.config import with_overrides
            from drivers.sim.rig import build_sim_camera

            cfg = with_overrides(
                self.config,
                {"world.trajectory": {"kind": "static", "position_m": (0.0, 0.0, self._z_m)}},
            )
            self._rig = build_sim_camera(cfg, virtual_start_s=0.0, t0=1.0)
            self._frame = SIM_REPEAT_FRAMES * (self._placed.get(self._z_m, 1) - 1)
        return self._rig.source, self._rig.state


class LabRig:
    """The real camera: VISCA on ``camera.port``, frames from ``capture.device``, an operator."""

    def __init__(
        self, config: DffdConfig, prompt: Callable[[str], Awaitable[None]] | None = None
    ) -> None:
        from drivers.visca.camera import profile_for

        if config.camera.driver != "visca" or config.capture.source not in ("v4l2", "stream"):
            raise CalibrationError(
                "the lab procedure needs camera.driver = 'visca' with camera.port, and "
                "capture.source = 'v4l2' with capture.device (or 'stream' with capture.url); "
                "use --sim for the simulator"
            )
        # lens.file's optics are reused (f is fixed at a fixed zoom); calibrate writes that file,
        # so it need not exist yet: the packaged default lens's optics then, with a note.
        self.optics_note: str | None = None
        try:
            lens = Lens.from_toml(config.lens.file)
        except LensError as exc:
            lens = Lens.from_toml(lens_table(DEFAULT_LENS))
            self.optics_note = _default_optics_note(config, lens, exc)
        self.config = config
        self.profile = profile_for(config.camera.model)
        self.focal_length_mm = lens.focal_length_mm
        self.pixel_pitch_mm = lens.pixel_pitch_mm
        self.f_number = lens.f_number
        self.zoom_counts = (
            config.lens.zoom_counts if config.lens.zoom_counts is not None else lens.zoom_counts
        )
        self.focus_range = self.profile.focus_range
        self._prompt = prompt or ask_operator
        self._camera: Any = None
        self._source: Any = None
        self._pending: asyncio.Task[None] | None = None

    async def __aenter__(self) -> LabRig:
        """Open the link and the device, initialise the camera (manual focus, the zoom)."""
        from drivers.capture import CaptureSettings, OpenCVFrameSource
        from drivers.visca.camera import Camera
        from drivers.visca.link import ViscaLink

        cfg = self.config
        assert cfg.camera.port is not None  # validated with driver = 'visca'
        self._link = ViscaLink(cfg.camera.port, cfg.camera.baudrate)
        await self._link.__aenter__()
        self._camera = Camera(self._link, cfg.camera.address, self.profile)
        async with asyncio.timeout(CAMERA_INIT_TIMEOUT_S):
            await self._camera.initialize()
            if self.zoom_counts is not None:
                await self._camera.zoom_direct(self.zoom_counts)
        # latency_s = 0: frame.t is the delivery (read) time, the clock of step_focus.
        if cfg.capture.source == "stream":
            from drivers.stream import StreamFrameSource, StreamSettings

            assert cfg.capture.url is not None  # validated with source = 'stream'
            self._source = StreamFrameSource(
                StreamSettings(cfg.capture.url, fps=cfg.capture.fps, timestamps="arrival")
            )
        else:
            assert cfg.capture.device is not None  # validated with source = 'v4l2'
            settings = CaptureSettings(
                device=cfg.capture.device, width=cfg.capture.width, height=cfg.capture.height,
                fps=cfg.capture.fps, fourcc=cfg.capture.fourcc, latency_s=0.0,
            )  # fmt: skip
            self._source = OpenCVFrameSource(settings)
        await self._source.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        """Close the device and the link."""
        if self._pending is not None:
            self._pending.cancel()
        if self._source is not None:
            await self._source.close()
        await self._link.__aexit__(None, None, None)

    async def place_target(self, z_m: float) -> None:
        """Ask the operator to place the target and wait for Enter (InputEndedError: Ctrl-D)."""
        await self._prompt(
            f"Place the target {z_m:g} m from the camera on the optical axis, then press Enter: "
        )

    async def frame_at(self, counts: int, settle_frames: int) -> Image:
        """Focus Direct, wait for Completion, skip the frames that may predate it."""
        await self._finish_pending()
        await self._camera.focus_direct(counts)
        done = time.monotonic()
        wait = settle_frames / self.config.capture.fps
        while True:
            image, delivered = await self.next_frame()
            if delivered >= done + wait:
                return image

    async def step_focus(self, counts: int) -> float:
        """Write Focus Direct now; its Completion is awaited before the next move."""
        await self._finish_pending()
        handle = await self._camera.start_focus_direct(counts)
        t = time.monotonic()
        self._pending = asyncio.ensure_future(_completion(handle))
        return t

    async def next_frame(self) -> tuple[Image, float]:
        """The next frame from the device (gray) and its read time."""
        async with asyncio.timeout(FRAME_TIMEOUT_S):
            frame = await self._source.next_frame()
        image: Image = frame.image if frame.image.ndim == 2 else frame.image[..., 1]
        return image, float(frame.t)

    async def _finish_pending(self) -> None:
        if self._pending is not None:
            task, self._pending = self._pending, None
            await task


# -- private helpers --------------------------------------------------------------------------
def _default_optics_note(config: DffdConfig, lens: Lens, exc: LensError) -> str:
    """What the lab procedure starts from when ``lens.file`` cannot be read."""
    file = config.lens.file
    why = (
        f"lens.file {file} does not exist yet (this calibration writes its table)"
        if not file.exists()
        else f"lens.file: {exc}"
    )
    optics = f"focal_length_mm {lens.focal_length_mm:g}, pixel_pitch_mm {lens.pixel_pitch_mm:g}"
    if lens.f_number is not None:
        optics += f", f_number {lens.f_number:g}"
    if config.lens.zoom_counts is None and lens.zoom_counts is not None:
        optics += f", zoom_counts {lens.zoom_counts}"
    return (
        f"{why}; using the optics of the packaged lens {lens.name}: {optics}. The table "
        "written carries them: check them against your camera (f at the zoom used) and grabber; "
        "to start from others, name a lens file with them for this run (DFFD_LENS__FILE=FILE)"
    )


async def _completion(handle: Any) -> None:
    await handle.completed()


def _lens_meta(optics: object, zoom_counts: int) -> dict[str, object]:
    import tomllib

    text = optics.lens_table_toml(zoom_counts)  # type: ignore[attr-defined]
    data = tomllib.loads(text)["lens"]
    return {k: data[k] for k in ("name", "focal_length_mm", "pixel_pitch_mm", "focus_table")}


__all__ = ["LabRig", "SimRig"]
