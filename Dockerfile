# One image for every SpatialAnt service; the compose file picks the entry point per container.
#   docker build -t spatialant:latest .
#   docker run --rm spatialant python -m services.renderer --help
# The GPU variants use the same image: torch's CUDA build comes from TORCH_INDEX_URL (see below).
FROM python:3.11-slim

# open3d needs libusb/libGL/libgomp at import time, whatever the service.
RUN apt-get update \
 && apt-get install -y --no-install-recommends libusb-1.0-0 libgl1 libgomp1 \
 && rm -rf /var/lib/apt/lists/*

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    ANT_LOG_JSON=true \
    NUMBA_CACHE_DIR=/tmp/numba

# CPU wheels by default; build the GPU image with
#   docker build --build-arg TORCH_INDEX_URL=https://download.pytorch.org/whl/cu128 -t spatialant:gpu .
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu

WORKDIR /app
# Dependencies first: this layer is rebuilt only when the lock file changes, not on every code edit.
COPY requirements.lock pyproject.toml ./
RUN pip install --extra-index-url "${TORCH_INDEX_URL}" -r requirements.lock

COPY shared ./shared
COPY libs ./libs
COPY services ./services
COPY deploy ./deploy
COPY evaluation ./evaluation
COPY bench ./bench
RUN pip install --no-deps --no-build-isolation -e . \
 && useradd --system --uid 10001 --home /app ant \
 && mkdir -p /data/maps /data/gateway /tmp/numba \
 && chown -R ant /data /tmp/numba

USER ant
# Services are zenoh peers of the router; the gateway also serves HTTP.
EXPOSE 8000
# The healthcheck is per service (compose): python -m deploy.healthcheck <service>
CMD ["python", "-m", "deploy.healthcheck", "--help"]
