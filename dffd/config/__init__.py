"""Typed configuration: pydantic models loaded from TOML with ``DFFD_<SECTION>__<KEY>`` overrides.

:func:`load_config` is the only way the rest of the service gets its settings (see
``docs/design.md`` for the sections); a bad file raises :class:`ConfigError` naming each bad
field by its dotted path (``mqtt.url``) and what is allowed; environment variables win over the
file (``DFFD_MQTT__URL=mqtt://127.0.0.1:18883``); :func:`problems` lists what else would stop
``dffd run`` (missing files, devices) — the truth ``dffd check-config`` reports.

Modules: ``models`` (the sections), ``loading`` (TOML + environment + paths), ``explain`` (the
error explainer), ``check`` (check-config and the pre-start checks).
"""

from __future__ import annotations

from dffd.config.check import check_run_config, missing_devices, problems
from dffd.config.explain import ConfigError
from dffd.config.loading import load_config
from dffd.config.models import (
    ENV_PREFIX,
    CameraSection,
    CaptureSection,
    DffdConfig,
    EstimatorsSection,
    LensSection,
    LogSection,
    MqttEndpoint,
    MqttSection,
    SchedulerSection,
    SimSection,
    TargetSection,
    WebSection,
)

__all__ = [
    "ENV_PREFIX",
    "CameraSection",
    "CaptureSection",
    "ConfigError",
    "DffdConfig",
    "EstimatorsSection",
    "LensSection",
    "LogSection",
    "MqttEndpoint",
    "MqttSection",
    "SchedulerSection",
    "SimSection",
    "TargetSection",
    "WebSection",
    "check_run_config",
    "load_config",
    "missing_devices",
    "problems",
]
