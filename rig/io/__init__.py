"""File formats at the rig's boundary (CSV in, JSON and C headers out)."""
