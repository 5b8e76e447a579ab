"""The procedure language (YAML to validated steps) and the planner (steps to timed commands)."""
