"""Scene simulator (placeholder until the simphys branch lands its package file)."""
