"""Experiment scripts and validation generators (importable as ``experiments.*`` from the repo root)."""
