"""Pieces the shape functions share (one place, not one copy per folder)."""
