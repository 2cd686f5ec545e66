"""edgerecon's queue side: the job contract (``contract``), the job store and the worker registry in
Redis (``store``, ``registry``), the rq job (``job``) and the worker process that runs it
(``process``), with the one configuration (``settings``). It uses ``core`` and never ``service``.
"""
