"""Simulated cage behind real wire protocols. Imports neither rig nor drivers."""
