"""Shipped configuration files (pipeline YAML, node parameters)."""
