# edgerecon: one image for the API and the workers (docker-compose.yml runs both from it).
#   docker build -t edgerecon .
#   API:    docker run -e REDIS_URL=redis://host:6379/0 -p 8000:8000 edgerecon
#   worker: docker run -e REDIS_URL=redis://host:6379/0 edgerecon edgerecon worker
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# torch.compile turns the network's element-wise kernels into C++; without a compiler the
# workers fall back to eager kernels (slower steps).
RUN apt-get update \
    && apt-get install -y --no-install-recommends g++ \
    && rm -rf /var/lib/apt/lists/*

# CPU-only torch first, from PyTorch's CPU index (the PyPI wheel for Linux pulls gigabytes of
# CUDA libraries); `pip install .` below finds the pinned version already satisfied.
RUN pip install --index-url https://download.pytorch.org/whl/cpu torch==2.13.0

WORKDIR /app
COPY pyproject.toml README.md ./
COPY core core
COPY service service
COPY worker worker
COPY evaluation evaluation
RUN pip install .

RUN useradd --create-home --uid 10001 edgerecon
USER edgerecon
# torch.compile's cache of compiled kernels: docker-compose.yml mounts a volume here so that
# restarted workers skip most of the compile time.
ENV TORCHINDUCTOR_CACHE_DIR=/home/edgerecon/.cache/torchinductor
RUN mkdir -p "$TORCHINDUCTOR_CACHE_DIR"
# Compile the kernels now, into the image (and into a new inductor-cache volume, which Docker fills
# from it): a new container's first fit then loads them in about 5 s instead of compiling them for
# 25-45 s (when it runs on the kind of CPU the image was built on: the cache is per instruction
# set). The worker's own warm-up: two-step fits of a tiny cloud and the first steps of default fits,
# one of each network a job may train (worker/process.py: warm_kernels).
RUN python -c "from core.runtime import configure; configure(compile=True); \
from worker.process import warm_kernels; warm_kernels()"

EXPOSE 8000
# Healthy when the API answers and Redis with it (/healthz is 503 while Redis is down).
HEALTHCHECK --interval=30s --timeout=5s --start-period=20s --retries=3 \
    CMD ["python", "-c", "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4)"]
CMD ["uvicorn", "service.app:app", "--host", "0.0.0.0", "--port", "8000", "--no-access-log"]
