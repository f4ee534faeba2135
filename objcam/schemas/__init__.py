"""Typed manifests and artifacts exchanged between stages."""
