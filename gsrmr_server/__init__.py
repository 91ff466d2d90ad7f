"""Server side of gsrmr: scheduling, the Gaussian-splatting engine, the simulated world and the nodes."""
