"""What a procedure will achieve, known before it runs: the sigma of every parameter each
calibrate step will report, what limits it, and whether the acceptance criteria can pass."""
