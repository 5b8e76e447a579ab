"""The cage controller: field commands to safe coil currents, trim, null, characterization."""
