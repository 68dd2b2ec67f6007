"""Grasp synthesis: wrench quality and the Q-distance LP (host, XLA, Pallas), the energy, Adam, the batched
descent (Algorithm 1), samplers, filters, device sharding and the pipeline `grasp.synthesize`."""
