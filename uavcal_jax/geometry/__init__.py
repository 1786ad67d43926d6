"""Shared geometry: SO(3)/SE(3) helpers, camera model, triangulation."""
