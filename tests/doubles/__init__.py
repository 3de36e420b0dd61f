"""Scripted stand-ins of the services, for tests and benchmarks: real bus servers that answer like the
real services but walk scripted paths, so the gateway and the evaluation runner can be exercised (and
loaded) without the cost of the simulator, the reconstructor and a policy. They live here, not in the
production packages, so no service image ships them."""
