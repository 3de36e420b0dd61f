"""In-process tools that span services (a simulator, the mapper and the reconstructor in one process), for
pictures of the whole pipeline. A service's own ``tools/`` use only that service; what needs several lives
here, like ``bench/``, so no service imports another service's core."""
