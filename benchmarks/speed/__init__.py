"""Speed measurements: what an operation, a training step or a start-up costs on this machine."""
