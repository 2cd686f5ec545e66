"""edgerecon's fitting core: reading clouds, parameters, the network, losses, the fit, extraction.

Importing this package, ``core.ply`` or ``core.params`` does not import torch, so the API process
can validate uploads without it. The fit itself lives in ``core.fit`` (the loop), ``core.losses``
(the three loss terms) and ``core.network`` (the MLP with its exact derivatives); ``core.reconstruct``
ties fit and extraction together.
"""
