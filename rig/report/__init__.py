"""Human-readable output of results: text tables now, the acceptance report later."""
