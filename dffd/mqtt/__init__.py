"""MQTT interface (design.md §7): payload models, topics, JSON Schemas and the publisher client."""
