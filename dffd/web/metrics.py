"""Prometheus metrics of one daemon (prometheus-client), served at ``/metrics``.

Two kinds: histograms the daemon feeds as things happen (:meth:`Metrics.observe_publish_latency`,
:meth:`Metrics.observe_frame_cpu`), and everything else read from the daemon's
:class:`~dffd.web.interface.Snapshot` at scrape time, so a scrape always agrees with the
``…/status`` payload. Each :class:`Metrics` has its own registry (no process-global state).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Final

from prometheus_client import CollectorRegistry, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from prometheus_client.registry import Collector

from dffd.web.interface import Snapshot

CONTENT_TYPE: Final = CONTENT_TYPE_LATEST

# Exposure → publish: the design budget is p50 ≤ 10 ms, p99 ≤ 30 ms to the subscriber; buckets
# resolve that range finely and still catch a stalled loop (seconds).
LATENCY_BUCKETS_S: Final = (
    0.002, 0.005, 0.0075, 0.01, 0.015, 0.02, 0.03, 0.05, 0.075, 0.1, 0.25, 0.5, 1.0, 2.5,
)  # fmt: skip
# Core CPU per frame: ~0.3–1 ms when tracking with the numba kernels, a few ms for a whole-frame
# search, tens of ms means the estimator cannot keep up with 30 fps.
CPU_BUCKETS_S: Final = (
    0.0002, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.033, 0.05, 0.1,
)  # fmt: skip

STATES: Final = ("idle", "acquiring", "tracking", "lost")


class Metrics:
    """The registry of one daemon; ``render()`` is the body of a ``/metrics`` response."""

    def __init__(self, snapshot: Callable[[], Snapshot | None]) -> None:
        self.registry = CollectorRegistry()
        self.publish_latency = Histogram(
            "dffd_publish_latency_seconds",
            "Frame exposure to estimate handed to MQTT, seconds",
            buckets=LATENCY_BUCKETS_S,
            registry=self.registry,
        )
        self.frame_cpu = Histogram(
            "dffd_core_cpu_seconds",
            "Estimator thread CPU time per processed frame, seconds",
            buckets=CPU_BUCKETS_S,
            registry=self.registry,
        )
        self.registry.register(_SnapshotCollector(snapshot))

    def observe_publish_latency(self, seconds: float) -> None:
        """One estimate published ``seconds`` after its frame's exposure."""
        self.publish_latency.observe(max(0.0, seconds))

    def observe_frame_cpu(self, seconds: float) -> None:
        """The estimator spent ``seconds`` of thread CPU time on one frame."""
        self.frame_cpu.observe(max(0.0, seconds))

    def render(self) -> bytes:
        """The text exposition format (``Content-Type``: :data:`CONTENT_TYPE`)."""
        return generate_latest(self.registry)


class _SnapshotCollector(Collector):
    """Gauges and counters read from the daemon's snapshot at scrape time."""

    def __init__(self, snapshot: Callable[[], Snapshot | None]) -> None:
        self._snapshot = snapshot

    def describe(self) -> Iterable[Metric]:
        # Nothing up front: the families depend on a snapshot that may not exist yet.
        return []

    def collect(self) -> Iterable[Metric]:
        snap = self._snapshot()
        if snap is None:
            return []
        st = snap.status
        out: list[Metric] = []

        def gauge(name: str, doc: str, value: float | None) -> None:
            if value is not None:
                out.append(GaugeMetricFamily(name, doc, value=value))

        def counter(name: str, doc: str, value: float) -> None:
            out.append(CounterMetricFamily(name, doc, value=value))

        state = GaugeMetricFamily(
            "dffd_state", "1 for the current tracking state", labels=["state"]
        )
        for name in STATES:
            state.add_metric([name], 1.0 if st.state == name else 0.0)
        out.append(state)
        search = st.search
        gauge(
            "dffd_search_sweeping",
            "1 while pan/tilt sweeps its range for a target automatic acquisition cannot see",
            1.0 if search is not None and search.phase == "sweeping" else 0.0,
        )
        gauge(
            "dffd_last_estimate_age_seconds",
            "Age of the last published estimate (absent when there is none)",
            snap.last_estimate_age_s,
        )
        if st.rates is not None:
            r = st.rates
            gauge("dffd_frame_rate_hz", "Frames captured per second", r.frame_hz)
            gauge("dffd_estimate_rate_hz", "Estimates published per second", r.estimate_hz)
            gauge("dffd_depth_rate_hz", "Depth measurements (bursts) per second", r.depth_hz)
            gauge(
                "dffd_depth_rate_limit_hz",
                "Theoretical depth-measurement rate of this configuration",
                r.depth_limit_hz,
            )
        bursts = CounterMetricFamily(
            "dffd_bursts", "Focus bursts fitted, by outcome", labels=["outcome"]
        )
        bursts.add_metric(["accepted"], snap.bursts_accepted)
        bursts.add_metric(["rejected"], snap.bursts_rejected)
        out.append(bursts)
        if st.link is not None:
            ln = st.link
            gauge("dffd_link_connected", "1 while the VISCA link is up", float(ln.connected))
            counter("dffd_link_errors", "VISCA error replies", ln.errors)
            counter("dffd_link_timeouts", "VISCA commands that timed out", ln.timeouts)
            counter("dffd_link_reconnects", "VISCA link reconnects", ln.reconnects)
            counter("dffd_link_replies", "VISCA replies received", ln.replies)
            if ln.ip_retransmits is not None:
                counter(
                    "dffd_link_ip_retransmits", "VISCA-over-IP datagrams resent", ln.ip_retransmits
                )
                counter(
                    "dffd_link_ip_sequence_errors",
                    "VISCA-over-IP sequence errors reported by the camera",
                    ln.ip_sequence_errors or 0,
                )
                counter("dffd_link_ip_resets", "VISCA-over-IP sequence RESETs", ln.ip_resets or 0)
            gauge(
                "dffd_link_last_reply_age_seconds",
                "Time since the last VISCA reply",
                ln.last_reply_age_s,
            )
        if st.video is not None:
            vd = st.video
            gauge("dffd_video_connected", "1 while the video stream is up", float(vd.connected))
            counter("dffd_video_reconnects", "Video stream losses reopened", vd.reconnects)
        if st.mqtt is not None:
            mq = st.mqtt
            gauge("dffd_mqtt_connected", "1 while connected to the broker", float(mq.connected))
            gauge(
                "dffd_mqtt_backlog_messages", "Messages waiting in the outage backlog", mq.backlog
            )
            counter("dffd_mqtt_reconnects", "MQTT reconnects", mq.reconnects)
            counter("dffd_mqtt_published", "MQTT messages handed to the broker", mq.published)
        if st.drops is not None:
            drops = CounterMetricFamily(
                "dffd_dropped", "Items dropped by the bounded queues", labels=["queue"]
            )
            d = st.drops
            for queue, value in (
                ("frames", d.frames),
                ("publish_queue", d.publish_queue),
                ("backlog", d.backlog),
                ("log", d.log),
            ):
                drops.add_metric([queue], value)
            out.append(drops)
        return out
