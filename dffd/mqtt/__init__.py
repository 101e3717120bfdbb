"""MQTT interface (design.md §7): payload models, topics, JSON Schemas, the publisher client and
the ``…/cmd`` path."""
