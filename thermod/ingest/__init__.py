"""Footage from other tools → format-v1 recordings."""
