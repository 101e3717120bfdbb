"""Estimation core: pure, synchronous, deterministic. No I/O in here."""
