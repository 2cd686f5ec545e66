"""edgerecon's front ends: the HTTP API (``service.app``) and the command line (``service.cli``)."""
