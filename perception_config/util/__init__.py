"""Plumbing with no domain knowledge: atomic files, size-limited JSON, stop signals, Open3D threads,
versioned folders."""
