"""edgerecon's fitting core: reading clouds, parameters, the network, losses, the fit, extraction.

It knows nothing of HTTP, queues or Redis, and imports nothing of ``worker``, ``service`` or
``evaluation``. Importing this package, ``core.ply``, ``core.params``, ``core.progress`` or
``core.outputs`` does not import torch, so the API process can validate uploads without it. The fit
itself lives in ``core.fit`` (the loop), ``core.losses`` (the loss terms) and ``core.network`` (the
MLP with its exact derivatives); ``core.reconstruct`` ties fit and extraction together, and
``core.runtime`` holds what is process-wide (threads, compiled kernels, malloc tuning).
"""
