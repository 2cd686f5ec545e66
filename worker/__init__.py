"""edgerecon's worker: the rq job (``worker.jobs``) and the worker process that runs it (``worker.main``)."""
