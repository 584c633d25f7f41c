# One image for every capvector service: the CLI, the Prefect server and the deployment server.
FROM python:3.11-slim

# Offscreen MuJoCo rendering on Mesa (EGL/OSMesa); make + git for the set-up commands.
RUN apt-get update \
 && apt-get install -y --no-install-recommends libegl1 libgl1-mesa-dri libosmesa6 make git \
 && rm -rf /var/lib/apt/lists/*

WORKDIR /app
COPY pyproject.toml README.md Makefile ./
COPY capvector_core ./capvector_core
COPY capvector_stats ./capvector_stats
COPY artifacts ./artifacts
COPY tasks ./tasks
COPY flows ./flows
COPY capvector ./capvector
# CPU build of torch first (the same pin as the project), then the project. As in the Makefile:
# `--build-arg TORCH_INDEX=` takes torch from PyPI alone (the CUDA build on Linux).
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
RUN pip install --no-cache-dir --no-deps ${TORCH_INDEX:+--extra-index-url "$TORCH_INDEX"} torch==2.13.0 \
 && pip install --no-cache-dir torch==2.13.0 \
 && pip install --no-cache-dir .

ENV MUJOCO_GL=egl \
    PYOPENGL_PLATFORM=egl \
    PREFECT_SERVER_ANALYTICS_ENABLED=false \
    DO_NOT_TRACK=1 \
    CAPVECTOR_HOME=/data/capvector

VOLUME ["/data"]
ENTRYPOINT []
CMD ["capvector", "--help"]
