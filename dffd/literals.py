"""Names shared by the configuration, the scheduler and the MQTT payloads, each defined once.

Pure (typing only), so the core and the scheduler can import it.
"""

from __future__ import annotations

from typing import Literal

__all__ = ["BestEstimator", "BurstMode", "BurstPolicy", "FocusMeasure", "PanTiltMode"]

# The estimators that can be published as ``best`` (the raw measurement cannot).
BestEstimator = Literal["lpv", "kf", "cf2", "cf1"]
# When a burst is due: every N tracking frames, or when the depth's σ grows past a threshold.
BurstPolicy = Literal["every_n", "sigma"]
# rolling: a focus triangle lo, mid, hi, mid, … with a burst at every end; classic: mid → end →
# end → mid per burst (docs/estimation.md).
BurstMode = Literal["rolling", "classic"]
# drive: Pan-tiltDrive speeds; absolute: absolute moves; off: the head stays where it is.
PanTiltMode = Literal["drive", "absolute", "off"]
# The focus measure of a frame: "edge_variance", the second moment of the edge-derivative profile
# (any PSF: blur variances add); "peak_gradient", the paper's 1/mean(max ||∇I||²), a parabola in
# the focus setting only for a Gaussian PSF (docs/estimation.md §8); "debiased_peak", the peak
# gradient's vertex less its bias fitted online against the edge moment's (dffd.core.combine, §12).
FocusMeasure = Literal["edge_variance", "peak_gradient", "debiased_peak"]
