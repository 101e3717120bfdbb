"""The daemon's asyncio shell: app, embedded broker, durable log, systemd notification."""
