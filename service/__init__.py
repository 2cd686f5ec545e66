"""edgerecon's front ends: the HTTP API (``service.app``), the command line (``service.cli``) and
``edgerecon serve`` (``service.serve``). They use ``worker``'s contract and store; nothing imports them.
"""
