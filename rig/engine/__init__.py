"""The run engine: executes procedure plans on the rig, records everything, safe state on exit."""
