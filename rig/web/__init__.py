"""rig serve: the web page for live runs, past runs and the cage (ADR 0016)."""
