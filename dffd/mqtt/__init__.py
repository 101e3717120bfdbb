"""MQTT interface (DESIGN §6): payload models, topics, JSON Schemas and the publisher client."""
